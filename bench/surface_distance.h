// Distances between two triangle surfaces from dense area-weighted samples and
// exact point-to-triangle distances, with a bounding-volume hierarchy.
#pragma once

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <random>
#include <vector>

#include "core/mesh.h"

namespace iteas::eval {

using V3 = std::array<double, 3>;
inline V3 sub(const V3& a, const V3& b) { return {a[0] - b[0], a[1] - b[1], a[2] - b[2]}; }
inline double dot(const V3& a, const V3& b) { return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]; }
inline V3 madd(const V3& a, const V3& d, double t) { return {a[0] + d[0] * t, a[1] + d[1] * t, a[2] + d[2] * t}; }

// Closest point on triangle abc to p (Ericson, Real-Time Collision Detection, 5.1.5).
inline V3 closest_on_triangle(const V3& p, const V3& a, const V3& b, const V3& c) {
  const V3 ab = sub(b, a), ac = sub(c, a), ap = sub(p, a);
  const double d1 = dot(ab, ap), d2 = dot(ac, ap);
  if (d1 <= 0 && d2 <= 0) return a;
  const V3 bp = sub(p, b);
  const double d3 = dot(ab, bp), d4 = dot(ac, bp);
  if (d3 >= 0 && d4 <= d3) return b;
  const double vc = d1 * d4 - d3 * d2;
  if (vc <= 0 && d1 >= 0 && d3 <= 0) return madd(a, ab, d1 / (d1 - d3));
  const V3 cp = sub(p, c);
  const double d5 = dot(ab, cp), d6 = dot(ac, cp);
  if (d6 >= 0 && d5 <= d6) return c;
  const double vb = d5 * d2 - d1 * d6;
  if (vb <= 0 && d2 >= 0 && d6 <= 0) return madd(a, ac, d2 / (d2 - d6));
  const double va = d3 * d6 - d5 * d4;
  if (va <= 0 && (d4 - d3) >= 0 && (d5 - d6) >= 0) return madd(b, sub(c, b), (d4 - d3) / ((d4 - d3) + (d5 - d6)));
  const double denom = 1.0 / (va + vb + vc);
  const double v = vb * denom, w = vc * denom;
  return {a[0] + ab[0] * v + ac[0] * w, a[1] + ab[1] * v + ac[1] * w, a[2] + ab[2] * v + ac[2] * w};
}

class Bvh {
 public:
  explicit Bvh(const Mesh& m) : m_(m) {
    const int32_t nf = m.num_faces();
    order_.resize(nf);
    for (int32_t f = 0; f < nf; ++f) order_[f] = f;
    centroid_.resize(size_t(nf));
    for (int32_t f = 0; f < nf; ++f)
      for (int k = 0; k < 3; ++k)
        centroid_[f][k] = (vtx(f, 0)[k] + vtx(f, 1)[k] + vtx(f, 2)[k]) / 3.0;
    nodes_.reserve(2 * size_t(nf) / kLeaf + 2);
    nodes_.resize(1);
    build(0, 0, nf);
  }

  // Squared distance from p to the surface.
  double distance2(const V3& p) const {
    double best = INFINITY;
    int32_t stack[128];
    int sp = 0;
    stack[sp++] = 0;
    while (sp) {
      const Node& n = nodes_[stack[--sp]];
      if (box_distance2(n, p) >= best) continue;
      if (n.count) {
        for (int32_t i = n.first; i < n.first + n.count; ++i) {
          const int32_t f = order_[i];
          const V3 q = closest_on_triangle(p, vtx(f, 0), vtx(f, 1), vtx(f, 2));
          const V3 d = sub(p, q);
          best = std::min(best, dot(d, d));
        }
      } else {
        const double dl = box_distance2(nodes_[n.left], p), dr = box_distance2(nodes_[n.left + 1], p);
        if (dl < dr) { stack[sp++] = n.left + 1; stack[sp++] = n.left; }
        else { stack[sp++] = n.left; stack[sp++] = n.left + 1; }
      }
    }
    return best;
  }

 private:
  static constexpr int kLeaf = 4;
  struct Node {
    V3 lo, hi;
    int32_t left = 0, first = 0, count = 0;
  };
  V3 vtx(int32_t f, int k) const {
    const float* p = &m_.positions[3 * size_t(m_.corner_vertex[3 * size_t(f) + k])];
    return {p[0], p[1], p[2]};
  }
  static double box_distance2(const Node& n, const V3& p) {
    double d = 0;
    for (int k = 0; k < 3; ++k) {
      const double e = std::max({n.lo[k] - p[k], 0.0, p[k] - n.hi[k]});
      d += e * e;
    }
    return d;
  }
  // Fills node |index|; the two children of an inner node sit side by side.
  void build(int32_t index, int32_t first, int32_t count) {
    Node n;
    n.lo = {INFINITY, INFINITY, INFINITY};
    n.hi = {-INFINITY, -INFINITY, -INFINITY};
    for (int32_t i = first; i < first + count; ++i)
      for (int c = 0; c < 3; ++c) {
        const V3 v = vtx(order_[i], c);
        for (int k = 0; k < 3; ++k) { n.lo[k] = std::min(n.lo[k], v[k]); n.hi[k] = std::max(n.hi[k], v[k]); }
      }
    if (count <= kLeaf) {
      n.first = first;
      n.count = count;
      nodes_[index] = n;
      return;
    }
    int axis = 0;
    for (int k = 1; k < 3; ++k) if (n.hi[k] - n.lo[k] > n.hi[axis] - n.lo[axis]) axis = k;
    const int32_t mid = first + count / 2;
    std::nth_element(order_.begin() + first, order_.begin() + mid, order_.begin() + first + count,
                     [&](int32_t a, int32_t b) { return centroid_[a][axis] < centroid_[b][axis]; });
    n.left = int32_t(nodes_.size());
    nodes_.resize(nodes_.size() + 2);
    nodes_[index] = n;
    build(n.left, first, mid - first);
    build(n.left + 1, mid, first + count - mid);
  }

  const Mesh& m_;
  std::vector<int32_t> order_;
  std::vector<V3> centroid_;
  std::vector<Node> nodes_;
};

// Area-weighted random points on the surface (deterministic for a seed).
inline std::vector<V3> sample_surface(const Mesh& m, size_t n, uint64_t seed) {
  const int32_t nf = m.num_faces();
  std::vector<double> cdf(size_t(nf) + 1, 0.0);
  auto vtx = [&](int32_t f, int k) {
    const float* p = &m.positions[3 * size_t(m.corner_vertex[3 * size_t(f) + k])];
    return V3{p[0], p[1], p[2]};
  };
  for (int32_t f = 0; f < nf; ++f) {
    const V3 a = vtx(f, 0), u = sub(vtx(f, 1), a), w = sub(vtx(f, 2), a);
    const V3 c = {u[1] * w[2] - u[2] * w[1], u[2] * w[0] - u[0] * w[2], u[0] * w[1] - u[1] * w[0]};
    cdf[f + 1] = cdf[f] + 0.5 * std::sqrt(dot(c, c));
  }
  std::mt19937_64 rng(seed);
  std::uniform_real_distribution<double> U(0.0, 1.0);
  std::vector<V3> out;
  out.reserve(n);
  for (size_t i = 0; i < n; ++i) {
    const double r = U(rng) * cdf.back();
    const int32_t f = int32_t(std::upper_bound(cdf.begin(), cdf.end(), r) - cdf.begin()) - 1;
    double s = U(rng), t = U(rng);
    if (s + t > 1) { s = 1 - s; t = 1 - t; }
    const V3 a = vtx(std::clamp(f, 0, nf - 1), 0), b = vtx(std::clamp(f, 0, nf - 1), 1), c = vtx(std::clamp(f, 0, nf - 1), 2);
    out.push_back({a[0] + (b[0] - a[0]) * s + (c[0] - a[0]) * t, a[1] + (b[1] - a[1]) * s + (c[1] - a[1]) * t,
                   a[2] + (b[2] - a[2]) * s + (c[2] - a[2]) * t});
  }
  return out;
}

struct Deviation {
  double hausdorff = 0, rms = 0;  // absolute units
};

// Symmetric: samples of each surface against the other.
inline Deviation deviation(const Mesh& a, const Bvh& bvh_a, const Mesh& b, const Bvh& bvh_b, size_t samples) {
  Deviation d;
  double sum = 0;
  size_t n = 0;
  for (const auto& [from, to] : {std::make_pair(&a, &bvh_b), std::make_pair(&b, &bvh_a)}) {
    for (const V3& p : sample_surface(*from, samples, 12345)) {
      const double d2 = to->distance2(p);
      d.hausdorff = std::max(d.hausdorff, std::sqrt(d2));
      sum += d2;
      ++n;
    }
  }
  d.rms = std::sqrt(sum / double(std::max<size_t>(n, 1)));
  return d;
}

}  // namespace iteas::eval
