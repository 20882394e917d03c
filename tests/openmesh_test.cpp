// Differential test: our uniform modified Butterfly against OpenMesh's
// ModifiedButterflyT on closed manifold meshes (issue 3, point 1).
#include <gtest/gtest.h>

#include <OpenMesh/Core/Mesh/TriMesh_ArrayKernelT.hh>
#include <OpenMesh/Tools/Subdivider/Uniform/ModifiedButterFlyT.hh>

#include <cmath>
#include <unordered_map>

#include "core/refine.h"
#include "tests/openmesh_adapter.h"
#include "tests/support.h"

namespace iteas {
namespace {

struct Traits : OpenMesh::DefaultTraits {
  typedef OpenMesh::Vec3d Point;  // double, so the comparison measures the schemes, not rounding
};
using OMesh = OpenMesh::TriMesh_ArrayKernelT<Traits>;

std::vector<double> openmesh_refine(const Mesh& m, int levels) {
  OMesh om;
  test::to_openmesh(m, om);
  OpenMesh::Subdivider::Uniform::ModifiedButterflyT<OMesh> bf;
  bf.attach(om);
  bf(size_t(levels));
  bf.detach();
  std::vector<double> p;
  for (auto v : om.vertices())
    for (int k = 0; k < 3; ++k) p.push_back(om.point(v)[k]);
  return p;
}

// Max over our vertices of the distance to the nearest OpenMesh vertex and
// vice versa (vertex orders differ), via a uniform grid.
double symmetric_max_distance(const std::vector<double>& a, const Array<float>& b, double cell) {
  auto key = [&](double x, double y, double z) {
    return (int64_t(std::floor(x / cell)) * 73856093) ^ (int64_t(std::floor(y / cell)) * 19349663) ^
           (int64_t(std::floor(z / cell)) * 83492791);
  };
  auto one_way = [&](const auto& from, const auto& to) {
    std::unordered_multimap<int64_t, size_t> grid;
    for (size_t i = 0; i < to.size() / 3; ++i) grid.emplace(key(to[3 * i], to[3 * i + 1], to[3 * i + 2]), i);
    double worst = 0;
    for (size_t i = 0; i < from.size() / 3; ++i) {
      double best = INFINITY;
      for (int dx = -1; dx <= 1; ++dx)
        for (int dy = -1; dy <= 1; ++dy)
          for (int dz = -1; dz <= 1; ++dz) {
            auto range = grid.equal_range(key(from[3 * i] + dx * cell, from[3 * i + 1] + dy * cell, from[3 * i + 2] + dz * cell));
            for (auto it = range.first; it != range.second; ++it) {
              double d = 0;
              for (int k = 0; k < 3; ++k) d += (double(from[3 * i + k]) - double(to[3 * it->second + k])) * (double(from[3 * i + k]) - double(to[3 * it->second + k]));
              best = std::min(best, std::sqrt(d));
            }
          }
      worst = std::max(worst, best);
    }
    return worst;
  };
  return std::max(one_way(a, b), one_way(b, a));
}

void compare(const std::string& name, const Mesh& input, int max_level) {
  const double diag = bounding_box(input).diagonal();
  for (int level = 1; level <= max_level; ++level) {
    Mesh ours = input;
    RefineOptions o;
    o.mode = Mode::kUniform;
    o.levels = level;
    o.max_triangles = int64_t(1) << 40;
    RefineStats st;
    refine_mesh(ours, o, RefineHooks(), &st);
    const std::vector<double> theirs = openmesh_refine(input, level);
    ASSERT_EQ(int64_t(theirs.size() / 3), int64_t(ours.num_vertices())) << name << " level " << level;
    const double d = symmetric_max_distance(theirs, ours.positions, 1e-4 * diag);
    EXPECT_LE(d, 1e-5 * diag) << name << " level " << level;
  }
}

TEST(OpenMeshDifferential, GeneratedIcosphere) { compare("icosphere", test::icosphere(2), 3); }

TEST(OpenMeshDifferential, ClosedCorpusMeshes) {
  const std::vector<std::pair<std::string, int>> files = {
      {test::data_dir() + "/eight.off", 3}, {test::data_dir() + "/decimated-knight.off", 3}, {test::data_dir() + "/bunny-npm.obj", 3}};
  std::vector<std::pair<std::string, int>> all = files;
  if (!test::corpus_dir().empty())
    for (const char* f : {"/classic/kitten.nf20k.off", "/classic/bunny.off", "/classic/3holes.off"})
      all.push_back({test::corpus_dir() + f, 3});
  for (const auto& [path, levels] : all) {
    Document d;
    ASSERT_TRUE(test::load(path, &d).ok()) << path;
    compare(path, d.meshes[0].mesh, levels);
  }
}

}  // namespace
}  // namespace iteas
