// A decoded input file: the refinable meshes plus, for glTF inputs, everything
// else in the file kept verbatim (JSON and buffer bytes) so it survives
// unchanged. Readers and writers here are safe for untrusted bytes: they return
// a Status instead of asserting, and check declared counts against the bytes
// actually present before allocating.
#pragma once

#include <cstdint>
#include <functional>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "core/corner_table.h"
#include "core/mesh.h"
#include "core/options.h"

namespace iteas {

enum class ErrorKind {
  kOk = 0,
  kBadInput,     // malformed file or option (HTTP 400, exit 3)
  kUnsupported,  // unknown format or required extension (415, exit 3)
  kUnusable,     // well-formed but unusable: no triangles, non-finite (422, exit 3)
  kTooLarge,     // declared or predicted size over a limit (413, exit 3)
  kIo,           // could not read or write a file (exit 4)
};

struct Status {
  ErrorKind kind = ErrorKind::kOk;
  std::string code;     // snake_case machine code
  std::string message;  // one line, for people
  bool ok() const { return kind == ErrorKind::kOk; }
  static Status Ok() { return {}; }
  static Status Error(ErrorKind k, std::string code, std::string message) {
    return {k, std::move(code), std::move(message)};
  }
};

struct ReadLimits {
  int64_t max_vertices = 1LL << 26;   // per accessor / mesh
  int64_t max_triangles = 1LL << 26;  // per mesh, input side
  // Draco decompression-bomb limit: heap the decoder may use, as a base plus a
  // multiple of the payload's size (corpus payloads over a few KB measure under
  // 90x, tiny ones up to 138x, well inside the base).
  int64_t draco_base_bytes = 64LL << 20;
  int64_t draco_expansion = 256;
};

// One channel of one primitive as it was in the input, so the output writes
// the same attribute set back.
struct GroupInfo {
  int gltf_primitive = -1;            // index in the glTF mesh's primitives
  std::vector<uint8_t> has_channel;   // per Mesh::channels entry
  int targets = 0;                    // morph targets
  bool skinned = false;
};

struct MeshSlot {
  int gltf_mesh = -1;  // index in the glTF "meshes" array; -1 for other formats
  std::string name;
  Mesh mesh;
  std::vector<GroupInfo> groups;  // per face_group id
  int64_t input_primitives = 0, input_triangles = 0, input_vertices = 0;
  int64_t dropped_faces = 0;  // repeated vertex after welding
  int64_t welded_vertices = 0;
  int targets = 0;  // morph targets of this mesh
};

struct Document {
  std::string format;  // glb, gltf, drc, obj, ply, off, stl
  int64_t input_bytes = 0;
  bool is_gltf = false;
  nlohmann::json gltf;                        // original JSON (glTF inputs)
  std::vector<std::vector<uint8_t>> buffers;  // decoded glTF buffers
  std::vector<MeshSlot> meshes;
  int64_t passthrough_primitives = 0;  // POINTS/LINES or without POSITION
  std::vector<std::string> warnings;
};

// Detects the format from magic bytes and, failing that, |name_hint|'s
// extension ("" when none). Returns "" when unknown.
std::string sniff_format(const uint8_t* data, size_t size, const std::string& name_hint);

Status read_document(const uint8_t* data, size_t size, const std::string& format, const ReadLimits& limits,
                     Document* doc);

// What a writer actually wrote (Draco may merge points, so counts come from it).
struct WriteCounts {
  int64_t meshes = 0, primitives = 0, vertices = 0, triangles = 0;
  int64_t quantization_collapsed = 0;  // triangles Draco dropped: zero area once quantized
};
// Called by glTF writers before the JSON is serialised; its result goes to
// asset.extras.iteas. May be empty.
using ExtrasFn = std::function<nlohmann::json(const WriteCounts&)>;

// Writes |doc| as |format| (glb, gltf, drc, obj, ply).
Status write_document(const Document& doc, const OutputOptions& options, const std::string& format,
                      const ExtrasFn& extras, std::vector<uint8_t>* out, WriteCounts* counts);

// Per-format pieces, used by read_document / write_document.
Status read_gltf(const uint8_t* data, size_t size, bool binary, const ReadLimits& limits, Document* doc);
Status write_gltf(const Document& doc, const OutputOptions& options, bool binary, const ExtrasFn& extras,
                  std::vector<uint8_t>* out, WriteCounts* counts);
Status read_classic(const uint8_t* data, size_t size, const std::string& format, const ReadLimits& limits,
                    Document* doc);
Status write_classic(const Document& doc, const OutputOptions& options, const std::string& format,
                     std::vector<uint8_t>* out, WriteCounts* counts);

}  // namespace iteas
