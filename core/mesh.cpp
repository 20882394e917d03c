#include "core/mesh.h"

#include <algorithm>
#include <cmath>

namespace iteas {

int32_t Mesh::add_wedge(int32_t vertex) {
  wedge_vertex.push_back(vertex);
  for (Channel& ch : channels) ch.data.resize(ch.data.size() + ch.components, 0.0f);
  return num_wedges() - 1;
}

int Mesh::find_channel(const std::string& name) const {
  for (size_t i = 0; i < channels.size(); ++i)
    if (channels[i].name == name) return static_cast<int>(i);
  return -1;
}

double Aabb::diagonal() const {
  double s = 0;
  for (int k = 0; k < 3; ++k) s += double(hi[k] - lo[k]) * double(hi[k] - lo[k]);
  return std::sqrt(s);
}

Aabb bounding_box(const Mesh& mesh) {
  Aabb box;
  const int32_t n = mesh.num_vertices();
  if (n == 0) return box;
  for (int k = 0; k < 3; ++k) box.lo[k] = box.hi[k] = mesh.positions[k];
  for (int32_t v = 1; v < n; ++v)
    for (int k = 0; k < 3; ++k) {
      box.lo[k] = std::min(box.lo[k], mesh.positions[3 * v + k]);
      box.hi[k] = std::max(box.hi[k], mesh.positions[3 * v + k]);
    }
  return box;
}

int64_t drop_degenerate_faces(Mesh& mesh) {
  const int32_t nf = mesh.num_faces();
  int32_t out = 0;
  for (int32_t f = 0; f < nf; ++f) {
    const int32_t* v = &mesh.corner_vertex[3 * f];
    if (v[0] == v[1] || v[1] == v[2] || v[2] == v[0]) continue;
    for (int k = 0; k < 3; ++k) {
      mesh.corner_vertex[3 * out + k] = mesh.corner_vertex[3 * f + k];
      if (mesh.has_wedges()) mesh.corner_wedge[3 * out + k] = mesh.corner_wedge[3 * f + k];
    }
    if (!mesh.face_group.empty()) mesh.face_group[out] = mesh.face_group[f];
    ++out;
  }
  mesh.corner_vertex.resize(3 * size_t(out));
  if (mesh.has_wedges()) mesh.corner_wedge.resize(3 * size_t(out));
  if (!mesh.face_group.empty()) mesh.face_group.resize(out);
  return nf - out;
}

void Mesh::materialize() {
  if (!has_wedges()) {
    corner_wedge = corner_vertex;
    wedge_vertex.resize(num_vertices());
    for (int32_t v = 0; v < num_vertices(); ++v) wedge_vertex[v] = v;
  }
  if (face_group.empty()) face_group.assign(num_faces(), 0);
}

void compact(Mesh& mesh) {
  mesh.materialize();
  std::vector<int32_t> vmap(mesh.num_vertices(), -1), wmap(mesh.num_wedges(), -1);
  int32_t nv = 0, nw = 0;
  for (size_t c = 0; c < mesh.corner_vertex.size(); ++c) {
    int32_t& v = mesh.corner_vertex[c];
    if (vmap[v] < 0) vmap[v] = nv++;
    int32_t& w = mesh.corner_wedge[c];
    if (wmap[w] < 0) wmap[w] = nw++;
  }
  // Keep original relative order so that unchanged meshes stay unchanged.
  std::vector<int32_t> vorder, worder;
  vorder.reserve(nv);
  worder.reserve(nw);
  nv = nw = 0;
  for (size_t v = 0; v < vmap.size(); ++v)
    if (vmap[v] >= 0) { vmap[v] = nv++; vorder.push_back(int32_t(v)); }
  for (size_t w = 0; w < wmap.size(); ++w)
    if (wmap[w] >= 0) { wmap[w] = nw++; worder.push_back(int32_t(w)); }
  if (size_t(nv) == vmap.size() && size_t(nw) == wmap.size()) return;
  std::vector<float> pos(3 * size_t(nv));
  for (int32_t i = 0; i < nv; ++i)
    for (int k = 0; k < 3; ++k) pos[3 * i + k] = mesh.positions[3 * size_t(vorder[i]) + k];
  mesh.positions.swap(pos);
  for (VertexChannel& vc : mesh.vertex_channels) {
    std::vector<float> d(3 * size_t(nv));
    for (int32_t i = 0; i < nv; ++i)
      for (int k = 0; k < 3; ++k) d[3 * i + k] = vc.data[3 * size_t(vorder[i]) + k];
    vc.data.swap(d);
  }
  std::vector<int32_t> wv(nw);
  for (int32_t i = 0; i < nw; ++i) wv[i] = vmap[mesh.wedge_vertex[worder[i]]];
  mesh.wedge_vertex.swap(wv);
  for (Channel& ch : mesh.channels) {
    std::vector<float> d(size_t(nw) * ch.components);
    for (int32_t i = 0; i < nw; ++i)
      for (int k = 0; k < ch.components; ++k)
        d[size_t(i) * ch.components + k] = ch.data[size_t(worder[i]) * ch.components + k];
    ch.data.swap(d);
  }
  for (int32_t& v : mesh.corner_vertex) v = vmap[v];
  for (int32_t& w : mesh.corner_wedge) w = wmap[w];
}

}  // namespace iteas
