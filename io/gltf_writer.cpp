// glTF 2.0 / GLB writer. For glTF inputs the original JSON is edited in place:
// only the refined TRIANGLES primitives are rewritten; nodes, materials,
// images (as bytes), skins, animations and extras are kept, with accessor and
// bufferView indices remapped after the replaced geometry is dropped.
#include <algorithm>
#include <cmath>
#include <cstring>
#include <set>

#include "core/parallel.h"
#include "io/container.h"
#include "io/document.h"
#include "io/draco_codec.h"
#include "io/pipeline.h"

namespace iteas {
namespace {

using json = nlohmann::json;

constexpr int kFloat = 5126, kU16 = 5123, kU32 = 5125;

const char* type_name(int comps) {
  switch (comps) {
    case 1: return "SCALAR";
    case 2: return "VEC2";
    case 3: return "VEC3";
    default: return "VEC4";
  }
}

std::string base64(const std::vector<uint8_t>& in) {
  static const char* t = "ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
  std::string out;
  out.reserve((in.size() + 2) / 3 * 4);
  size_t i = 0;
  for (; i + 2 < in.size(); i += 3) {
    const uint32_t v = (uint32_t(in[i]) << 16) | (uint32_t(in[i + 1]) << 8) | in[i + 2];
    out += t[v >> 18]; out += t[(v >> 12) & 63]; out += t[(v >> 6) & 63]; out += t[v & 63];
  }
  if (i + 1 == in.size()) {
    const uint32_t v = uint32_t(in[i]) << 16;
    out += t[v >> 18]; out += t[(v >> 12) & 63]; out += "==";
  } else if (i + 2 == in.size()) {
    const uint32_t v = (uint32_t(in[i]) << 16) | (uint32_t(in[i + 1]) << 8);
    out += t[v >> 18]; out += t[(v >> 12) & 63]; out += t[(v >> 6) & 63]; out += '=';
  }
  return out;
}

struct Builder {
  json& j;
  std::vector<uint8_t>& bin;

  int add_view(const void* data, size_t bytes, int target) {
    while (bin.size() % 4) bin.push_back(0);
    const size_t off = bin.size();
    bin.insert(bin.end(), static_cast<const uint8_t*>(data), static_cast<const uint8_t*>(data) + bytes);
    json v = {{"buffer", 0}, {"byteOffset", off}, {"byteLength", bytes}};
    if (target) v["target"] = target;
    j["bufferViews"].push_back(v);
    return int(j["bufferViews"].size()) - 1;
  }
  int add_accessor(json acc) {
    j["accessors"].push_back(std::move(acc));
    return int(j["accessors"].size()) - 1;
  }
  int float_accessor(const std::vector<float>& data, int comps, bool minmax) {
    const int64_t count = int64_t(data.size() / comps);
    json acc = {{"bufferView", add_view(data.data(), data.size() * 4, 34962)},
                {"componentType", kFloat}, {"count", count}, {"type", type_name(comps)}};
    if (minmax) {
      std::vector<float> lo(comps, INFINITY), hi(comps, -INFINITY);
      for (int64_t i = 0; i < count; ++i)
        for (int k = 0; k < comps; ++k) {
          lo[k] = std::min(lo[k], data[size_t(i) * comps + k]);
          hi[k] = std::max(hi[k], data[size_t(i) * comps + k]);
        }
      acc["min"] = lo;
      acc["max"] = hi;
    }
    return add_accessor(std::move(acc));
  }
  int u16_accessor(const std::vector<float>& data, int comps) {
    std::vector<uint16_t> v(data.size());
    for (size_t i = 0; i < data.size(); ++i) v[i] = uint16_t(std::clamp(data[i], 0.0f, 65535.0f));
    return add_accessor({{"bufferView", add_view(v.data(), v.size() * 2, 34962)},
                         {"componentType", kU16}, {"count", data.size() / comps}, {"type", type_name(comps)}});
  }
  int index_accessor(const std::vector<int32_t>& idx, int64_t vertices) {
    if (vertices < 65535) {
      std::vector<uint16_t> v(idx.begin(), idx.end());
      return add_accessor({{"bufferView", add_view(v.data(), v.size() * 2, 34963)},
                           {"componentType", kU16}, {"count", idx.size()}, {"type", "SCALAR"}});
    }
    return add_accessor({{"bufferView", add_view(idx.data(), idx.size() * 4, 34963)},
                         {"componentType", kU32}, {"count", idx.size()}, {"type", "SCALAR"}});
  }
};

// Values cleaned for the validator: unit normals, unit tangents with w = +-1,
// weights summing to one, colours in [0, 1].
void tidy(const Channel& ch, std::vector<float>& v) {
  const int n = ch.components;
  const size_t count = v.size() / n;
  if ((ch.kind == ChannelKind::kNormal || ch.kind == ChannelKind::kTangent) && n >= 3) {
    for (size_t i = 0; i < count; ++i) {
      float* x = &v[i * n];
      const double len = std::sqrt(double(x[0]) * x[0] + double(x[1]) * x[1] + double(x[2]) * x[2]);
      if (len > 0) for (int k = 0; k < 3; ++k) x[k] = float(x[k] / len);
      else { x[0] = 0; x[1] = 0; x[2] = 1; if (ch.kind == ChannelKind::kTangent) { x[0] = 1; x[2] = 0; } }
      if (n == 4) x[3] = x[3] < 0 ? -1.0f : 1.0f;
    }
  } else if (ch.kind == ChannelKind::kWeights) {
    for (size_t i = 0; i < count; ++i) {
      float* x = &v[i * n];
      double s = 0;
      for (int k = 0; k < n; ++k) s += x[k];
      if (s > 0) for (int k = 0; k < n; ++k) x[k] = float(x[k] / s);
    }
  } else if (ch.name.rfind("COLOR_", 0) == 0) {
    for (float& x : v) x = std::clamp(x, 0.0f, 1.0f);
  }
}

bool is_target_channel(const std::string& name) { return name.rfind("target", 0) == 0 && name.find(':') != std::string::npos; }

// One refined primitive's geometry as written: the faces of one group, their
// corners' wedges numbered by first use, the values per vertex; with Draco,
// the payload instead (the arrays freed once encoded).
struct PrimitiveData {
  struct Attr {
    std::string name;
    const Channel* ch;
    std::vector<float> data;
  };
  std::vector<int32_t> idx;
  int64_t nvert = 0, triangles = 0;
  std::vector<float> pos;
  std::vector<Attr> attrs;
  std::vector<std::vector<float>> target_pos;  // per morph target, per vertex
  bool draco = false;
  std::vector<EncodeAttribute> encoded;  // with Draco: what the payload holds (no data pointers)
  EncodeResult enc;
  Status status;
  bool ready = false;
};

void gather_primitive(const MeshSlot& slot, int group, PrimitiveData* d) {
  const Mesh& m = slot.mesh;
  const GroupInfo& gi = slot.groups[group];
  std::vector<int32_t> remap(size_t(m.wedge_count()), -1), order;
  std::vector<int32_t>& idx = d->idx;
  for (int32_t f = 0; f < m.num_faces(); ++f) {
    if (m.group_of(f) != group) continue;
    for (int k = 0; k < 3; ++k) {
      const int32_t w = m.wedge_of(3 * f + k);
      if (remap[w] < 0) { remap[w] = int32_t(order.size()); order.push_back(w); }
      idx.push_back(remap[w]);
    }
  }
  d->triangles = int64_t(idx.size() / 3);
  if (idx.empty()) return;  // nothing left: the caller drops the primitive
  const int64_t nvert = d->nvert = int64_t(order.size());
  auto vertex_of = [&](int32_t w) { return m.has_wedges() ? m.wedge_vertex[w] : w; };
  d->pos.resize(size_t(nvert) * 3);
  for (int64_t i = 0; i < nvert; ++i)
    for (int k = 0; k < 3; ++k) d->pos[size_t(i) * 3 + k] = m.positions[3 * size_t(vertex_of(order[i])) + k];
  for (size_t c = 0; c < m.channels.size(); ++c) {
    if (!gi.has_channel[c]) continue;
    const Channel& ch = m.channels[c];
    PrimitiveData::Attr a{ch.name, &ch, std::vector<float>(size_t(nvert) * ch.components)};
    for (int64_t i = 0; i < nvert; ++i)
      for (int k = 0; k < ch.components; ++k) a.data[size_t(i) * ch.components + k] = ch.data[size_t(order[i]) * ch.components + k];
    if (!is_target_channel(ch.name)) tidy(ch, a.data);
    d->attrs.push_back(std::move(a));
  }
  // Morph targets' positions per vertex (written without Draco).
  if (gi.targets > 0) {
    d->target_pos.resize(size_t(gi.targets));
    for (int t = 0; t < gi.targets; ++t) {
      std::vector<float>& td = d->target_pos[size_t(t)];
      td.resize(size_t(nvert) * 3);
      const std::vector<float>& src = m.vertex_channels[t].data;
      for (int64_t i = 0; i < nvert; ++i)
        for (int k = 0; k < 3; ++k) td[size_t(i) * 3 + k] = src[3 * size_t(vertex_of(order[i])) + k];
    }
  }
}

// Gathers a primitive and, with Draco, encodes it and frees the arrays.
void prepare_primitive(const MeshSlot& slot, int group, const OutputOptions& opt, const float* grid_origin,
                       float grid_range, PrimitiveData* d) {
  gather_primitive(slot, group, d);
  d->ready = true;
  d->draco = opt.draco && slot.groups[group].targets == 0;
  if (!d->draco || d->idx.empty()) return;
  EncodeRequest req;
  req.points = d->nvert;
  req.faces = &d->idx;
  req.attributes.push_back({"POSITION", 3, d->pos.data(), false});
  for (const PrimitiveData::Attr& a : d->attrs)
    if (!is_target_channel(a.name))
      req.attributes.push_back({a.name, a.ch->components, a.data.data(), a.ch->kind == ChannelKind::kJoints});
  req.grid_origin = grid_origin;
  req.grid_range = grid_range;
  d->status = draco_encode(req, opt, &d->enc);
  for (EncodeAttribute& a : req.attributes) a.data = nullptr;
  d->encoded = std::move(req.attributes);
  std::vector<int32_t>().swap(d->idx);
  std::vector<float>().swap(d->pos);
  std::vector<PrimitiveData::Attr>().swap(d->attrs);
}

// Writes the JSON of one refined primitive (geometry only; the caller keeps
// its material and extras) and its bytes.
Status write_primitive(Builder& b, const MeshSlot& slot, int group, PrimitiveData& d, json* prim, bool* used_draco,
                       WriteCounts* counts) {
  if (d.triangles == 0) return Status::Ok();  // nothing left: the caller drops the primitive
  if (!d.status.ok()) return d.status;
  const GroupInfo& gi = slot.groups[group];
  json& p = *prim;
  p["attributes"] = json::object();
  p["mode"] = 4;
  if (p.contains("extensions") && p["extensions"].is_object()) {
    p["extensions"].erase("KHR_draco_mesh_compression");
    if (p["extensions"].empty()) p.erase("extensions");
  }
  p.erase("targets");
  if (d.draco) {
    const EncodeResult& enc = d.enc;
    const int view = b.add_view(enc.bytes.data(), enc.bytes.size(), 0);
    json ext_attrs = json::object();
    for (const EncodeAttribute& a : d.encoded) {
      ext_attrs[a.semantic] = enc.unique_ids.at(a.semantic);
      json acc = {{"componentType", a.integer ? kU16 : kFloat}, {"count", enc.points}, {"type", type_name(a.components)}};
      if (a.semantic == "POSITION") {
        acc["min"] = {enc.pos_min[0], enc.pos_min[1], enc.pos_min[2]};
        acc["max"] = {enc.pos_max[0], enc.pos_max[1], enc.pos_max[2]};
      }
      p["attributes"][a.semantic] = b.add_accessor(acc);
    }
    p["indices"] = b.add_accessor({{"componentType", enc.points < 65535 ? kU16 : kU32},
                                   {"count", enc.faces * 3}, {"type", "SCALAR"}});
    p["extensions"]["KHR_draco_mesh_compression"] = {{"bufferView", view}, {"attributes", ext_attrs}};
    *used_draco = true;
    counts->primitives += 1;
    counts->vertices += enc.points;
    counts->triangles += enc.faces;
    counts->quantization_collapsed += d.triangles - enc.faces;
    return Status::Ok();
  }
  const int64_t nvert = d.nvert;
  p["attributes"]["POSITION"] = b.float_accessor(d.pos, 3, true);
  for (const PrimitiveData::Attr& a : d.attrs) {
    if (is_target_channel(a.name)) continue;
    p["attributes"][a.name] = a.ch->kind == ChannelKind::kJoints ? b.u16_accessor(a.data, a.ch->components)
                                                                 : b.float_accessor(a.data, a.ch->components, false);
  }
  p["indices"] = b.index_accessor(d.idx, nvert);
  counts->primitives += 1;
  counts->vertices += nvert;
  counts->triangles += d.triangles;
  if (gi.targets > 0) {
    json targets = json::array();
    for (int t = 0; t < gi.targets; ++t) {
      json tj = json::object();
      tj["POSITION"] = b.float_accessor(d.target_pos[size_t(t)], 3, true);
      const std::string prefix = "target" + std::to_string(t) + ":";
      for (const PrimitiveData::Attr& a : d.attrs)
        if (a.name.rfind(prefix, 0) == 0) tj[a.name.substr(prefix.size())] = b.float_accessor(a.data, a.ch->components, false);
      targets.push_back(tj);
    }
    p["targets"] = targets;
  }
  return Status::Ok();
}

void collect_refs(const json& j, const std::set<std::pair<int, int>>& replaced, std::vector<uint8_t>& acc_used) {
  auto use = [&](const json& v) {
    if (v.is_number_integer() && v.get<int64_t>() >= 0 && size_t(v.get<int64_t>()) < acc_used.size()) acc_used[v.get<int64_t>()] = 1;
  };
  if (j.contains("meshes") && j["meshes"].is_array())
    for (size_t mi = 0; mi < j["meshes"].size(); ++mi) {
      const json& mesh = j["meshes"][mi];
      if (!mesh.is_object() || !mesh.contains("primitives") || !mesh["primitives"].is_array()) continue;
      for (size_t pi = 0; pi < mesh["primitives"].size(); ++pi) {
        if (replaced.count({int(mi), int(pi)})) continue;
        const json& p = mesh["primitives"][pi];
        if (p.contains("attributes") && p["attributes"].is_object())
          for (const auto& v : p["attributes"]) use(v);
        if (p.contains("indices")) use(p["indices"]);
        if (p.contains("targets") && p["targets"].is_array())
          for (const auto& t : p["targets"])
            if (t.is_object()) for (const auto& v : t) use(v);
      }
    }
  if (j.contains("skins") && j["skins"].is_array())
    for (const auto& s : j["skins"]) if (s.is_object() && s.contains("inverseBindMatrices")) use(s["inverseBindMatrices"]);
  if (j.contains("animations") && j["animations"].is_array())
    for (const auto& a : j["animations"])
      if (a.is_object() && a.contains("samplers") && a["samplers"].is_array())
        for (const auto& s : a["samplers"]) {
          if (s.contains("input")) use(s["input"]);
          if (s.contains("output")) use(s["output"]);
        }
  if (j.contains("nodes") && j["nodes"].is_array())
    for (const auto& n : j["nodes"])
      if (n.is_object() && n.contains("extensions") && n["extensions"].contains("EXT_mesh_gpu_instancing")) {
        const json& ext = n["extensions"]["EXT_mesh_gpu_instancing"];
        if (ext.contains("attributes") && ext["attributes"].is_object()) for (const auto& v : ext["attributes"]) use(v);
      }
}

template <typename F>
void remap_acc_refs(json& j, const std::set<std::pair<int, int>>& replaced, F remap) {
  auto fix = [&](json& v) { if (v.is_number_integer()) v = remap(v.get<int64_t>()); };
  if (j.contains("meshes"))
    for (size_t mi = 0; mi < j["meshes"].size(); ++mi) {
      json& mesh = j["meshes"][mi];
      if (!mesh.contains("primitives")) continue;
      for (size_t pi = 0; pi < mesh["primitives"].size(); ++pi) {
        if (replaced.count({int(mi), int(pi)})) continue;
        json& p = mesh["primitives"][pi];
        if (p.contains("attributes")) for (auto& v : p["attributes"]) fix(v);
        if (p.contains("indices")) fix(p["indices"]);
        if (p.contains("targets")) for (auto& t : p["targets"]) for (auto& v : t) fix(v);
      }
    }
  if (j.contains("skins"))
    for (auto& s : j["skins"]) if (s.contains("inverseBindMatrices")) fix(s["inverseBindMatrices"]);
  if (j.contains("animations"))
    for (auto& a : j["animations"])
      if (a.contains("samplers"))
        for (auto& s : a["samplers"]) { if (s.contains("input")) fix(s["input"]); if (s.contains("output")) fix(s["output"]); }
  if (j.contains("nodes"))
    for (auto& n : j["nodes"])
      if (n.contains("extensions") && n["extensions"].contains("EXT_mesh_gpu_instancing")) {
        json& ext = n["extensions"]["EXT_mesh_gpu_instancing"];
        if (ext.contains("attributes")) for (auto& v : ext["attributes"]) fix(v);
      }
}

void set_extension(json& j, const std::string& name, bool on) {
  for (const char* key : {"extensionsUsed", "extensionsRequired"}) {
    json arr = j.contains(key) && j[key].is_array() ? j[key] : json::array();
    json out = json::array();
    for (const auto& e : arr) if (!(e.is_string() && e.get<std::string>() == name)) out.push_back(e);
    if (on) out.push_back(name);
    if (out.empty()) j.erase(key);
    else j[key] = out;
  }
}

}  // namespace

Status write_gltf(const Document& doc, const OutputOptions& opt, bool binary, const ExtrasFn& extras,
                  std::vector<uint8_t>* out, WriteCounts* counts) {
  json j;
  std::vector<uint8_t> bin;
  std::set<std::pair<int, int>> replaced;
  for (const MeshSlot& s : doc.meshes)
    for (const GroupInfo& g : s.groups) replaced.insert({s.gltf_mesh, g.gltf_primitive});

  if (doc.is_gltf) {
    j = doc.gltf;
    // Keep what the rest of the file still references; drop the replaced geometry.
    const size_t nacc = j.contains("accessors") && j["accessors"].is_array() ? j["accessors"].size() : 0;
    std::vector<uint8_t> acc_used(nacc, 0);
    collect_refs(j, replaced, acc_used);
    std::vector<int64_t> acc_map(nacc, -1);
    json accessors = json::array();
    for (size_t i = 0; i < nacc; ++i)
      if (acc_used[i]) { acc_map[i] = int64_t(accessors.size()); accessors.push_back(j["accessors"][i]); }
    remap_acc_refs(j, replaced, [&](int64_t i) -> int64_t { return i >= 0 && size_t(i) < nacc ? acc_map[i] : i; });
    const size_t nview = j.contains("bufferViews") && j["bufferViews"].is_array() ? j["bufferViews"].size() : 0;
    std::vector<uint8_t> view_used(nview, 0);
    auto use_view = [&](const json& v) {
      if (v.is_number_integer() && v.get<int64_t>() >= 0 && size_t(v.get<int64_t>()) < nview) view_used[v.get<int64_t>()] = 1;
    };
    for (const auto& a : accessors) {
      if (a.contains("bufferView")) use_view(a["bufferView"]);
      if (a.contains("sparse") && a["sparse"].is_object()) {
        if (a["sparse"].contains("indices")) use_view(a["sparse"]["indices"].value("bufferView", json(-1)));
        if (a["sparse"].contains("values")) use_view(a["sparse"]["values"].value("bufferView", json(-1)));
      }
    }
    if (j.contains("images") && j["images"].is_array())
      for (const auto& im : j["images"]) if (im.is_object() && im.contains("bufferView")) use_view(im["bufferView"]);
    if (j.contains("meshes"))
      for (size_t mi = 0; mi < j["meshes"].size(); ++mi)
        for (size_t pi = 0; j["meshes"][mi].contains("primitives") && pi < j["meshes"][mi]["primitives"].size(); ++pi) {
          if (replaced.count({int(mi), int(pi)})) continue;
          const json& p = j["meshes"][mi]["primitives"][pi];
          if (p.contains("extensions") && p["extensions"].contains("KHR_draco_mesh_compression"))
            use_view(p["extensions"]["KHR_draco_mesh_compression"].value("bufferView", json(-1)));
        }
    std::vector<int64_t> view_map(nview, -1);
    json views = json::array();
    for (size_t i = 0; i < nview; ++i) {
      if (!view_used[i]) continue;
      json v = j["bufferViews"][i];
      const int64_t buf = v.value("buffer", int64_t(-1)), off = v.value("byteOffset", int64_t(0)),
                    len = v.value("byteLength", int64_t(0));
      if (buf < 0 || size_t(buf) >= doc.buffers.size() || off < 0 || len < 0 ||
          uint64_t(off) + uint64_t(len) > doc.buffers[buf].size())
        return Status::Error(ErrorKind::kBadInput, "bad_buffer_view", "bufferView " + std::to_string(i) + " is out of bounds");
      while (bin.size() % 4) bin.push_back(0);
      v["buffer"] = 0;
      v["byteOffset"] = bin.size();
      bin.insert(bin.end(), doc.buffers[buf].begin() + off, doc.buffers[buf].begin() + off + len);
      view_map[i] = int64_t(views.size());
      views.push_back(v);
    }
    auto fix_view = [&](json& v) {
      if (v.is_number_integer() && v.get<int64_t>() >= 0 && size_t(v.get<int64_t>()) < nview) v = view_map[v.get<int64_t>()];
    };
    for (auto& a : accessors) {
      if (a.contains("bufferView")) fix_view(a["bufferView"]);
      if (a.contains("sparse") && a["sparse"].is_object()) {
        if (a["sparse"].contains("indices") && a["sparse"]["indices"].contains("bufferView")) fix_view(a["sparse"]["indices"]["bufferView"]);
        if (a["sparse"].contains("values") && a["sparse"]["values"].contains("bufferView")) fix_view(a["sparse"]["values"]["bufferView"]);
      }
    }
    if (j.contains("images")) for (auto& im : j["images"]) if (im.contains("bufferView")) fix_view(im["bufferView"]);
    if (j.contains("meshes"))
      for (size_t mi = 0; mi < j["meshes"].size(); ++mi)
        for (size_t pi = 0; j["meshes"][mi].contains("primitives") && pi < j["meshes"][mi]["primitives"].size(); ++pi) {
          if (replaced.count({int(mi), int(pi)})) continue;
          json& p = j["meshes"][mi]["primitives"][pi];
          if (p.contains("extensions") && p["extensions"].contains("KHR_draco_mesh_compression") &&
              p["extensions"]["KHR_draco_mesh_compression"].contains("bufferView"))
            fix_view(p["extensions"]["KHR_draco_mesh_compression"]["bufferView"]);
        }
    j["accessors"] = accessors;
    j["bufferViews"] = views;
  } else {
    j = {{"asset", {{"version", "2.0"}, {"generator", "IteAS"}}}, {"scene", 0},
         {"scenes", json::array({{{"nodes", json::array()}}})}, {"nodes", json::array()}, {"meshes", json::array()}};
    for (size_t i = 0; i < doc.meshes.size(); ++i) {
      j["nodes"].push_back({{"mesh", i}});
      j["scenes"][0]["nodes"].push_back(i);
      json prims = json::array();
      for (size_t g = 0; g < doc.meshes[i].groups.size(); ++g) prims.push_back(json::object());
      j["meshes"].push_back({{"primitives", prims}});
    }
    j["accessors"] = json::array();
    j["bufferViews"] = json::array();
  }

  Builder b{j, bin};
  bool used_draco = false;
  // One quantization grid per mesh so primitives that share a border keep it.
  std::vector<Aabb> boxes(doc.meshes.size());
  std::vector<float> ranges(doc.meshes.size(), 0.0f);
  for (size_t si = 0; si < doc.meshes.size(); ++si) {
    boxes[si] = bounding_box(doc.meshes[si].mesh);
    for (int k = 0; k < 3; ++k) ranges[si] = std::max(ranges[si], boxes[si].hi[k] - boxes[si].lo[k]);
  }
  // Draco payloads are encoded on the job's threads, a primitive at a time
  // (each on its own: the bytes do not depend on the thread count), and kept
  // until written in order; without Draco each primitive's arrays are
  // gathered just before they are written.
  std::vector<std::vector<PrimitiveData>> data(doc.meshes.size());
  std::vector<std::pair<size_t, int>> prims_all;
  for (size_t si = 0; si < doc.meshes.size(); ++si) {
    data[si].resize(doc.meshes[si].groups.size());
    for (size_t g = 0; g < doc.meshes[si].groups.size(); ++g) prims_all.push_back({si, int(g)});
  }
  if (opt.draco && resolve_threads(opt.threads) > 1 && prims_all.size() > 1)
    parallel_for_chunks(int64_t(prims_all.size()), opt.threads, [&](int64_t first, int64_t end) {
      for (int64_t i = first; i < end; ++i) {
        const auto [si, g] = prims_all[size_t(i)];
        prepare_primitive(doc.meshes[si], g, opt, boxes[si].lo, ranges[si], &data[si][size_t(g)]);
      }
    });
  for (size_t si = 0; si < doc.meshes.size(); ++si) {
    const MeshSlot& slot = doc.meshes[si];
    const int mesh_index = doc.is_gltf ? slot.gltf_mesh : int(si);
    std::vector<int> empty_prims;
    for (size_t g = 0; g < slot.groups.size(); ++g) {
      json& prim = j["meshes"][mesh_index]["primitives"][slot.groups[g].gltf_primitive < 0 ? int(g) : slot.groups[g].gltf_primitive];
      PrimitiveData& d = data[si][g];
      if (!d.ready) prepare_primitive(slot, int(g), opt, boxes[si].lo, ranges[si], &d);
      Status s = write_primitive(b, slot, int(g), d, &prim, &used_draco, counts);
      d = PrimitiveData();
      if (!s.ok()) return s;
      if (!prim.contains("indices")) empty_prims.push_back(slot.groups[g].gltf_primitive < 0 ? int(g) : slot.groups[g].gltf_primitive);
    }
    // Primitives whose every face was degenerate are removed (a primitive
    // needs at least one triangle); a mesh keeps at least its first.
    std::sort(empty_prims.rbegin(), empty_prims.rend());
    json& prims = j["meshes"][mesh_index]["primitives"];
    for (int pi : empty_prims)
      if (prims.size() > 1) prims.erase(prims.begin() + pi);
  }
  set_extension(j, "KHR_draco_mesh_compression", used_draco);
  if (j["accessors"].empty()) j.erase("accessors");
  if (j["bufferViews"].empty()) j.erase("bufferViews");
  if (bin.empty()) {
    j.erase("buffers");
  } else {
    while (bin.size() % 4) bin.push_back(0);
    json buf = {{"byteLength", bin.size()}};
    if (!binary) buf["uri"] = "data:application/octet-stream;base64," + base64(bin);
    j["buffers"] = json::array({buf});
  }
  counts->meshes = int64_t(doc.meshes.size());
  if (extras) j["asset"]["extras"]["iteas"] = extras(*counts);

  const std::string text = json_text(j);
  out->clear();
  if (!binary) {
    out->assign(text.begin(), text.end());
    return Status::Ok();
  }
  *out = pack_glb(text, bin.empty() ? nullptr : bin.data(), bin.size());
  if (out->empty())
    return Status::Error(ErrorKind::kTooLarge, "output_too_large",
                         "the output needs " + std::to_string((text.size() + bin.size()) >> 20) +
                             " MiB, over the 4 GiB a GLB file can hold: use Draco compression or a lower max_triangles");
  return Status::Ok();
}

}  // namespace iteas
