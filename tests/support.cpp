#include "tests/support.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <map>
#include <unordered_map>

namespace fs = std::filesystem;

namespace iteas::test {

std::string data_dir() { return ITEAS_SOURCE_DIR "/tests/data"; }

std::string corpus_dir() {
  if (const char* env = std::getenv("ITEAS_CORPUS")) return fs::is_directory(env) ? env : "";
  const std::string d = ITEAS_SOURCE_DIR "/../shared/meshes";
  return fs::is_directory(d) ? d : "";
}

std::vector<uint8_t> read_bytes(const std::string& path) {
  std::ifstream f(path, std::ios::binary);
  return std::vector<uint8_t>(std::istreambuf_iterator<char>(f), std::istreambuf_iterator<char>());
}

static void add_dir(const std::string& dir, std::vector<std::string>& out) {
  if (!fs::is_directory(dir)) return;
  std::vector<std::string> files;
  for (const auto& e : fs::directory_iterator(dir))
    if (e.is_regular_file() && e.path().extension() != ".md") files.push_back(e.path().string());
  std::sort(files.begin(), files.end());
  out.insert(out.end(), files.begin(), files.end());
}

std::vector<std::string> valid_mesh_files() {
  std::vector<std::string> out;
  add_dir(data_dir(), out);
  const std::string c = corpus_dir();
  if (!c.empty())
    for (const char* s : {"gltf", "gltf-draco", "drc", "classic", "classic-converted"}) add_dir(c + "/" + s, out);
  return out;
}

std::vector<std::string> nasty_files() {
  std::vector<std::string> out;
  add_dir(data_dir() + "/nasty", out);
  const std::string c = corpus_dir();
  if (!c.empty()) add_dir(c + "/nasty", out);
  return out;
}

Status load(const std::string& path, Document* doc) {
  const std::vector<uint8_t> b = read_bytes(path);
  return read_document(b.data(), b.size(), sniff_format(b.data(), b.size(), path), ReadLimits(), doc);
}

std::vector<NamedMesh> valid_meshes(int64_t max_faces, int64_t min_faces) {
  std::vector<NamedMesh> out;
  for (const std::string& path : valid_mesh_files()) {
    Document d;
    if (!load(path, &d).ok()) continue;  // point clouds: covered by the io tests
    for (MeshSlot& s : d.meshes)
      if (s.mesh.num_faces() >= min_faces && s.mesh.num_faces() <= max_faces)
        out.push_back({path + "#" + std::to_string(&s - d.meshes.data()), s.mesh});
  }
  return out;
}

EdgeFacts edge_facts(const Mesh& m) {
  // Each face side as its undirected edge (smaller vertex in the high bits)
  // and, in the lowest bit, 0 when it runs from the smaller vertex to the
  // larger (1 otherwise, a degenerate side included); sorted, an edge's
  // uses lie side by side. (A std::map of edges took most of the time of
  // the tests that call this on every mesh.)
  const int32_t nc = int32_t(m.corner_vertex.size());
  std::vector<uint64_t> sides(size_t(nc), 0);
  for (int32_t c = 0; c < nc; ++c) {
    const int32_t f = c / 3, k = c % 3;
    const int32_t a = m.corner_vertex[3 * f + (k + 1) % 3], b = m.corner_vertex[3 * f + (k + 2) % 3];
    const uint64_t key = uint64_t(uint32_t(std::min(a, b))) << 32 | uint32_t(std::max(a, b));
    sides[size_t(c)] = key << 1 | uint64_t(!(a < b));
  }
  std::sort(sides.begin(), sides.end());
  EdgeFacts e;
  std::unordered_map<int32_t, std::vector<int32_t>> next;  // unmatched directed edges
  for (size_t i = 0; i < sides.size();) {
    const uint64_t key = sides[i] >> 1;
    int32_t forward = 0, backward = 0;
    for (; i < sides.size() && sides[i] >> 1 == key; ++i) (sides[i] & 1 ? backward : forward)++;
    ++e.edges;
    const int32_t n = forward + backward;
    if (n == 2 && forward == 1) continue;
    e.boundary_corners += n;
    if (n >= 3) ++e.non_manifold;
    else if (n == 2) ++e.conflicts;
    if (n == 1) {
      const int32_t lo = int32_t(key >> 32), hi = int32_t(key & 0xFFFFFFFFu);
      if (forward) next[lo].push_back(hi);
      else next[hi].push_back(lo);
    }
  }
  // Loops of single-use edges (manifold boundary only).
  std::unordered_map<int32_t, size_t> cursor;
  for (auto& [start, outs] : next) {
    while (cursor[start] < outs.size()) {
      int32_t v = start;
      ++e.boundary_loops;
      for (int guard = 0; guard < 100000000; ++guard) {
        auto it = next.find(v);
        if (it == next.end() || cursor[v] >= it->second.size()) break;
        v = it->second[cursor[v]++];
        if (v == start) break;
      }
    }
  }
  return e;
}

int64_t euler_characteristic(const Mesh& m) {
  std::vector<uint8_t> used(m.num_vertices(), 0);
  int64_t v = 0;
  for (int32_t x : m.corner_vertex) if (!used[x]) { used[x] = 1; ++v; }
  return v - edge_facts(m).edges + m.num_faces();
}

Mesh icosphere(int subdivisions) {
  const double t = (1.0 + std::sqrt(5.0)) / 2.0;
  std::vector<std::array<double, 3>> p = {{-1, t, 0}, {1, t, 0}, {-1, -t, 0}, {1, -t, 0}, {0, -1, t}, {0, 1, t},
                                          {0, -1, -t}, {0, 1, -t}, {t, 0, -1}, {t, 0, 1}, {-t, 0, -1}, {-t, 0, 1}};
  std::vector<std::array<int32_t, 3>> f = {{0, 11, 5}, {0, 5, 1}, {0, 1, 7}, {0, 7, 10}, {0, 10, 11}, {1, 5, 9}, {5, 11, 4},
                                           {11, 10, 2}, {10, 7, 6}, {7, 1, 8}, {3, 9, 4}, {3, 4, 2}, {3, 2, 6}, {3, 6, 8},
                                           {3, 8, 9}, {4, 9, 5}, {2, 4, 11}, {6, 2, 10}, {8, 6, 7}, {9, 8, 1}};
  for (int s = 0; s < subdivisions; ++s) {
    std::map<std::pair<int32_t, int32_t>, int32_t> mid;
    auto midpoint = [&](int32_t a, int32_t b) {
      auto key = std::make_pair(std::min(a, b), std::max(a, b));
      auto it = mid.find(key);
      if (it != mid.end()) return it->second;
      p.push_back({(p[a][0] + p[b][0]) / 2, (p[a][1] + p[b][1]) / 2, (p[a][2] + p[b][2]) / 2});
      return mid[key] = int32_t(p.size() - 1);
    };
    std::vector<std::array<int32_t, 3>> nf;
    for (auto& tri : f) {
      const int32_t a = midpoint(tri[0], tri[1]), b = midpoint(tri[1], tri[2]), c = midpoint(tri[2], tri[0]);
      nf.push_back({tri[0], a, c});
      nf.push_back({tri[1], b, a});
      nf.push_back({tri[2], c, b});
      nf.push_back({a, b, c});
    }
    f.swap(nf);
  }
  Mesh m;
  for (auto& q : p) {
    const double l = std::sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2]);
    for (int k = 0; k < 3; ++k) m.positions.push_back(float(q[k] / l));
  }
  for (auto& tri : f) {
    for (int k = 0; k < 3; ++k) m.corner_vertex.push_back(tri[k]);
    m.face_group.push_back(0);
  }
  m.materialize();
  return m;
}

Mesh planar_grid(int n, const double o[3], const double u[3], const double v[3]) {
  Mesh m;
  for (int j = 0; j <= n; ++j)
    for (int i = 0; i <= n; ++i)
      for (int k = 0; k < 3; ++k) m.positions.push_back(float(o[k] + u[k] * i / n + v[k] * j / n));
  auto id = [&](int i, int j) { return int32_t(j * (n + 1) + i); };
  for (int j = 0; j < n; ++j)
    for (int i = 0; i < n; ++i) {
      // Alternate diagonals so valences vary (4, 6, 8), not just a regular grid.
      if ((i + j) % 2 == 0) {
        m.corner_vertex.insert(m.corner_vertex.end(), {id(i, j), id(i + 1, j), id(i + 1, j + 1), id(i, j), id(i + 1, j + 1), id(i, j + 1)});
      } else {
        m.corner_vertex.insert(m.corner_vertex.end(), {id(i, j), id(i + 1, j), id(i, j + 1), id(i + 1, j), id(i + 1, j + 1), id(i, j + 1)});
      }
      m.face_group.insert(m.face_group.end(), {0, 0});
    }
  m.materialize();
  return m;
}

Mesh two_tetrahedra_sharing_a_vertex() {
  Mesh m;
  m.positions = {0, 0, 0, 1, 0, 0, 0, 1, 0, 0, 0, 1, -1, 0, 0, 0, -1, 0, 0, 0, -1};
  m.corner_vertex = {0, 2, 1, 0, 1, 3, 0, 3, 2, 1, 2, 3,   // tetrahedron (0, 1, 2, 3)
                     0, 5, 4, 0, 4, 6, 0, 6, 5, 4, 5, 6};  // tetrahedron (0, 4, 5, 6)
  m.face_group.assign(8, 0);
  m.materialize();
  return m;
}

}  // namespace iteas::test
