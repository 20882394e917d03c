// Helpers shared by the test files: mesh files shipped under tests/data and,
// when present, the whole corpus under ../shared/meshes (ITEAS_CORPUS overrides).
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "core/mesh.h"
#include "io/document.h"

namespace iteas::test {

std::string data_dir();    // tests/data
std::string corpus_dir();  // "" when the corpus is absent
std::vector<uint8_t> read_bytes(const std::string& path);

// Valid meshes: the shipped ones, plus the corpus's valid sections if present.
std::vector<std::string> valid_mesh_files();
// Deliberately broken inputs: tests/data/nasty plus corpus nasty/.
std::vector<std::string> nasty_files();

Status load(const std::string& path, Document* doc);

// Every mesh of the valid files that loads, with between |min_faces| and
// |max_faces| triangles; named "path#index" (big ones are left to the
// corpus-wide CLI test to keep the suites quick).
struct NamedMesh {
  std::string name;
  Mesh mesh;
};
std::vector<NamedMesh> valid_meshes(int64_t max_faces, int64_t min_faces = 0);

// Facts computed by brute force from faces alone (by vertex index).
struct EdgeFacts {
  int64_t edges = 0;            // undirected
  int64_t boundary_corners = 0; // face sides without a proper partner
  int64_t non_manifold = 0;     // edges with 3+ face uses
  int64_t conflicts = 0;        // 2 uses in the same direction
  int64_t boundary_loops = 0;   // loops of the unmatched directed edges
};
EdgeFacts edge_facts(const Mesh& m);
int64_t euler_characteristic(const Mesh& m);  // V (used) - E + F

// Generated shapes.
Mesh icosphere(int subdivisions);
Mesh planar_grid(int n, const double origin[3], const double u[3], const double v[3]);
// Two tetrahedra, (0, 1, 2, 3) and (0, 4, 5, 6), sharing vertex 0: a vertex
// with two closed fans of three faces.
Mesh two_tetrahedra_sharing_a_vertex();

}  // namespace iteas::test
