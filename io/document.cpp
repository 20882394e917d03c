#include "io/document.h"

#include <algorithm>
#include <cctype>
#include <cstring>

namespace iteas {

std::string sniff_format(const uint8_t* data, size_t size, const std::string& name_hint) {
  if (size >= 4 && std::memcmp(data, "glTF", 4) == 0) return "glb";
  if (size >= 5 && std::memcmp(data, "DRACO", 5) == 0) return "drc";
  if (size >= 4 && std::memcmp(data, "ply", 3) == 0 && (data[3] == '\n' || data[3] == '\r')) return "ply";
  if (size >= 3 && std::memcmp(data, "OFF", 3) == 0) return "off";
  // Text: a JSON object is glTF; otherwise fall back to the name's extension.
  size_t i = 0;
  while (i < size && i < 4096 && std::isspace(data[i])) ++i;
  if (i < size && data[i] == '{') return "gltf";
  std::string ext;
  const size_t dot = name_hint.find_last_of('.');
  if (dot != std::string::npos) ext = name_hint.substr(dot + 1);
  std::transform(ext.begin(), ext.end(), ext.begin(), [](unsigned char c) { return char(std::tolower(c)); });
  if (ext == "obj" || ext == "stl" || ext == "off" || ext == "ply" || ext == "drc" || ext == "glb" || ext == "gltf") return ext;
  if (size >= 84) {  // binary STL: 80-byte header, count, 50 bytes per triangle
    uint32_t n;
    std::memcpy(&n, data + 80, 4);
    if (uint64_t(84) + uint64_t(n) * 50 == size) return "stl";
  }
  if (size >= 5 && std::memcmp(data, "solid", 5) == 0) return "stl";
  // OBJ has no magic: lines starting with v/vt/vn/f/o/g/#/mtllib.
  i = 0;
  while (i < size && i < 4096 && std::isspace(data[i])) ++i;
  if (i + 1 < size && ((data[i] == 'v' && (data[i + 1] == ' ' || data[i + 1] == 't' || data[i + 1] == 'n')) ||
                       data[i] == '#' || (data[i] == 'o' && data[i + 1] == ' ') || (data[i] == 'g' && data[i + 1] == ' ') ||
                       (size - i > 6 && std::memcmp(data + i, "mtllib", 6) == 0)))
    return "obj";
  return "";
}

Status read_document(const uint8_t* data, size_t size, const std::string& format, const ReadLimits& limits, Document* doc) {
  *doc = Document();
  doc->format = format;
  doc->input_bytes = int64_t(size);
  Status s;
  if (format == "glb" || format == "gltf") s = read_gltf(data, size, format == "glb", limits, doc);
  else if (format == "drc" || format == "obj" || format == "ply" || format == "off" || format == "stl")
    s = read_classic(data, size, format, limits, doc);
  else return Status::Error(ErrorKind::kUnsupported, "unsupported_format", "unrecognised input format");
  if (!s.ok()) return s;
  int64_t triangles = 0;
  for (MeshSlot& slot : doc->meshes) {
    slot.dropped_faces = drop_degenerate_faces(slot.mesh);
    triangles += slot.mesh.num_faces();
    if (slot.dropped_faces)
      doc->warnings.push_back(std::to_string(slot.dropped_faces) + " faces with a repeated vertex dropped from mesh " +
                              std::to_string(&slot - doc->meshes.data()));
  }
  if (triangles == 0) return Status::Error(ErrorKind::kUnusable, "no_triangles", "the input has no usable triangles");
  return Status::Ok();
}

Status write_document(const Document& doc, const OutputOptions& options, const std::string& format,
                      const ExtrasFn& extras, std::vector<uint8_t>* out, WriteCounts* counts) {
  WriteCounts local;
  if (!counts) counts = &local;
  *counts = WriteCounts();
  if (format == "glb" || format == "gltf") return write_gltf(doc, options, format == "glb", extras, out, counts);
  return write_classic(doc, options, format, out, counts);
}

}  // namespace iteas
