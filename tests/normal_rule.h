// The rule recompute_normals follows, written plainly (a map, one face at a
// time), for the tests and the fuzz target to check it against.
#pragma once

#include <array>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <map>
#include <utility>
#include <vector>

#include "core/mesh.h"

namespace iteas::test {

// A wedge's normal as bits (+0 and -0 apart).
inline std::array<uint32_t, 3> normal_bits(const Channel& normal, int32_t w) {
  std::array<uint32_t, 3> b;
  std::memcpy(b.data(), &normal.data[3 * size_t(w)], 12);
  return b;
}

// What recompute_normals must give, by its rule: wedges grouped by (vertex,
// normal bits) in a map, a group named by its first wedge; each group's
// faces' cross products summed in face order (3 per wedge, at the group's
// first wedge); each wedge's normal its group's sum normalised (a group with
// a zero sum keeps its own normal, normalised).
struct NormalRule {
  std::vector<int32_t> group;
  std::vector<double> sums;
  std::vector<float> normals;
};
inline NormalRule normal_rule(const Mesh& m, int channel) {
  const Channel& normal = m.channels[size_t(channel)];
  const int32_t nw = m.num_wedges();
  NormalRule r;
  std::map<std::pair<int32_t, std::array<uint32_t, 3>>, int32_t> first;
  for (int32_t w = 0; w < nw; ++w)
    r.group.push_back(first.try_emplace(std::make_pair(m.wedge_vertex[w], normal_bits(normal, w)), w).first->second);
  r.sums.assign(3 * size_t(nw), 0.0);
  for (int32_t f = 0; f < m.num_faces(); ++f) {
    const float* a = &m.positions[3 * size_t(m.corner_vertex[3 * f])];
    const float* b = &m.positions[3 * size_t(m.corner_vertex[3 * f + 1])];
    const float* c = &m.positions[3 * size_t(m.corner_vertex[3 * f + 2])];
    const double u[3] = {double(b[0]) - a[0], double(b[1]) - a[1], double(b[2]) - a[2]};
    const double v[3] = {double(c[0]) - a[0], double(c[1]) - a[1], double(c[2]) - a[2]};
    const double n[3] = {u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0]};
    for (int k = 0; k < 3; ++k) {
      const int32_t g = r.group[size_t(m.corner_wedge[3 * f + k])];
      for (int i = 0; i < 3; ++i) r.sums[3 * size_t(g) + i] += n[i];
    }
  }
  r.normals.assign(normal.data.begin(), normal.data.end());
  for (int32_t w = 0; w < nw; ++w) {
    const double* n = &r.sums[3 * size_t(r.group[w])];
    float* out = &r.normals[3 * size_t(w)];
    const double len = std::sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2]);
    if (len > 0) {
      for (int i = 0; i < 3; ++i) out[i] = float(n[i] / len);
    } else {
      const double l2 = std::sqrt(double(out[0]) * out[0] + double(out[1]) * out[1] + double(out[2]) * out[2]);
      if (l2 > 0) for (int i = 0; i < 3; ++i) out[i] = float(out[i] / l2);
    }
  }
  return r;
}

}  // namespace iteas::test
