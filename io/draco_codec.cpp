#include "io/draco_codec.h"

#include <algorithm>
#include <cmath>
#include <limits>

#include <draco/attributes/attribute_quantization_transform.h>
#include <draco/compression/decode.h>
#include <draco/core/options.h>
#include <draco/core/quantization_utils.h>
#include <draco/compression/expert_encode.h>
#include <draco/mesh/mesh.h>

#include "io/memory_budget.h"

namespace iteas {
namespace {

std::string semantic_of(const draco::PointAttribute& att, int* tex, int* color, int* generic) {
  switch (att.attribute_type()) {
    case draco::GeometryAttribute::POSITION: return "POSITION";
    case draco::GeometryAttribute::NORMAL: return "NORMAL";
    case draco::GeometryAttribute::TEX_COORD: return "TEXCOORD_" + std::to_string((*tex)++);
    case draco::GeometryAttribute::COLOR: return "COLOR_" + std::to_string((*color)++);
    default: return "_GENERIC_" + std::to_string((*generic)++);
  }
}

Status read_attribute(const draco::PointAttribute& att, int64_t points, const std::string& semantic,
                      DecodedAttribute* out) {
  const int comps = att.num_components();
  if (comps < 1 || comps > 4)
    return Status::Error(ErrorKind::kBadInput, "bad_draco", "Draco attribute " + semantic + " has " +
                                                               std::to_string(comps) + " components");
  out->semantic = semantic;
  out->components = comps;
  out->data.assign(size_t(points) * comps, 0.0f);
  float tmp[4];
  for (int64_t p = 0; p < points; ++p) {
    const draco::AttributeValueIndex avi = att.mapped_index(draco::PointIndex(uint32_t(p)));
    if (avi.value() >= att.size())
      return Status::Error(ErrorKind::kBadInput, "bad_draco", "Draco attribute value index out of range");
    if (!att.ConvertValue<float>(avi, static_cast<int8_t>(comps), tmp))
      return Status::Error(ErrorKind::kBadInput, "bad_draco", "Draco attribute " + semantic + " unreadable");
    for (int k = 0; k < comps; ++k) out->data[size_t(p) * comps + k] = tmp[k];
  }
  return Status::Ok();
}

Status decode_unguarded(const uint8_t* data, size_t size, const std::map<std::string, int>* semantic_ids,
                        const ReadLimits& limits, DecodedGeometry* out) {
  draco::DecoderBuffer buffer;
  buffer.Init(reinterpret_cast<const char*>(data), size);
  auto type = draco::Decoder::GetEncodedGeometryType(&buffer);
  if (!type.ok())
    return Status::Error(ErrorKind::kBadInput, "bad_draco", "not a Draco payload: " + type.status().error_msg_string());
  if (type.value() != draco::TRIANGULAR_MESH)
    return Status::Error(ErrorKind::kUnusable, "no_triangles", "Draco payload is a point cloud: no triangles");
  draco::Decoder decoder;
  auto decoded = decoder.DecodeMeshFromBuffer(&buffer);
  if (!decoded.ok())
    return Status::Error(ErrorKind::kBadInput, "bad_draco", "Draco decode failed: " + decoded.status().error_msg_string());
  const std::unique_ptr<draco::Mesh>& dm = decoded.value();
  const int64_t points = dm->num_points(), faces = dm->num_faces();
  if (points > limits.max_vertices || faces > limits.max_triangles)
    return Status::Error(ErrorKind::kTooLarge, "too_large", "Draco payload exceeds the vertex or triangle limit");
  out->points = points;
  out->faces.resize(size_t(faces) * 3);
  for (int64_t f = 0; f < faces; ++f) {
    const draco::Mesh::Face& face = dm->face(draco::FaceIndex(uint32_t(f)));
    for (int k = 0; k < 3; ++k) {
      const uint32_t p = face[k].value();
      if (p >= uint64_t(points))
        return Status::Error(ErrorKind::kBadInput, "bad_draco", "Draco face references a missing point");
      out->faces[size_t(f) * 3 + k] = int32_t(p);
    }
  }
  out->attributes.clear();
  if (semantic_ids) {
    for (const auto& [semantic, uid] : *semantic_ids) {
      if (uid < 0)
        return Status::Error(ErrorKind::kBadInput, "bad_draco", "Draco extension attribute id is negative");
      const draco::PointAttribute* att = dm->GetAttributeByUniqueId(uint32_t(uid));
      if (!att)
        return Status::Error(ErrorKind::kBadInput, "bad_draco",
                             "Draco extension names attribute id " + std::to_string(uid) + " for " + semantic +
                                 ", which the payload does not have");
      DecodedAttribute a;
      Status s = read_attribute(*att, points, semantic, &a);
      if (!s.ok()) return s;
      out->attributes.push_back(std::move(a));
    }
  } else {
    int tex = 0, color = 0, generic = 0;
    for (int i = 0; i < dm->num_attributes(); ++i) {
      const draco::PointAttribute* att = dm->attribute(i);
      DecodedAttribute a;
      Status s = read_attribute(*att, points, semantic_of(*att, &tex, &color, &generic), &a);
      if (!s.ok()) return s;
      out->attributes.push_back(std::move(a));
    }
  }
  return Status::Ok();
}

// The bounds of the positions a decoder of the payload gets, without
// decoding it: the encoder quantises each value with draco::Quantizer after
// subtracting the grid's origin, and the decoder multiplies the integer back
// with draco::Dequantizer and adds the origin. The same library classes with
// the same parameters (the explicit grid as the encoder reads it, or the one
// it computes from the attribute with the same routine) give the decoded
// values bit for bit. The payload holds the values of the points the faces
// use (a point no face uses is left out; equal points may be merged and a
// non-manifold one split, which keeps the values); where the encoder dropped
// a face (one that names a point twice, or whose points it merged), the
// caller decodes instead.
bool dequantised_bounds(const draco::Mesh& dm, const draco::PointAttribute& att, const std::vector<int32_t>& faces,
                        int bits, const float* grid_origin, float grid_range, EncodeResult* out) {
  if (att.num_components() != 3 || out->faces != int64_t(faces.size() / 3) || faces.empty()) return false;
  draco::AttributeQuantizationTransform grid;
  const bool ok = grid_origin && grid_range > 0 ? grid.SetParameters(bits, grid_origin, 3, grid_range)
                                                : grid.ComputeParameters(att, bits);
  if (!ok) return false;
  const int32_t max_quantized = int32_t((1u << uint32_t(bits)) - 1);
  // A range so small (denormal) that a step's inverse overflows makes every
  // value's quantisation 0 * inf, a NaN converted to an integer (undefined;
  // found by fuzz_http): the decoder's bounds are taken from the payload.
  if (!std::isfinite(float(max_quantized) / grid.range())) return false;
  draco::Quantizer quantize;
  quantize.Init(grid.range(), max_quantized);
  draco::Dequantizer dequantize;
  if (!dequantize.Init(grid.range(), max_quantized)) return false;
  std::vector<uint8_t> used(dm.num_points(), 0);
  for (int32_t p : faces) used[size_t(p)] = 1;
  float lo[3], hi[3];
  for (int k = 0; k < 3; ++k) { lo[k] = std::numeric_limits<float>::infinity(); hi[k] = -lo[k]; }
  const float origin[3] = {grid.min_value(0), grid.min_value(1), grid.min_value(2)};
  for (uint32_t p = 0; p < dm.num_points(); ++p) {
    if (!used[p]) continue;
    float v[3];
    att.GetValue(att.mapped_index(draco::PointIndex(p)), v);
    for (int k = 0; k < 3; ++k) {
      const float back = dequantize.DequantizeFloat(quantize.QuantizeFloat(v[k] - origin[k])) + origin[k];
      lo[k] = std::min(lo[k], back);
      hi[k] = std::max(hi[k], back);
    }
  }
  for (int k = 0; k < 3; ++k) { out->pos_min[k] = lo[k]; out->pos_max[k] = hi[k]; }
  return true;
}

// The bounds of the positions a decoder gets, by decoding the payload.
Status decoded_bounds(EncodeResult* out) {
  DecodedGeometry check;
  std::map<std::string, int> pos_only;
  if (out->unique_ids.count("POSITION")) pos_only["POSITION"] = out->unique_ids["POSITION"];
  ReadLimits unlimited;
  unlimited.max_vertices = unlimited.max_triangles = INT64_MAX;
  Status s = draco_decode(out->bytes.data(), out->bytes.size(), &pos_only, unlimited, &check);
  if (!s.ok()) return s;
  if (check.points != out->points || int64_t(check.faces.size() / 3) != out->faces)
    return Status::Error(ErrorKind::kBadInput, "encode_failed", "Draco payload counts differ from the encoder's");
  if (!check.attributes.empty() && check.points > 0) {
    const std::vector<float>& p = check.attributes[0].data;
    for (int k = 0; k < 3; ++k) out->pos_min[k] = out->pos_max[k] = p[k];
    for (int64_t i = 1; i < check.points; ++i)
      for (int k = 0; k < 3; ++k) {
        out->pos_min[k] = std::min(out->pos_min[k], p[3 * size_t(i) + k]);
        out->pos_max[k] = std::max(out->pos_max[k], p[3 * size_t(i) + k]);
      }
  }
  return Status::Ok();
}

}  // namespace

Status draco_decode(const uint8_t* data, size_t size, const std::map<std::string, int>* semantic_ids,
                    const ReadLimits& limits, DecodedGeometry* out) {
  // Decompression-bomb limit: libdraco sizes its buffers from counts declared
  // in the payload, so a few hundred bytes can ask for gigabytes. Everything
  // the decoder (and our copy of its result) allocates on this thread is
  // capped at a base plus a multiple of the payload size.
  const int64_t cap = limits.draco_base_bytes + limits.draco_expansion * int64_t(size);
  try {
    MemoryBudget budget(cap);
    return decode_unguarded(data, size, semantic_ids, limits, out);
  } catch (const MemoryLimitExceeded&) {
    *out = DecodedGeometry();
    return Status::Error(ErrorKind::kTooLarge, "decompression_bomb",
                         "Draco payload of " + std::to_string(size) + " bytes needs more than " +
                             std::to_string(cap >> 20) + " MiB to decode (limit: " +
                             std::to_string(limits.draco_base_bytes >> 20) + " MiB + " +
                             std::to_string(limits.draco_expansion) + "x the payload)");
  }
}

Status draco_encode(const EncodeRequest& req, const OutputOptions& options, EncodeResult* out) {
  draco::Mesh dm;
  const int64_t points = req.points;
  const int64_t faces = int64_t(req.faces->size() / 3);
  dm.set_num_points(uint32_t(points));
  dm.SetNumFaces(size_t(faces));
  for (int64_t f = 0; f < faces; ++f) {
    draco::Mesh::Face face;
    for (int k = 0; k < 3; ++k) face[k] = draco::PointIndex(uint32_t((*req.faces)[size_t(f) * 3 + k]));
    dm.SetFace(draco::FaceIndex(uint32_t(f)), face);
  }
  std::vector<int> ids;
  const draco::PointAttribute* position = nullptr;
  for (const EncodeAttribute& a : req.attributes) {
    draco::GeometryAttribute::Type type = draco::GeometryAttribute::GENERIC;
    if (a.semantic == "POSITION") type = draco::GeometryAttribute::POSITION;
    else if (a.semantic == "NORMAL") type = draco::GeometryAttribute::NORMAL;
    else if (a.semantic.rfind("TEXCOORD_", 0) == 0) type = draco::GeometryAttribute::TEX_COORD;
    else if (a.semantic.rfind("COLOR_", 0) == 0) type = draco::GeometryAttribute::COLOR;
    draco::GeometryAttribute ga;
    const draco::DataType dt = a.integer ? draco::DT_UINT16 : draco::DT_FLOAT32;
    const int elem = a.integer ? 2 : 4;
    ga.Init(type, nullptr, uint8_t(a.components), dt, false, int64_t(elem) * a.components, 0);
    const int id = dm.AddAttribute(ga, true, uint32_t(points));
    if (id < 0) return Status::Error(ErrorKind::kBadInput, "encode_failed", "Draco rejected attribute " + a.semantic);
    draco::PointAttribute* att = dm.attribute(id);
    att->set_unique_id(uint32_t(id));
    std::vector<uint16_t> ivals(a.components);
    for (int64_t p = 0; p < points; ++p) {
      const float* src = a.data + size_t(p) * a.components;
      if (a.integer) {
        for (int k = 0; k < a.components; ++k) ivals[k] = uint16_t(std::clamp(src[k], 0.0f, 65535.0f));
        att->SetAttributeValue(draco::AttributeValueIndex(uint32_t(p)), ivals.data());
      } else {
        att->SetAttributeValue(draco::AttributeValueIndex(uint32_t(p)), src);
      }
    }
    ids.push_back(id);
    out->unique_ids[a.semantic] = id;
    if (type == draco::GeometryAttribute::POSITION && !a.integer) position = att;
  }
  // The explicit grid as the encoder reads it: Draco keeps quantization
  // options as text (std::to_string, six decimals) and parses them back, so
  // it quantises with those values. Where that moves the grid by more than
  // 1 % of its range (a mesh under about 5e-5 units across, whose range
  // could even read as 0 and collapse every point), the primitive gets the
  // grid the encoder computes from its own points instead.
  float grid_origin[3] = {0, 0, 0}, grid_range = 0;
  bool explicit_grid = false;
  if (req.grid_origin && req.grid_range > 0) {
    draco::Options text;
    text.SetVector("origin", req.grid_origin, 3);
    text.SetFloat("range", req.grid_range);
    text.GetVector("origin", 3, grid_origin);
    grid_range = text.GetFloat("range");
    const float slack = 0.01f * req.grid_range;
    explicit_grid = grid_range > 0 && std::fabs(grid_range - req.grid_range) <= slack;
    for (int k = 0; k < 3; ++k) explicit_grid = explicit_grid && std::fabs(grid_origin[k] - req.grid_origin[k]) <= slack;
  }
  draco::ExpertEncoder encoder(dm);
  const int speed = 10 - std::clamp(options.draco_level, 0, 10);
  encoder.SetSpeedOptions(speed, speed);
  encoder.SetTrackEncodedProperties(true);
  for (size_t i = 0; i < req.attributes.size(); ++i) {
    const EncodeAttribute& a = req.attributes[i];
    if (a.integer) continue;  // JOINTS stay exact
    if (a.semantic == "POSITION") {
      if (explicit_grid)
        encoder.SetAttributeExplicitQuantization(ids[i], options.position_bits, 3, req.grid_origin, req.grid_range);
      else
        encoder.SetAttributeQuantization(ids[i], options.position_bits);
    } else if (a.semantic == "NORMAL") {
      encoder.SetAttributeQuantization(ids[i], options.normal_bits);
    } else if (a.semantic.rfind("TEXCOORD_", 0) == 0) {
      encoder.SetAttributeQuantization(ids[i], options.texcoord_bits);
    } else if (a.semantic.rfind("COLOR_", 0) == 0) {
      encoder.SetAttributeQuantization(ids[i], options.color_bits);
    } else {
      encoder.SetAttributeQuantization(ids[i], options.generic_bits);
    }
  }
  draco::EncoderBuffer buffer;
  const draco::Status st = encoder.EncodeToBuffer(&buffer);
  if (!st.ok()) return Status::Error(ErrorKind::kBadInput, "encode_failed", "Draco encode failed: " + st.error_msg_string());
  out->bytes.assign(buffer.data(), buffer.data() + buffer.size());
  out->points = int64_t(encoder.num_encoded_points());
  out->faces = int64_t(encoder.num_encoded_faces());

  // Accessor min/max must describe the decoded (dequantised) positions.
  if (!position ||
      dequantised_bounds(dm, *position, *req.faces, options.position_bits, explicit_grid ? grid_origin : nullptr,
                         grid_range, out))
    return Status::Ok();
  return decoded_bounds(out);
}

}  // namespace iteas
