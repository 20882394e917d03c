// Draco encode/decode between our Mesh and Draco's. Decoding validates every
// attribute id an extension names before touching it (Debian's tinygltf with
// Draco segfaults there); encoding uses the ExpertEncoder with encoded-property
// tracking so accessor counts come from the encoder.
#pragma once

#include <cstdint>
#include <map>
#include <string>
#include <vector>

#include "io/document.h"

namespace iteas {

// A decoded Draco geometry in glTF terms: faces plus per-point attributes.
struct DecodedAttribute {
  std::string semantic;  // glTF semantic (POSITION, NORMAL, TEXCOORD_0, ...)
  int components = 0;
  std::vector<float> data;  // per point
};
struct DecodedGeometry {
  int64_t points = 0;
  std::vector<int32_t> faces;  // 3 per triangle, point indices
  std::vector<DecodedAttribute> attributes;
};

// Raw .drc (or a glTF extension payload when |semantic_ids| is given: then
// only those attributes, each looked up by unique id and checked).
Status draco_decode(const uint8_t* data, size_t size, const std::map<std::string, int>* semantic_ids,
                    const ReadLimits& limits, DecodedGeometry* out);

struct EncodeAttribute {
  std::string semantic;
  int components = 0;
  const float* data = nullptr;  // per point
  bool integer = false;         // JOINTS: stored as unsigned 16-bit
};
struct EncodeRequest {
  int64_t points = 0;
  const std::vector<int32_t>* faces = nullptr;
  std::vector<EncodeAttribute> attributes;
  const float* grid_origin = nullptr;  // explicit position grid (shared by a mesh's primitives)
  float grid_range = 0;
};
struct EncodeResult {
  std::vector<uint8_t> bytes;
  int64_t points = 0, faces = 0;
  std::map<std::string, int> unique_ids;  // semantic -> Draco unique id
  float pos_min[3] = {0, 0, 0}, pos_max[3] = {0, 0, 0};  // of the positions a decoder gets
};
Status draco_encode(const EncodeRequest& req, const OutputOptions& options, EncodeResult* out);

}  // namespace iteas
