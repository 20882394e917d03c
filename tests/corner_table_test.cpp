// Corner-table invariants on every mesh we have (issue 2, point 4).
#include <gtest/gtest.h>

#include <atomic>
#include <stdexcept>

#include "core/corner_table.h"
#include "core/parallel.h"
#include "tests/support.h"

namespace iteas {
namespace {

TEST(CornerTable, InvariantsOnEveryMesh) {
  int checked = 0;
  for (const std::string& path : test::valid_mesh_files()) {
    Document doc;
    if (!test::load(path, &doc).ok()) continue;  // point clouds: covered by io tests
    for (MeshSlot& slot : doc.meshes) {
      Mesh m = slot.mesh;
      const test::EdgeFacts brute = test::edge_facts(m);
      CornerTable ct;
      const TopologyReport rep = ct.build(m, true, 2);
      SCOPED_TRACE(path);
      EXPECT_EQ(rep.boundary_edges, brute.boundary_corners);
      EXPECT_EQ(rep.non_manifold_edges, brute.non_manifold);
      EXPECT_EQ(rep.orientation_conflicts, brute.conflicts);
      const Array<int32_t>& cv = m.corner_vertex;
      for (int32_t c = 0; c < ct.num_corners(); ++c) {
        const int32_t d = ct.opposite(c);
        if (d < 0) continue;
        ASSERT_EQ(ct.opposite(d), c);
        ASSERT_NE(d / 3, c / 3);
        // The two faces share the edge, reversed.
        ASSERT_EQ(cv[next_corner(c)], cv[prev_corner(d)]);
        ASSERT_EQ(cv[prev_corner(c)], cv[next_corner(d)]);
      }
      // After splitting, every vertex has one fan: walking it from its corner
      // visits exactly the corners that reference it.
      std::vector<int32_t> count(m.num_vertices(), 0);
      for (int32_t v : cv) ++count[v];
      for (int32_t v = 0; v < m.num_vertices(); ++v) {
        const int32_t first = ct.vertex_corner(v);
        if (count[v] == 0) continue;
        ASSERT_GE(first, 0);
        int32_t n = 0, c = first;
        do { ++n; c = ct.swing_right(c); } while (c >= 0 && c != first && n <= count[v]);
        ASSERT_EQ(n, count[v]) << "vertex " << v;
      }
      ++checked;
    }
  }
  EXPECT_GT(checked, 20);
}

TEST(CornerTable, CutsNonManifoldAndConflicts) {
  // Three triangles on one edge (0,1) and a fourth glued with the wrong orientation.
  Mesh m;
  m.positions = {0, 0, 0, 1, 0, 0, 0, 1, 0, 0, -1, 0, 0, 0, 1, 1, 1, 1, 2, 2, 2};
  m.corner_vertex = {0, 1, 2, 1, 0, 3, 0, 1, 4, /* conflict pair: */ 2, 5, 6, 2, 5, 1};
  m.face_group.assign(5, 0);
  m.materialize();
  const test::EdgeFacts brute = test::edge_facts(m);
  CornerTable ct;
  const TopologyReport rep = ct.build(m, true, 1);
  EXPECT_EQ(rep.non_manifold_edges, 1);
  EXPECT_EQ(rep.orientation_conflicts, 2);  // (2,5) and (1,2)
  EXPECT_EQ(brute.conflicts, 2);
  EXPECT_EQ(rep.boundary_edges, brute.boundary_corners);
}

}  // namespace
}  // namespace iteas

// A block that throws (a memory budget, bad_alloc) must not terminate the
// process: every thread is joined and the exception reaches the caller.
TEST(Parallel, ExceptionsReachTheCallerAfterEveryThreadJoined) {
  for (int thrower = 0; thrower < 4; ++thrower) {
    std::atomic<int64_t> done{0};
    EXPECT_THROW(iteas::parallel_for(4000, 4, [&](int64_t b, int64_t e) {
      if (b / 1000 == thrower) throw std::runtime_error("block failed");
      done += e - b;
    }, 1000), std::runtime_error);
    EXPECT_EQ(done.load(), 3000) << "the other blocks ran to the end";
  }
}
