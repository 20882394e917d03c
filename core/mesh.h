// The refinable mesh: one welded connectivity per glTF mesh, attributes kept per
// corner ("wedges") so seams, hard normals and primitive borders survive.
// Flat arrays only (meshoptimizer / Draco style), no pointer graphs.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

namespace iteas {

// How a per-wedge channel is carried through refinement (SPEC §2 "Attributes").
enum class ChannelKind : uint8_t {
  kLinear,   // TEXCOORD_n, COLOR_n, anything else: interpolated along the edge
  kNormal,   // recomputed from the refined geometry, hard edges kept
  kTangent,  // interpolated, re-orthogonalised against the normal, w kept
  kJoints,   // JOINTS_n: blended together with the paired WEIGHTS_n
  kWeights,  // WEIGHTS_n: top 4 influences kept, renormalised
};

struct Channel {
  std::string name;        // glTF semantic, e.g. "TEXCOORD_0"
  int components = 0;      // 1..4
  ChannelKind kind = ChannelKind::kLinear;
  int pair = -1;           // for kJoints/kWeights: index of the partner channel
  std::vector<float> data; // components per wedge
};

// A per-vertex channel refined with the Butterfly stencil weights
// (morph-target position deltas).
struct VertexChannel {
  std::string name;
  std::vector<float> data;  // 3 per vertex
};

struct Mesh {
  std::vector<float> positions;       // 3 per vertex
  std::vector<int32_t> corner_vertex; // 3 per face: corner -> vertex
  std::vector<int32_t> corner_wedge;  // 3 per face: corner -> wedge
  std::vector<int32_t> face_group;    // per face: primitive id
  std::vector<int32_t> wedge_vertex;  // per wedge: its vertex
  std::vector<Channel> channels;      // per-wedge data
  std::vector<VertexChannel> vertex_channels;  // per-vertex data (morph deltas)

  int32_t num_vertices() const { return static_cast<int32_t>(positions.size() / 3); }
  int32_t num_faces() const { return static_cast<int32_t>(corner_vertex.size() / 3); }
  int32_t num_wedges() const { return static_cast<int32_t>(wedge_vertex.size()); }

  // corner_wedge/wedge_vertex may be empty when the mesh has no per-wedge
  // channels: then every vertex is its own wedge. face_group may be empty:
  // then every face is in group 0. Refinement uses both to save memory.
  bool has_wedges() const { return !corner_wedge.empty(); }
  int32_t wedge_of(int32_t c) const { return corner_wedge.empty() ? corner_vertex[c] : corner_wedge[c]; }
  int32_t group_of(int32_t f) const { return face_group.empty() ? 0 : face_group[f]; }
  int32_t wedge_count() const { return has_wedges() ? num_wedges() : num_vertices(); }
  // Makes corner_wedge/face_group explicit again (identity / zeros).
  void materialize();

  // Adds a wedge for |vertex| with all channel values zero; returns its index.
  int32_t add_wedge(int32_t vertex);
  // Index of the channel with that name, or -1.
  int find_channel(const std::string& name) const;
};

// Geometry facts used by tests and statistics.
struct Aabb {
  float lo[3] = {0, 0, 0};
  float hi[3] = {0, 0, 0};
  double diagonal() const;
};
Aabb bounding_box(const Mesh& mesh);

// Drops faces with a repeated vertex (SPEC §2); returns how many were dropped.
int64_t drop_degenerate_faces(Mesh& mesh);

}  // namespace iteas
