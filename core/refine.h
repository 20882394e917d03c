// The IteAS iteration driver (SPEC §2): angles -> threshold -> selection ->
// red-green closure -> Butterfly refinement, level after level.
//
// Each level is split OpenSubdiv-style into a topology pass (which edges split,
// new connectivity, parent->child maps) and a data pass that applies stencil
// weights computed on the *old* level to positions, morph deltas and wedges.
// Old vertices never move. The data pass runs on all threads; results are
// bit-identical for any thread count.
#pragma once

#include <atomic>
#include <cstdint>
#include <functional>
#include <string>
#include <vector>

#include "core/angles.h"
#include "core/corner_table.h"
#include "core/mesh.h"
#include "core/options.h"

namespace iteas {

struct LevelStats {
  int level = 0;
  double threshold = 0;
  int64_t faces_selected = 0;
  int64_t faces_stalled = 0;  // above T but not selected: bending as much as their parent did
  int64_t faces_within_tolerance = 0;  // above T but not selected: the split would move the surface <= tolerance
  int64_t faces_over_flat_limit = 0;   // selected although not above T: deviation > flat_limit (in faces_selected)
  int64_t red_splits = 0;     // faces split 1 -> 4
  int64_t green_splits = 0;   // faces bisected to close a crack
  int64_t greens_merged = 0;  // green pairs merged back into their parent
  int64_t vertices_added = 0;
  int64_t vertices_guarded = 0;  // new vertices pulled toward their edge midpoint (sliver guard)
  int64_t triangles_after = 0;
  double mean_theta_after = 0, max_theta_after = 0;
  double ms = 0;
};

struct RefineStats {
  int64_t triangles_in = 0, vertices_in = 0, triangles_out = 0, vertices_out = 0;
  double threshold = 0;            // T of the first level
  std::vector<LevelStats> levels;  // one row per level performed
  std::string stopped_by;          // converged | stalled | max_levels | budget | cancelled
                                   // (converged: nothing left to select, within tolerance included)
  AngleSummary before, after;      // "above" counts edges above T
  QualitySummary quality_before, quality_after;
  int64_t uniform_triangles = 0;   // uniform subdivision to the same level
  double reduction_percent = 0;    // 100 (1 - triangles_out / uniform_triangles)
  TopologyReport topology;
  bool budget_clamped = false;
  int64_t peak_bytes = 0;          // peak bytes of the core's mesh structures
  double ms_topology = 0, ms_refine = 0;
};

struct RefineHooks {
  // Injected clock in milliseconds (the core reads no clock itself); may be empty.
  std::function<double()> now_ms;
  // Called per level and phase ("analyse", "refine"), fraction in [0, 1].
  std::function<void(int level, const char* phase, double fraction)> progress;
  // Honoured between phases.
  const std::atomic<bool>* cancel = nullptr;
  // Testing: refine uniform levels with the general adaptive path.
  bool force_adaptive_path = false;
  // Testing: false recomputes every adaptive level's angles and deviations
  // instead of carrying those of unchanged edges from the level before.
  bool carry = true;
  // Testing: false builds every adaptive level's corner table from scratch
  // instead of renumbering the old one and matching only round changed faces.
  bool incremental_table = true;
  // Testing: false walks an extraordinary vertex's fan for each of its edges
  // on every adaptive level instead of reading the level's rings
  // (build_level_rings) where most edges are measured afresh.
  bool level_rings = true;
  // Testing: called on each adaptive level whose selection measures
  // deviations, with every corner's deviation of that level once they are
  // made (-1: not computed, the edge's faces needing none; carried or
  // computed afresh alike).
  std::function<void(const float* deviation, int64_t corners)> deviations;
  // Benchmarks: false skips the smoothness and quality statistics of uniform
  // refinement (θ after each level, triangle angles before and after), to time
  // the subdivision alone. Adaptive modes need θ and compute it regardless.
  bool statistics = true;
  // Testing: false runs on exactly the threads the options give, where the
  // refinement would otherwise take one for a small job (threads_for).
  bool choose_threads = true;
  // Testing: false keeps the input's face and vertex order in uniform mode
  // (see order_faces_spatially; the output is then the same mesh numbered
  // as the input is).
  bool spatial_order = true;
  // Testing: false takes the baseline x86-64 (SSE2) routines where the
  // processor has wider ones (AVX, AVX2, AVX-512); the output is the same.
  bool wide = true;
};

enum class RefineResult { kOk, kCancelled };

RefineResult refine_mesh(Mesh& mesh, const RefineOptions& options, const RefineHooks& hooks,
                         RefineStats* stats);

// The normal channel (the first of kind kNormal with 3 components, if the
// mesh has wedges) recomputed from the faces, as refinement does after its
// last level: each wedge takes the area-weighted sum of the face normals
// over its smoothing group (the wedges of its vertex whose normals are the
// same bit for bit: UV seams stay smooth, hard edges stay hard), summed in
// face order and normalised; a group whose sum is zero keeps its own
// normal, normalised. On up to |threads| threads (<= 0: all cores); the
// result is the same for any count.
void recompute_normals(Mesh& mesh, int threads = 1);
// Its parts (exposed for tests): each wedge's smoothing group, named by the
// group's first wedge, for the normal channel |normal_channel|; and each
// group's sum of its faces' cross products (twice the area times the unit
// normal) in face order, in double precision, 3 per wedge (at the group's
// first wedge; zero elsewhere). Bit for bit what the rule gives, on any
// number of threads.
Array<int32_t> smoothing_groups(const Mesh& mesh, int normal_channel, int threads = 1);
Array<double> smoothing_group_sums(const Mesh& mesh, const Array<int32_t>& group, int threads = 1);

// Every tangent channel (kind kTangent, 3 or 4 components) made orthogonal to
// the normal channel NORMAL where there is one (t - (t . n) n) and of unit
// length, in double precision; a tangent of length zero (after that) is left
// as it is; the handedness w (a fourth component) made -1 when negative, else
// 1. As refinement does after recompute_normals. On up to |threads| threads;
// the same result for any count.
void orthogonalise_tangents(Mesh& mesh, int threads = 1);

// Bytes held by the mesh's arrays (capacity), for the memory statistics.
int64_t mesh_bytes(const Mesh& mesh);

}  // namespace iteas
