#include "core/mesh.h"

#include <algorithm>
#include <cmath>
#include <cstdint>

#if defined(__linux__)
#include <sys/mman.h>
#endif

namespace iteas {

void prepare_pages(void* p, size_t bytes) {
#if defined(__linux__)
  constexpr uintptr_t kPage = 4096, kHuge = kHugePageBytes;
  if (bytes < kPrefaultBytes) return;
  const uintptr_t lo = reinterpret_cast<uintptr_t>(p), hi = lo + bytes;
#if defined(MADV_HUGEPAGE)
  // The whole 2 MB stretches of the block (which starts on a 2 MB boundary
  // when it is that large); advice only, errors ignored.
  if (bytes >= kHuge) {
    const uintptr_t b = (lo + kHuge - 1) & ~(kHuge - 1), e = hi & ~(kHuge - 1);
    if (e > b) madvise(reinterpret_cast<void*>(b), e - b, MADV_HUGEPAGE);
  }
#endif
#if defined(MADV_POPULATE_WRITE)
  // Every page of the block will be written: fault them all in with one call
  // instead of one trap per page (Linux 5.14+; older kernels say EINVAL and
  // the pages fault on first write as before).
  // A block the allocator handed back from memory it kept (already resident)
  // is left alone: walking it costs more than it saves.
  const uintptr_t b = (lo + kPage - 1) & ~(kPage - 1), e = hi & ~(kPage - 1);
  if (e <= b) return;
  // One call asks about the last pages: resident there means the block came
  // from memory the allocator kept (heap blocks are carved upwards), fresh
  // means a new mapping or a heap grown for it.
  constexpr uintptr_t kProbe = 64;
  const uintptr_t from = std::max(b, e - kProbe * kPage);
  unsigned char v[kProbe];
  if (mincore(reinterpret_cast<void*>(from), e - from, v) == 0 &&
      std::all_of(v, v + (e - from) / kPage, [](unsigned char x) { return (x & 1) != 0; }))
    return;
  madvise(reinterpret_cast<void*>(b), e - b, MADV_POPULATE_WRITE);
#endif
#else
  (void)p;
  (void)bytes;
#endif
}

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

}  // namespace iteas
