// Fuzz target: every reader a request can reach (GLB, glTF JSON with the Draco
// extension, raw .drc, OBJ, PLY, OFF, STL), then the writers on what was read.
// The first byte picks the format so one corpus covers all of them.
#include <cstddef>
#include <cstdint>
#include <string>

#include "io/document.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  if (size < 1) return 0;
  static const char* kFormats[] = {"glb", "gltf", "drc", "obj", "ply", "off", "stl"};
  const std::string format = kFormats[data[0] % 7];
  iteas::ReadLimits limits;
  limits.max_vertices = 1 << 20;
  limits.max_triangles = 1 << 20;
  iteas::Document doc;
  if (!iteas::read_document(data + 1, size - 1, format, limits, &doc).ok()) return 0;
  std::vector<uint8_t> out;
  iteas::OutputOptions opt;
  opt.draco = (data[0] & 8) != 0;
  iteas::write_document(doc, opt, "glb", nullptr, &out, nullptr);
  return 0;
}
