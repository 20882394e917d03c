// Fuzz target: the core on arbitrary index buffers — corner table (cuts,
// splits), then one or two levels in every mode. Positions come from the
// input too, so degenerate and non-finite-free odd geometry is exercised.
// With bit 128 of the second byte, the mesh carries normals and tangents
// (and seams): the oracles below then compare them too, and the refined
// mesh's smoothing groups and sums are checked against the rule.
#include <algorithm>
#include <cstddef>
#include <cstdint>
#include <cstring>

#include "core/corner_table.h"
#include "core/cpu_features.h"
#include "core/refine.h"
#include "tests/normal_rule.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  if (size < 4) return 0;
  const int nv = 3 + data[0] % 29;
  const int mode = data[1] % 3, levels = 1 + data[2] % 2;
  size_t at = 3;
  iteas::Mesh m;
  for (int v = 0; v < nv; ++v)
    for (int k = 0; k < 3; ++k) m.positions.push_back(at < size ? float(int8_t(data[at++])) : float(v * 3 + k));
  while (at + 3 <= size) {
    for (int k = 0; k < 3; ++k) m.corner_vertex.push_back(data[at++] % nv);
  }
  if (m.corner_vertex.empty()) return 0;
  m.face_group.assign(m.corner_vertex.size() / 3, 0);
  m.materialize();
  iteas::drop_degenerate_faces(m);
  if (m.num_faces() == 0) return 0;
  const bool attributes = (data[1] & 128) != 0;
  if (attributes) {
    // Normals and tangents drawn from a few values, some corners with a
    // wedge of their own (seams), no face groups (the uniform levels' wider
    // children routine then takes the wedges too).
    m.face_group.clear();
    iteas::Channel normal, tangent;
    normal.name = "NORMAL";
    normal.components = 3;
    normal.kind = iteas::ChannelKind::kNormal;
    tangent.name = "TANGENT";
    tangent.components = 4;
    tangent.kind = iteas::ChannelKind::kTangent;
    const float values[4][4] = {{0, 0, 1, 1}, {0, 1, 0, -1}, {0.6f, 0, 0.8f, 0}, {-0.0f, 0, 1, -1}};
    auto add_values = [&](size_t pick) {
      for (int k = 0; k < 3; ++k) normal.data.push_back(values[pick % 4][k]);
      for (int k = 0; k < 4; ++k) tangent.data.push_back(values[(pick / 4) % 4][(k + 1) % 4]);
    };
    for (int32_t w = 0; w < m.num_wedges(); ++w) add_values(data[3 + size_t(w) % (size - 3)]);
    for (size_t c = 0; c < m.corner_wedge.size(); ++c) {
      const uint8_t b = data[3 + (c * 7) % (size - 3)];
      if (!(b & 1)) continue;
      m.corner_wedge[c] = int32_t(m.wedge_vertex.size());
      m.wedge_vertex.push_back(m.corner_vertex[c]);
      add_values(b >> 1);
    }
    m.channels.push_back(normal);
    m.channels.push_back(tangent);
  }
  {
    // Oracle: the corner table's matching in AVX-512 registers, in AVX2
    // registers (where the processor has them) and with SSE2 alone give the
    // same table, fan orders and fan neighbours included.
    iteas::Mesh a = m;
    iteas::CornerTable narrow;
    const iteas::TopologyReport ra = narrow.build(a, true, 1, true, false);
    auto check = [&](bool wide) {
      iteas::Mesh b = m;
      iteas::CornerTable t;
      const iteas::TopologyReport rb = t.build(b, true, 1, true, wide);
      bool same = a.corner_vertex == b.corner_vertex && narrow.opposites() == t.opposites() &&
                  narrow.fans() == t.fans() && ra.boundary_edges == rb.boundary_edges &&
                  ra.non_manifold_edges == rb.non_manifold_edges && ra.split_vertices == rb.split_vertices;
      for (int32_t v = 0; same && v < a.num_vertices(); ++v) {
        same = narrow.vertex_corner(v) == t.vertex_corner(v);
        const int32_t *oa = narrow.fan_order(v), *ob = t.fan_order(v);
        const int32_t *na = narrow.fan_neighbours(v), *nb = t.fan_neighbours(v);
        same = same && (oa == nullptr) == (ob == nullptr) && (na == nullptr) == (nb == nullptr);
        const int32_t n = oa ? (narrow.fans()[v] < 0 ? -narrow.fans()[v] : narrow.fans()[v]) : 0;
        for (int32_t j = 0; same && j < n; ++j) same = oa[j] == ob[j] && (!na || na[j] == nb[j]);
      }
      if (!same) __builtin_trap();
    };
    check(true);
#if ITEAS_X86_FEATURES
    iteas::cpu_feature_cap() = int(iteas::CpuFeature::kAvx2);
    check(true);
    iteas::cpu_feature_cap() = int(iteas::CpuFeature::kAvx512);
#endif
  }
  iteas::RefineOptions o;
  o.mode = mode == 0 ? iteas::Mode::kIteas : (mode == 1 ? iteas::Mode::kUniform : iteas::Mode::kFixed);
  o.levels = levels;
  o.threads = 1;
  o.threshold.kind = mode == 2 ? iteas::ThresholdSpec::Kind::kDegrees : iteas::ThresholdSpec::Kind::kMean;
  o.threshold.value = 5;
  o.crease_angle = (data[2] & 4) ? 60 : 0;
  o.stall_ratio = (data[2] & 8) ? 0.999 : -1;  // stall detection in fixed mode too
  if (data[2] & 32) o.tolerance = o.flat_limit = 0.05;  // geometric tolerances in fixed mode too, coarse
  o.max_triangles = 20000;
  iteas::Mesh two = (data[2] & 16) ? m : iteas::Mesh();
  iteas::Mesh narrow = (data[2] & 64) ? m : iteas::Mesh();
  iteas::Mesh fresh = (data[2] & 128) ? m : iteas::Mesh(), walked = fresh;
  iteas::RefineStats st;
  iteas::refine_mesh(m, o, iteas::RefineHooks(), &st);
  // The input refined again (|again|, a copy of it) with other threads or
  // routines must give the same mesh, bit for bit, after as many levels.
  auto same_again = [&](iteas::Mesh& again, int threads, const iteas::RefineHooks& hooks) {
    o.threads = threads;
    iteas::RefineStats st2;
    iteas::refine_mesh(again, o, hooks, &st2);
    if (again.positions.size() != m.positions.size() || again.corner_vertex != m.corner_vertex ||
        std::memcmp(again.positions.data(), m.positions.data(), m.positions.size() * sizeof(float)) != 0 ||
        st2.triangles_out != st.triangles_out || st2.levels.size() != st.levels.size() ||
        again.corner_wedge != m.corner_wedge || again.wedge_vertex != m.wedge_vertex ||
        again.channels.size() != m.channels.size())
      __builtin_trap();
    for (size_t i = 0; i < m.channels.size(); ++i) {
      const iteas::Array<float>&x = again.channels[i].data, &y = m.channels[i].data;
      if (x.size() != y.size() || std::memcmp(x.data(), y.data(), x.size() * sizeof(float)) != 0) __builtin_trap();
    }
    // The statistics too: T, the input's and the output's angle summaries
    // and triangle quality, and every level's counts (on two threads a small
    // uniform job takes the input's angles beside its first level).
    auto same_summary = [](const iteas::AngleSummary& a, const iteas::AngleSummary& b) {
      return a.edges == b.edges && a.above == b.above && a.histogram == b.histogram &&
             std::memcmp(&a.mean, &b.mean, sizeof(double)) == 0 && std::memcmp(&a.max, &b.max, sizeof(double)) == 0;
    };
    auto same_quality = [](const iteas::QualitySummary& a, const iteas::QualitySummary& b) {
      return std::memcmp(&a.min_angle, &b.min_angle, sizeof(double)) == 0 &&
             std::memcmp(&a.p1_angle, &b.p1_angle, sizeof(double)) == 0;
    };
    if (std::memcmp(&st2.threshold, &st.threshold, sizeof(double)) != 0 || st2.stopped_by != st.stopped_by ||
        !same_summary(st2.before, st.before) || !same_summary(st2.after, st.after) ||
        !same_quality(st2.quality_before, st.quality_before) || !same_quality(st2.quality_after, st.quality_after))
      __builtin_trap();
    for (size_t l = 0; l < st.levels.size(); ++l) {
      const iteas::LevelStats &a = st2.levels[l], &b = st.levels[l];
      if (a.faces_selected != b.faces_selected || a.red_splits != b.red_splits || a.green_splits != b.green_splits ||
          a.greens_merged != b.greens_merged || a.vertices_added != b.vertices_added ||
          a.vertices_guarded != b.vertices_guarded || a.triangles_after != b.triangles_after)
        __builtin_trap();
    }
  };
  if (attributes) {
    // Oracle: the refined mesh's smoothing groups and their sums (a split
    // face's children summed together) against the rule written plainly:
    // groups by vertex and normal bits, each group's faces' cross products
    // added in face order.
    const int ni = m.find_channel("NORMAL");
    if (ni < 0) __builtin_trap();
    const iteas::Array<int32_t> group = iteas::smoothing_groups(m, ni, 1);
    const iteas::Array<double> sums = iteas::smoothing_group_sums(m, group, 1);
    const iteas::test::NormalRule rule = iteas::test::normal_rule(m, ni);
    if (!std::equal(group.begin(), group.end(), rule.group.begin(), rule.group.end()) ||
        sums.size() != rule.sums.size() ||
        std::memcmp(sums.data(), rule.sums.data(), sums.size() * sizeof(double)) != 0)
      __builtin_trap();
  }
  if (data[2] & 16) {
    // Oracle: two threads (the worker pool, pieces claimed in any order).
    // Exactly two: left to choose, the refinement takes one for a job this
    // small while the worker sleeps.
    iteas::RefineHooks exact;
    exact.choose_threads = false;
    same_again(two, 2, exact);
  }
  if (data[2] & 64) {
    // Oracle: the baseline routines (SSE2) against the wider ones the
    // processor has (AVX sums, AVX2 matching, the AVX-512 loops of uniform
    // levels: canonical corners, ring offsets, children and their opposites).
    iteas::RefineHooks baseline;
    baseline.wide = false;
    same_again(narrow, 1, baseline);
  }
  if (data[2] & 128) {
    // Oracle: adaptive levels' extraordinary rules read from a table of the
    // level's rings (build_level_rings) against walks of the fans. Without
    // carried deviations every adaptive level makes the table, those with
    // green pairs included; both must give the mesh of the first run.
    iteas::RefineHooks every_level;
    every_level.carry = false;
    same_again(fresh, 1, every_level);
    iteas::RefineHooks no_table = every_level;
    no_table.level_rings = false;
    same_again(walked, 1, no_table);
  }
  return 0;
}
