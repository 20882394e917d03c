#include "core/angles.h"

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstring>
#include <limits>
#include <mutex>
#include <optional>
#include <sstream>
#include <stdexcept>

#include "core/cpu_features.h"
#include "core/parallel.h"

#if ITEAS_X86_FEATURES
#include <immintrin.h>
#endif

namespace iteas {

bool face_normal(const Mesh& mesh, int32_t f, double n[3]) {
  const float* p = mesh.positions.data();
  const int32_t* cv = &mesh.corner_vertex[3 * size_t(f)];
  const float* a = p + 3 * size_t(cv[0]);
  const float* q = p + 3 * size_t(cv[1]);
  const float* r = p + 3 * size_t(cv[2]);
  const double u[3] = {double(q[0]) - a[0], double(q[1]) - a[1], double(q[2]) - a[2]};
  const double w[3] = {double(r[0]) - a[0], double(r[1]) - a[1], double(r[2]) - a[2]};
  n[0] = u[1] * w[2] - u[2] * w[1];
  n[1] = u[2] * w[0] - u[0] * w[2];
  n[2] = u[0] * w[1] - u[1] * w[0];
  const double len = std::sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2]);
  // Relative tolerance: a cross product ~1e-12 of the squared edge lengths is zero area.
  const double scale = u[0] * u[0] + u[1] * u[1] + u[2] * u[2] + w[0] * w[0] + w[1] * w[1] + w[2] * w[2];
  if (!(len > 1e-12 * scale) || !std::isfinite(len)) return false;
  for (int k = 0; k < 3; ++k) n[k] /= len;
  return true;
}

// Degrees between unit normals: atan2(|n1 x n2|, n1 . n2) is accurate for
// small and large angles alike.
static float angle_between(const double* n1, const double* n2) {
  const double cx = n1[1] * n2[2] - n1[2] * n2[1], cy = n1[2] * n2[0] - n1[0] * n2[2],
               cz = n1[0] * n2[1] - n1[1] * n2[0];
  const double dot = n1[0] * n2[0] + n1[1] * n2[1] + n1[2] * n2[2];
  return float(std::atan2(std::sqrt(cx * cx + cy * cy + cz * cz), dot) * (180.0 / M_PI));
}

float normal_angle(const Mesh& mesh, int32_t f, int32_t g) {
  double n1[3], n2[3];
  if (!face_normal(mesh, f, n1) || !face_normal(mesh, g, n2)) return std::numeric_limits<float>::quiet_NaN();
  return angle_between(n1, n2);
}

// atan2 for y >= 0 by a minimax polynomial on [0, 1] (max error ~1e-5 rad,
// under 0.001 degree): statistics only, never selection. Written without
// branches (selects only) so that loops over arrays of it vectorise.
__attribute__((always_inline)) static inline float fast_atan2_pos(float y, float x) {
  const float ax = __builtin_fabsf(x);
  const float mx = y > ax ? y : ax, mn = y > ax ? ax : y;
  const float a = mn / (mx > 1e-30f ? mx : 1e-30f), s = a * a;  // 0 when both are 0
  float r = ((-0.0464964749f * s + 0.15931422f) * s - 0.327622764f) * s * a + a;
  r = y > ax ? 1.57079637f - r : r;
  r = x < 0 ? 3.14159274f - r : r;
  return r;
}

// out[i] = atan2(y[i], x[i]) in degrees for i < n, y >= 0 (NaN stays NaN).
// (The selects above vectorise without trapping-math semantics: no trap can
// occur, the divisor is never zero. core/cpu_features.h.)
ITEAS_SELECTS_VECTORISE ITEAS_WIDE_CLONES static void atan2_degrees(const float* __restrict y,
                                                                    const float* __restrict x, float* __restrict out,
                                                                    int64_t n) {
  for (int64_t i = 0; i < n; ++i) out[i] = fast_atan2_pos(y[i], x[i]) * float(180.0 / M_PI);
}

// Unit normals in single precision of the faces whose edge vectors u = q - a
// and w = r - a are given (|n| at most 512), into out (3 per face); NaN for
// a zero-area face (a cross product under 1e-10 of the squared edge lengths)
// or a non-finite one. One vectorised loop, inlined into its callers' clones.
ITEAS_SELECTS_VECTORISE __attribute__((always_inline)) static inline void normals_of_edges(
    const float* __restrict ux, const float* __restrict uy, const float* __restrict uz, const float* __restrict wx,
    const float* __restrict wy, const float* __restrict wz, int n, float* __restrict out) {
  float nx[512], ny[512], nz[512];
  for (int i = 0; i < n; ++i) {
    const float x = uy[i] * wz[i] - uz[i] * wy[i];
    const float y = uz[i] * wx[i] - ux[i] * wz[i];
    const float z = ux[i] * wy[i] - uy[i] * wx[i];
    const float len2 = x * x + y * y + z * z;
    const float scale = ux[i] * ux[i] + uy[i] * uy[i] + uz[i] * uz[i] + wx[i] * wx[i] + wy[i] * wy[i] + wz[i] * wz[i];
    // Not finite: len2 >= 0 unless NaN or infinite.
    const bool ok = len2 > 1e-20f * scale * scale && len2 <= __FLT_MAX__;
    const float inv = 1.0f / __builtin_sqrtf(len2);
    const float nan = __builtin_nanf("");
    nx[i] = ok ? x * inv : nan;
    ny[i] = ok ? y * inv : nan;
    nz[i] = ok ? z * inv : nan;
  }
  for (int i = 0; i < n; ++i) { out[3 * i] = nx[i]; out[3 * i + 1] = ny[i]; out[3 * i + 2] = nz[i]; }
}

// Unit normals in single precision for the statistics pass, faces [f0, f1)
// into out (3 per face): the edge vectors gathered per block, then
// normals_of_edges (square roots and divisions four at a time).
ITEAS_SELECTS_VECTORISE ITEAS_WIDE_CLONES static void face_normals_or_nan(const Mesh& mesh, int64_t f0, int64_t f1,
                                                                          float* out) {
  constexpr int kBlock = 512;
  float ux[kBlock], uy[kBlock], uz[kBlock], wx[kBlock], wy[kBlock], wz[kBlock];
  const float* p = mesh.positions.data();
  const int32_t* cv = mesh.corner_vertex.data();
  for (int64_t b = f0; b < f1; b += kBlock) {
    const int n = int((f1 - b < kBlock ? f1 - b : kBlock));
    for (int i = 0; i < n; ++i) {
      const int32_t* t = cv + 3 * size_t(b + i);
      const float* a = p + 3 * size_t(t[0]);
      const float* q = p + 3 * size_t(t[1]);
      const float* r = p + 3 * size_t(t[2]);
      ux[i] = q[0] - a[0]; uy[i] = q[1] - a[1]; uz[i] = q[2] - a[2];
      wx[i] = r[0] - a[0]; wy[i] = r[1] - a[1]; wz[i] = r[2] - a[2];
    }
    normals_of_edges(ux, uy, uz, wx, wy, wz, n, out + 3 * size_t(b - f0));
  }
}

// Per edge of a block: |n1 x n2| and n1 . n2 from the gathered normals, in
// one vectorised loop (the same operations as before, so the same bits).
// Builtins, not std:: calls: a function with its own optimize attribute does
// not inline the header's wrappers, and a call stops vectorisation.
ITEAS_SELECTS_VECTORISE ITEAS_WIDE_CLONES static void sine_cosine(const float* const* __restrict n, int count,
                                                                  float* __restrict ys, float* __restrict xs) {
  const float *__restrict ax = n[0], *__restrict ay = n[1], *__restrict az = n[2];
  const float *__restrict gx = n[3], *__restrict gy = n[4], *__restrict gz = n[5];
  for (int i = 0; i < count; ++i) {
    const float cx = ay[i] * gz[i] - az[i] * gy[i], cy = az[i] * gx[i] - ax[i] * gz[i],
                cz = ax[i] * gy[i] - ay[i] * gx[i];
    ys[i] = __builtin_sqrtf(cx * cx + cy * cy + cz * cz);
    xs[i] = ax[i] * gx[i] + ay[i] * gy[i] + az[i] * gz[i];
  }
}

void edge_angles(const Mesh& mesh, const CornerTable& ct, Array<float>& theta, int threads) {
  edge_angles(mesh, ct, theta, threads, CarriedAngles());
}

// atan(√z)/√z = Σ (-1)^n z^n / (2n + 1) on [0, 0.1716] (tan²(π/8) =
// 0.17157...), economised to degree 10: the series to degree 40, then the
// highest terms traded for shifted Chebyshev polynomials one by one, in
// exact rational arithmetic (docs/performance/atan_fit.py); it departs from
// the function by under 3.4e-17, a third of a double's unit in the last place.
static constexpr double kAtanSeries[11] = {
    1.0, -0.33333333333328574, 0.19999999998880624, -0.1428571418286124, 0.11111106251209447,
    -0.09090774601216603, 0.0768997355213338, -0.06640397080889007, 0.0568915148219518,
    -0.04350236765267998, 0.021160659406873446};

// atan2(y, x) for y >= 0 in double, within a few units in the last place:
// a = min / max of y and |x| in [0, 1]; above tan(π/8), atan a = π/4 +
// atan((a - 1) / (a + 1)); then the series on |t| <= tan(π/8); then the
// octant. Selects only, so loops over it vectorise. y = |x| = 0 gives NaN.
__attribute__((always_inline)) static inline double atan2_pos(double y, double x) {
  const double ax = __builtin_fabs(x);
  const double mx = y > ax ? y : ax, mn = y > ax ? ax : y;
  const double a = mn / mx;
  const bool high = a > 0.41421356237309503;
  const double t = (high ? a - 1.0 : a) / (high ? a + 1.0 : 1.0);
  const double z = t * t;
  double p = kAtanSeries[10];
  for (int i = 9; i >= 0; --i) p = p * z + kAtanSeries[i];
  double r = t * p;
  r = high ? M_PI / 4 + r : r;
  r = y > ax ? M_PI / 2 - r : r;
  r = x < 0 ? M_PI - r : r;
  return r;
}

// The corners' points of a block of up to 256 triangles, one array per
// coordinate (a, q, r times x, y, z), for the vectorised loops below;
// faces[i] (or first + i without a list) is triangle i.
struct PointBlock {
  static constexpr int kSize = 256;
  float v[9][kSize];
  const float* at[9];
  PointBlock() {
    for (int j = 0; j < 9; ++j) at[j] = v[j];
  }
  void gather(const Mesh& mesh, const int32_t* faces, int64_t first, int n);
  // Entries [from, n): face(i)'s points.
  template <typename Face>
  void gather_faces(const Mesh& mesh, Face face, int from, int n) {
    const float* p = mesh.positions.data();
    const int32_t* cv = mesh.corner_vertex.data();
    float(*out)[kSize] = v;
    for (int i = from; i < n; ++i) {
      const int32_t* t = cv + 3 * size_t(face(i));
      for (int k = 0; k < 3; ++k) {
        const float* x = p + 3 * size_t(t[k]);
        for (int j = 0; j < 3; ++j) out[3 * k + j][i] = x[j];
      }
    }
  }
};

#if ITEAS_X86_FEATURES
namespace {
// from, from + 1, ..., from + 15: sixteen consecutive corners (or slots).
__attribute__((target("avx512f"), always_inline)) inline __m512i sixteen_from(int32_t from) {
  return _mm512_add_epi32(_mm512_set1_epi32(from),
                          _mm512_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15));
}

// Four points (or normals) of three floats, each read as four floats (the
// fourth, the next point's first, must be readable), one to a 128-bit lane.
__attribute__((target("avx512f"), always_inline)) inline __m512 four_points(const float* a, const float* b,
                                                                            const float* c, const float* d) {
  __m512 v = _mm512_castps128_ps512(_mm_loadu_ps(a));
  v = _mm512_insertf32x4(v, _mm_loadu_ps(b), 1);
  v = _mm512_insertf32x4(v, _mm_loadu_ps(c), 2);
  return _mm512_insertf32x4(v, _mm_loadu_ps(d), 3);
}

// PointBlock::gather of faces first, first + 1, ... sixteen at a time, where
// the processor has AVX-512: each point read as four floats (its x, y, z and
// the next float), four points to a register, the coordinates picked out in
// face order by permutations. A group whose faces use the mesh's last vertex
// (whose fourth float lies past the array) is left to the scalar loop, as
// are the last faces (under sixteen). Returns the faces done from the
// start: the groups before the first one left. (The scalar copy takes nine
// loads and nine stores a face. The summary with the quality, one thread,
// AMD Zen 5 class: bunny-npm level 1 0.114 -> 0.100 ms, level 3 1.65 ->
// 1.36 ms, level 4 7.6 -> 6.6-6.9 ms.)
// (Masked forms where GCC 12 warns of the plain ones' undefined operand.)
__attribute__((target("avx512f"))) int gather_points_avx512(const float* p, const int32_t* cv, int64_t first,
                                                            int n, int64_t points, float (*out)[PointBlock::kSize]) {
  const __m512i x = _mm512_setr_epi32(0, 4, 8, 12, 16, 20, 24, 28, 0, 0, 0, 0, 0, 0, 0, 0);
  const __m512i one = _mm512_set1_epi32(1);
  const __m512i last = _mm512_set1_epi32(int32_t(points - 1));
  int i = 0;
  for (; i + 16 <= n; i += 16) {
    const int32_t* t = cv + 3 * (first + i);
    const __m512i a = _mm512_loadu_si512(t), b = _mm512_loadu_si512(t + 16), c = _mm512_loadu_si512(t + 32);
    if (_mm512_cmpge_epi32_mask(_mm512_maskz_max_epi32(0xFFFF, _mm512_maskz_max_epi32(0xFFFF, a, b), c), last)) break;
    for (int k = 0; k < 3; ++k) {
      __m512 r[4];
      for (int e = 0; e < 4; ++e) {
        const int32_t* f = t + 3 * (4 * e) + k;  // face 4e's point k; the next faces 3 entries on
        r[e] = four_points(p + 3 * size_t(f[0]), p + 3 * size_t(f[3]), p + 3 * size_t(f[6]), p + 3 * size_t(f[9]));
      }
      __m512i pick = x;
      for (int j = 0; j < 3; ++j, pick = _mm512_add_epi32(pick, one)) {
        // Faces 0-7 from r[0], r[1]; 8-15 from r[2], r[3]; the low halves joined.
        const __m512 lo = _mm512_permutex2var_ps(r[0], pick, r[1]), hi = _mm512_permutex2var_ps(r[2], pick, r[3]);
        _mm512_storeu_ps(out[3 * k + j] + i, _mm512_maskz_shuffle_f32x4(0xFFFF, lo, hi, 0x44));
      }
    }
  }
  return i;
}
}  // namespace
#endif

void PointBlock::gather(const Mesh& mesh, const int32_t* faces, int64_t first, int n) {
  if (faces) {
    gather_faces(mesh, [&](int i) { return int64_t(faces[first + i]); }, 0, n);
    return;
  }
  int done = 0;
#if ITEAS_X86_FEATURES
  if (cpu_has(CpuFeature::kAvx512))
    done = gather_points_avx512(mesh.positions.data(), mesh.corner_vertex.data(), first, n, mesh.num_vertices(), v);
#endif
  gather_faces(mesh, [&](int i) { return first + i; }, done, n);  // the rest
}

// Per face of a block (its corners' points gathered per coordinate: a, q, r
// times x, y, z): the atan2 arguments of its smallest angle in double
// arithmetic, rounded to float — y = |cross| (twice the area), x = (e_a +
// e_b - e_min) / 2 — and y = NaN when two of its points coincide (no angles).
// One vectorised loop (builtins, not std:: calls, as in sine_cosine).
ITEAS_SELECTS_VECTORISE ITEAS_WIDE_CLONES static void smallest_angle_arguments(const float* const* __restrict pt, int n,
                                                                             float* __restrict ys,
                                                                             float* __restrict xs) {
  const float *__restrict ax = pt[0], *__restrict ay = pt[1], *__restrict az = pt[2];
  const float *__restrict qx = pt[3], *__restrict qy = pt[4], *__restrict qz = pt[5];
  const float *__restrict rx = pt[6], *__restrict ry = pt[7], *__restrict rz = pt[8];
  for (int i = 0; i < n; ++i) {
    const double u0 = double(qx[i]) - ax[i], u1 = double(qy[i]) - ay[i], u2 = double(qz[i]) - az[i];
    const double w0 = double(rx[i]) - ax[i], w1 = double(ry[i]) - ay[i], w2 = double(rz[i]) - az[i];
    const double z0 = double(rx[i]) - qx[i], z1 = double(ry[i]) - qy[i], z2 = double(rz[i]) - qz[i];
    const double cx = u1 * w2 - u2 * w1, cy = u2 * w0 - u0 * w2, cz = u0 * w1 - u1 * w0;
    const double e0 = z0 * z0 + z1 * z1 + z2 * z2;
    const double e1 = w0 * w0 + w1 * w1 + w2 * w2;
    const double e2 = u0 * u0 + u1 * u1 + u2 * u2;
    const double m12 = e1 < e2 ? e1 : e2, emin = e0 < m12 ? e0 : m12;
    const bool ok = (e0 > 0) & (e1 > 0) & (e2 > 0);  // no branches: selects vectorise
    const float y = float(__builtin_sqrt(cx * cx + cy * cy + cz * cz));
    ys[i] = ok ? y : __builtin_nanf("");
    xs[i] = float(0.5 * (e0 + e1 + e2 - 2.0 * emin));
  }
}

// face_normals_or_nan's normals of the faces whose points are gathered in pt
// (a, q, r times x, y, z): the same operations on the same floats (its edge
// vectors are the same differences of the gathered points), so its bits.
ITEAS_SELECTS_VECTORISE ITEAS_WIDE_CLONES static void normals_of_points(const float* const* __restrict pt, int n,
                                                                        float* __restrict out) {
  const float *__restrict ax = pt[0], *__restrict ay = pt[1], *__restrict az = pt[2];
  const float *__restrict qx = pt[3], *__restrict qy = pt[4], *__restrict qz = pt[5];
  const float *__restrict rx = pt[6], *__restrict ry = pt[7], *__restrict rz = pt[8];
  float ux[PointBlock::kSize], uy[PointBlock::kSize], uz[PointBlock::kSize];
  float wx[PointBlock::kSize], wy[PointBlock::kSize], wz[PointBlock::kSize];
  for (int i = 0; i < n; ++i) {
    ux[i] = qx[i] - ax[i]; uy[i] = qy[i] - ay[i]; uz[i] = qz[i] - az[i];
    wx[i] = rx[i] - ax[i]; wy[i] = ry[i] - ay[i]; wz[i] = rz[i] - az[i];
  }
  normals_of_edges(ux, uy, uz, wx, wy, wz, n, out);
}

// Triangle quality gathered a block of faces at a time (triangle_quality,
// and summarize_angles when it is asked for it as well): the smallest angle
// per face, its minimum, the faces counted and a histogram of 0.01-degree
// bins over [0, 60]. Counts and a minimum do not depend on the order of the
// blocks.
struct QualityTally {
  static constexpr int kBins = 6001;
  Array<int32_t> bins;  // (a mesh has fewer than 2^31 faces)
  int64_t faces = 0;
  float lo = 180.0f;
  void add(const PointBlock& points, int n) {
    float ys[PointBlock::kSize], xs[PointBlock::kSize], angles[PointBlock::kSize];
    smallest_angle_arguments(points.at, n, ys, xs);
    atan2_degrees(ys, xs, angles, n);
    int32_t* const h = bins.data();
    float low = lo;
    int counted = 0;
    for (int i = 0; i < n; ++i) {
      if (std::isnan(angles[i])) continue;  // repeated position: no angles
      low = std::min(low, angles[i]);
      ++h[std::min(kBins - 1, int(angles[i] * 100.0f))];
      ++counted;
    }
    lo = low;
    faces += counted;
  }
};

// The quality tallies of one parallel loop, one a thread: a piece leases a
// free one for its faces (no more pieces run at once than the loop has
// threads), so each thread adds into bins of its own, and the bins cross
// from one CPU to another once, when the loop is done and summary() merges
// them. (A tally a piece, each merged into the total under a lock, moved
// 24 KB between the CPUs a piece: bunny-npm uniform level 1 with the
// statistics on two threads, in a loop, medians 0.148 -> 0.144 ms.) Which
// tally a face goes to changes no count and no minimum.
class QualityTallies {
 public:
  explicit QualityTallies(int threads) : tallies_(size_t(resolve_threads(threads))), busy_(tallies_.size()) {}

  class Lease {
   public:
    explicit Lease(QualityTallies& owner) : owner_(owner) {
      for (size_t i = 0; i < owner_.tallies_.size(); ++i)
        if (!owner_.busy_[i].flag.exchange(true, std::memory_order_acquire)) {
          slot_ = i;
          tally_ = &owner_.tallies_[i];
          break;
        }
      // (parallel_for runs no more pieces at once than the threads it is given.)
      if (!tally_) throw std::logic_error("QualityTallies: more pieces at once than threads");
      if (tally_->bins.empty()) tally_->bins.assign(QualityTally::kBins, 0);
    }
    ~Lease() {
      if (slot_ != SIZE_MAX) owner_.busy_[slot_].flag.store(false, std::memory_order_release);
    }
    Lease(const Lease&) = delete;
    Lease& operator=(const Lease&) = delete;
    QualityTally& tally() { return *tally_; }

   private:
    QualityTallies& owner_;
    size_t slot_ = SIZE_MAX;
    QualityTally* tally_ = nullptr;
  };

  // The minimum and the 1st percentile (0 and 0 without a face).
  QualitySummary summary() {
    Array<int32_t> all;
    int64_t faces = 0;
    float lo = 180.0f;
    auto merge = [&](QualityTally& t) {
      if (t.bins.empty()) return;
      faces += t.faces;
      lo = std::min(lo, t.lo);
      if (all.empty()) {
        all.swap(t.bins);
        return;
      }
      for (int i = 0; i < QualityTally::kBins; ++i) all[i] += t.bins[i];
    };
    for (QualityTally& t : tallies_) merge(t);
    QualitySummary q;
    if (faces == 0) return q;
    q.min_angle = double(lo);
    // The first bin where the faces counted reach the rank, sixty-four bins
    // at a time up to the block that holds it.
    const int64_t rank = std::max<int64_t>(1, int64_t(std::ceil(0.01 * double(faces))));
    int64_t seen = 0;
    int i = 0;
    for (; i + 64 <= QualityTally::kBins; i += 64) {
      int64_t block = 0;
      for (int j = 0; j < 64; ++j) block += all[i + j];
      if (seen + block >= rank) break;
      seen += block;
    }
    for (; i < QualityTally::kBins; ++i) {
      seen += all[i];
      if (seen >= rank) {
        q.p1_angle = std::max(q.min_angle, i / 100.0);
        break;
      }
    }
    return q;
  }

 private:
  struct Flag {
    std::atomic<bool> flag{false};
  };
  std::vector<QualityTally> tallies_;
  std::vector<Flag> busy_;
};

// Unit normals in double of the faces whose points are gathered in pt (a,
// q, r times x, y, z), with face_normal's operations in its order, so its
// bits; NaN where face_normal says zero area (or not finite). (Doubles only,
// so the loop runs four to a register.)
ITEAS_SELECTS_VECTORISE ITEAS_WIDE_CLONES static void unit_normals(const float* const* __restrict pt, int n,
                                                                   double* __restrict nx, double* __restrict ny,
                                                                   double* __restrict nz) {
  const float *__restrict ax = pt[0], *__restrict ay = pt[1], *__restrict az = pt[2];
  const float *__restrict qx = pt[3], *__restrict qy = pt[4], *__restrict qz = pt[5];
  const float *__restrict rx = pt[6], *__restrict ry = pt[7], *__restrict rz = pt[8];
  for (int i = 0; i < n; ++i) {
    const double u0 = double(qx[i]) - ax[i], u1 = double(qy[i]) - ay[i], u2 = double(qz[i]) - az[i];
    const double w0 = double(rx[i]) - ax[i], w1 = double(ry[i]) - ay[i], w2 = double(rz[i]) - az[i];
    const double x = u1 * w2 - u2 * w1, y = u2 * w0 - u0 * w2, z = u0 * w1 - u1 * w0;
    const double len = __builtin_sqrt(x * x + y * y + z * z);
    const double scale = u0 * u0 + u1 * u1 + u2 * u2 + w0 * w0 + w1 * w1 + w2 * w2;
    const bool ok = (len > 1e-12 * scale) & (len <= __DBL_MAX__);
    const double nan = __builtin_nan("");
    nx[i] = ok ? x / len : nan;
    ny[i] = ok ? y / len : nan;
    nz[i] = ok ? z / len : nan;
  }
}

// face_normals of faces[first + i], or of faces first + i without a list.
static void face_normals_of(const Mesh& mesh, const int32_t* faces, int64_t first, int64_t n, double* nx,
                            double* ny, double* nz) {
  PointBlock points;
  for (int64_t i0 = 0; i0 < n; i0 += PointBlock::kSize) {
    const int k = int(std::min<int64_t>(PointBlock::kSize, n - i0));
    points.gather(mesh, faces, first + i0, k);
    unit_normals(points.at, k, nx + i0, ny + i0, nz + i0);
  }
}

void face_normals(const Mesh& mesh, const int32_t* faces, int64_t n, double* nx, double* ny, double* nz) {
  face_normals_of(mesh, faces, 0, n, nx, ny, nz);
}

// Per edge of a block (both unit normals gathered, one array per
// coordinate): angle_between's sine and cosine (its operations, so its
// bits), then atan2_pos in degrees, in double.
ITEAS_SELECTS_VECTORISE ITEAS_WIDE_CLONES static void exact_degrees(const double* const* __restrict n, int count,
                                                                    double* __restrict out) {
  const double *__restrict ax = n[0], *__restrict ay = n[1], *__restrict az = n[2];
  const double *__restrict gx = n[3], *__restrict gy = n[4], *__restrict gz = n[5];
  for (int i = 0; i < count; ++i) {
    const double cx = ay[i] * gz[i] - az[i] * gy[i], cy = az[i] * gx[i] - ax[i] * gz[i],
                 cz = ax[i] * gy[i] - ay[i] * gx[i];
    const double dot = ax[i] * gx[i] + ay[i] * gy[i] + az[i] * gz[i];
    out[i] = atan2_pos(__builtin_sqrt(cx * cx + cy * cy + cz * cz), dot) * (180.0 / M_PI);
  }
}

#if ITEAS_X86_FEATURES
namespace {
// edge_angles' listing of a chunk's edges [c, end) with no angle carried,
// sixteen corners at a time where the processor has AVX-512: the same lists
// as its one-corner loop (an edge at its first corner c, opp[c] > c: c in
// |corner|, its face's slot in |first|, the other face's in |second|, which
// for a face in a later chunk is a new slot, the face appended to |faces|).
// The new slots of a group are numbered in corner order (an expand of
// consecutive numbers into its far lanes). Returns the first corner not
// looked at; |ne| and |nl| advance.
__attribute__((target("avx512f"))) int32_t list_chunk_edges_avx512(const int32_t* opp, int32_t c, int32_t end,
                                                                   int32_t f0, int32_t f1, int32_t* corner,
                                                                   int32_t* first, int32_t* second, int32_t& ne,
                                                                   int32_t* faces, int32_t& nl) {
  const __m512i base = _mm512_set1_epi32(f0), past = _mm512_set1_epi32(f1);
  for (; c + 16 <= end; c += 16) {
    const __m512i at = sixteen_from(c);
    const __m512i d = _mm512_loadu_si512(opp + c);
    const __mmask16 keep = _mm512_cmpgt_epi32_mask(d, at);  // (a boundary's -1 is not)
    if (!keep) continue;
    const __m512i g = div3_epi32_avx512(_mm512_maskz_mov_epi32(keep, d));
    const __mmask16 far = _mm512_mask_cmpge_epi32_mask(keep, g, past);
    const __m512i slots = _mm512_maskz_expand_epi32(far, sixteen_from(nl));
    const __m512i other = _mm512_mask_blend_epi32(far, _mm512_sub_epi32(g, base), slots);
    _mm512_mask_compressstoreu_epi32(corner + ne, keep, at);
    _mm512_mask_compressstoreu_epi32(first + ne, keep, _mm512_sub_epi32(div3_epi32_avx512(at), base));
    _mm512_mask_compressstoreu_epi32(second + ne, keep, other);
    _mm512_mask_compressstoreu_epi32(faces + nl, far, g);
    ne += __builtin_popcount(keep);
    nl += __builtin_popcount(far);
  }
  return c;
}
}  // namespace
#endif

namespace {
// edge_angles' angles of edges a block at a time: both faces' unit normals
// gathered per coordinate, the angles from the vectorised polynomial, each
// rounded to the float the library's atan2 gives, but where it lies within
// 1e-12 of it (far beyond atan2_pos's error, a few units in the 16th digit)
// of a boundary between two floats, or is not a number: those (about 2 in
// 100,000 edges) are computed by angle_between itself, so every angle has
// its bits. Each angle goes to both corners of its edge.
struct AngleBlock {
  static constexpr int kSize = PointBlock::kSize;
  double gathered[6][kSize];
  const double* g6[6];
  int32_t corner[kSize];
  double degrees[kSize];
  int n = 0;
  AngleBlock() {
    for (int j = 0; j < 6; ++j) g6[j] = gathered[j];
  }
  // The edge at its first corner c, between the faces whose normals are
  // (x[s1], y[s1], z[s1]) and (x[s2], ...).
  void add(int32_t c, const double* x, const double* y, const double* z, int64_t s1, int64_t s2, float* theta,
           const int32_t* opp) {
    add_if(true, c, x, y, z, s1, s2, theta, opp);
  }
  // add() when |keep|, without a branch on it: the entry is written either
  // way and counted only when kept (whether a corner holds an edge follows
  // no pattern).
  void add_if(bool keep, int32_t c, const double* x, const double* y, const double* z, int64_t s1, int64_t s2,
              float* theta, const int32_t* opp) {
    corner[n] = c;
    gathered[0][n] = x[s1]; gathered[1][n] = y[s1]; gathered[2][n] = z[s1];
    gathered[3][n] = x[s2]; gathered[4][n] = y[s2]; gathered[5][n] = z[s2];
    n += keep;
    if (n == kSize) flush(theta, opp);
  }
  void flush(float* theta, const int32_t* opp) {
    exact_degrees(g6, n, degrees);
    for (int i = 0; i < n; ++i) {
      const double d = degrees[i];
      float a = float(d * (1.0 - 1e-12));
      if (!(a == float(d * (1.0 + 1e-12)))) {
        const double n1[3] = {gathered[0][i], gathered[1][i], gathered[2][i]};
        const double n2[3] = {gathered[3][i], gathered[4][i], gathered[5][i]};
        a = angle_between(n1, n2);
      }
      theta[corner[i]] = theta[opp[corner[i]]] = a;
    }
    n = 0;
  }
};
}  // namespace

void edge_angles(const Mesh& mesh, const CornerTable& ct, Array<float>& theta, int threads,
                 const CarriedAngles& carried) {
  // Fixed chunks of faces: each lists the edges it computes (each edge at
  // its smaller corner, for both corners), the faces whose normals they need
  // (its own once each; a neighbour in a later chunk once per edge), then
  // computes the normals and the angles in vectorised loops over blocks.
  // Values equal normal_angle's bit for bit.
  // The NaN fill first, on all threads (a corner's value may be written from
  // another chunk, that of its opposite).
  const int32_t nc = ct.num_corners();
  theta.resize(nc);
  parallel_for(nc, threads, [&](int64_t b, int64_t e) {
    std::fill(theta.data() + b, theta.data() + e, std::numeric_limits<float>::quiet_NaN());
  });
  // (The chunks only bound the normals held: any size gives the same
  // angles. On more than one thread, about eight per thread: an edge is
  // computed by the chunk of its smaller corner, so where faces come in no
  // spatial order the first chunks hold most of the edges (chunk k of n about
  // (n - k) / n of its faces' edges), and a thread left with a long first
  // chunk held the other up.)
  const int64_t nf = nc / 3;
  const int64_t used = resolve_threads(threads);
  // Up to this many faces (1.5 MB of normals), several threads compute
  // every face's normal first (below); one thread does up to one chunk's
  // faces: the same normals, in 96 KB at most, where the chunk's edge list
  // alone took 147 KB (over glibc's 128 KiB threshold, so mapped, filled and
  // unmapped each time).
  constexpr int64_t kWholeNormals = 65536;
  constexpr int64_t kChunkFaces = 4096;  // one thread's chunk, the largest on several
  const int64_t kFaces =
      used == 1 ? kChunkFaces : std::min<int64_t>(kChunkFaces, std::max<int64_t>(256, nf / (8 * used)));
  const int64_t chunks = (nf + kFaces - 1) / kFaces;
  const int32_t* opp = ct.opposites().data();
  const int32_t* cv = mesh.corner_vertex.data();
#if ITEAS_X86_FEATURES
  const bool wide512 = cpu_has(CpuFeature::kAvx512);
#endif
  if (!carried.theta && nf <= (used > 1 ? kWholeNormals : kChunkFaces)) {
    // Nothing carried and a small mesh (on one thread, up to one chunk's
    // faces): every face's normal once, on all threads, then the angles of
    // the edges, a range of corners a thread. (Chunks of 256 faces, each
    // computing the normals its edges need, computed a later chunk's face's
    // normal once per edge; in a scanner's face order most edges reach a
    // later chunk, and bunny-npm's angles took 36 µs on two threads as on
    // one.)
    Array<double> normals(3 * size_t(nf));
    double *const nx = normals.data(), *const ny = nx + nf, *const nz = ny + nf;
    parallel_for(nf, threads, [&](int64_t b, int64_t e) {
      face_normals_of(mesh, nullptr, b, e - b, nx + b, ny + b, nz + b);
    }, 1024);
    parallel_for(nc, threads, [&](int64_t b, int64_t e) {
      AngleBlock block;
      float* const th = theta.data();
      for (int32_t c = int32_t(b); c < int32_t(e); ++c) {
        const int32_t d = opp[c];
        const int32_t f = c / 3, g = d / 3;  // (d = -1: face 0, read and not kept)
        // An edge at its first corner (d > c; not at -1), between faces of
        // nonzero area (a zero-area face's normal is NaN: no angle).
        const bool keep = (d > c) & !std::isnan(nx[f]) & !std::isnan(nx[g]);
        block.add_if(keep, c, nx, ny, nz, f, g, th, opp);
      }
      block.flush(th, opp);
    }, 3072);
    return;
  }
  parallel_for_chunks(chunks, threads, [&](int64_t b, int64_t e) {
    // Written before read: slot per face of the chunk (-1: not listed), the
    // faces listed (the chunk's own at most once, a later chunk's once per
    // edge), the edges (corner and the slots of its two faces), the normals
    // per slot.
    Array<int32_t> slot(kFaces), faces(4 * kFaces + 1), edges(9 * kFaces + 3);
    // The edges' corners, then their first faces' slots, then the others'.
    int32_t* const ec = edges.data();
    int32_t* const e1 = ec + (3 * kFaces + 1);
    int32_t* const e2 = e1 + (3 * kFaces + 1);
    Array<double> normals;
    AngleBlock block;
    for (int64_t k = b; k < e; ++k) {
      const int64_t f0 = k * kFaces, f1 = std::min(nf, f0 + kFaces);
      int32_t* sl = slot.data();
      int32_t* fl = faces.data();
      int32_t nl = 0, ne = 0;
      if (!carried.theta) {
        // Every edge of the chunk is computed: every face's normal (slot f -
        // f0), and a later chunk's face once per edge, after them. No
        // branches: whether a corner holds an edge follows no pattern.
        nl = int32_t(f1 - f0);
        for (int32_t i = 0; i < nl; ++i) fl[i] = int32_t(f0) + i;
        int32_t c = int32_t(3 * f0);
#if ITEAS_X86_FEATURES
        // (One corner at a time, bunny-npm's 11,022 corners took about half
        // of the input's angles here, AMD Zen 5 class.)
        if (wide512)
          c = list_chunk_edges_avx512(opp, c, int32_t(3 * f1), int32_t(f0), int32_t(f1), ec, e1, e2, ne, fl, nl);
#endif
        for (; c < int32_t(3 * f1); ++c) {
          const int32_t d = opp[c], g = d / 3;  // d < c (or -1): no edge here
          const bool keep = d > c, far = g >= f1;
          ec[ne] = c;
          e1[ne] = c / 3 - int32_t(f0);
          e2[ne] = far ? nl : g - int32_t(f0);
          fl[nl] = g;
          nl += keep & far;
          ne += keep;
        }
      } else {
        std::fill(sl, sl + (f1 - f0), -1);
        // Carried first (after the first levels nearly every edge is), each
        // corner from its own face: both corners of a carried edge are
        // carried, with the same angle (see CarriedAngles), so no corner
        // waits for its edge's first and no store goes elsewhere.
        const float* old = carried.theta;
        float* th = theta.data();
        for (int32_t f = int32_t(f0); f < int32_t(f1); ++f) {
          unsigned kept;
          const int64_t from = carried.carried_corners(cv, f, kept);
          for (int k = 0; k < 3; ++k) {
            const int32_t c = 3 * f + k, d = opp[c];
            const bool first = d > c;  // else a boundary (-1), or done at the smaller corner
            // The angle carried for c, or -1 when there is none (an angle is
            // never negative; a carried NaN is a zero-area face's).
            const float t = kept >> k & 1 ? old[3 * from + k] : -1.0f;
            if (!(t < 0.0f)) {
              th[c] = t;
              continue;
            }
            if (!first) continue;
            int32_t& s1 = sl[f - f0];
            if (s1 < 0) { s1 = nl; fl[nl++] = f; }
            const int32_t g = d / 3;
            int32_t s2;
            if (g >= f1) {  // a later chunk's face
              s2 = nl;
              fl[nl++] = g;
            } else {
              int32_t& s = sl[g - f0];
              if (s < 0) { s = nl; fl[nl++] = g; }
              s2 = s;
            }
            ec[ne] = c;
            e1[ne] = s1;
            e2[ne] = s2;
            ++ne;
          }
        }
      }
      // The normals, a block of faces at a time.
      normals.resize(3 * size_t(nl));
      face_normals(mesh, fl, nl, normals.data(), normals.data() + nl, normals.data() + 2 * size_t(nl));
      // The angles of the edges whose faces both have a normal, a block at a
      // time (AngleBlock).
      const double* nm = normals.data();  // x of every slot, then y, then z
      float* const th = theta.data();
      for (int64_t i = 0; i < ne; ++i) {
        const int32_t s1 = e1[i], s2 = e2[i];
        if (std::isnan(nm[s1]) || std::isnan(nm[s2])) continue;  // a zero-area face: no angle
        block.add(ec[i], nm, nm + nl, nm + 2 * size_t(nl), s1, s2, th, opp);
      }
      block.flush(th, opp);
    }
  });
}

// The per-piece tally of summarize_angles: counts, an exact sum (units of
// 2^-40 degree in 128 bits: every angle of 2^-17 degree or more is a whole
// number of units, a smaller one is cut to whole units, under 1e-12 degree),
// the maximum and the 10-degree histogram.
struct AngleTally {
  static constexpr int kBins = 18;
  static constexpr double kUnits = 1099511627776.0;  // 2^40 units per degree
  __extension__ typedef __int128 Sum;
  int64_t edges = 0, above = 0;
  Sum sum = 0;
  float max = 0;
  int64_t hist[kBins] = {};

  // Whether angle t (>= 0 or NaN) is counted: a number, and under the
  // exclusion (creases) when there is one.
  static bool counted(float t, double exclude) { return !(std::isnan(t) || (exclude > 0 && t >= exclude)); }
  // Angle t, one at a time.
  void add(float t, double threshold, double exclude) {
    if (!counted(t, exclude)) return;
    ++edges;
    sum += static_cast<int64_t>(double(t) * kUnits);  // t <= 180: under 2^48 units
    max = std::max(max, t);
    above += t > threshold;
    hist[std::min(kBins - 1, std::max(0, int(t / 10.0f)))]++;
  }
  void merge(const AngleTally& o) {
    edges += o.edges;
    above += o.above;
    sum += o.sum;
    max = std::max(max, o.max);
    for (int k = 0; k < kBins; ++k) hist[k] += o.hist[k];
  }
};

#if ITEAS_X86_FEATURES
// add()'s comparisons as comparisons of floats, for the AVX2 tally: for a
// float t, double(t) > threshold exactly when t reaches the smallest float
// above the threshold, and double(t) >= exclude when t reaches the smallest
// float at or above it; int(t / 10.0f) >= k exactly when t reaches the
// smallest float whose quotient by 10 does (division is monotonic). A bound
// no float reaches is NaN (every comparison with it is false).
struct TallyBounds {
  float above, excluded;
  float bin[AngleTally::kBins];  // bin[k], k >= 1
  TallyBounds(double threshold, double exclude) {
    above = smallest_float(threshold, true);
    excluded = exclude > 0 ? smallest_float(exclude, false) : std::numeric_limits<float>::quiet_NaN();
    bin[0] = 0;
    for (int k = 1; k < AngleTally::kBins; ++k) {
      float t = 10.0f * float(k);
      while (t / 10.0f >= float(k)) t = std::nextafter(t, 0.0f);
      while (t / 10.0f < float(k)) t = std::nextafter(t, 1000.0f);
      bin[k] = t;
    }
  }
  // The smallest float f with double(f) > x (strict) or >= x.
  static float smallest_float(double x, bool strict) {
    const float inf = std::numeric_limits<float>::infinity();
    if (std::isnan(x)) return std::numeric_limits<float>::quiet_NaN();
    auto meets = [&](float f) { return strict ? double(f) > x : double(f) >= x; };
    if (!meets(std::numeric_limits<float>::max())) return meets(inf) ? inf : std::numeric_limits<float>::quiet_NaN();
    if (meets(-std::numeric_limits<float>::max())) return -std::numeric_limits<float>::max();
    float f = float(x);  // within a step or two of the answer
    while (!meets(f)) f = std::nextafter(f, inf);
    while (meets(std::nextafter(f, -inf))) f = std::nextafter(f, -inf);
    return f;
  }
};

// AngleTally::add over t[0, n) (n < 2^31 / 8), eight angles at a time: the
// same counts, sum, maximum and histogram. Valid angles are >= 0, so a
// float's bits order as integers (the maximum); the units are cut in
// doubles and read as integers through the bits of 1.5 * 2^52 + units; the
// histogram counts, per bin, the angles that reach its bound, and only for
// the eight angles where one reaches 10 degrees (most angles of a refined
// level lie under it: one increment per angle into the first bin made each
// wait for the one before).
__attribute__((target("avx2"))) void tally_avx2(const float* t, int64_t n, const TallyBounds& b, AngleTally& out) {
  const __m256 above = _mm256_set1_ps(b.above), excluded = _mm256_set1_ps(b.excluded);
  const __m256 ten = _mm256_set1_ps(b.bin[1]);
  const __m256d units = _mm256_set1_pd(AngleTally::kUnits), magic = _mm256_set1_pd(6755399441055744.0);
  const __m256i magic_bits = _mm256_castpd_si256(magic);
  __m256i edges = _mm256_setzero_si256(), over = edges, max_bits = edges, sum_lo = edges, sum_hi = edges;
  __m256i reach[AngleTally::kBins];
  for (__m256i& r : reach) r = _mm256_setzero_si256();
  const int64_t whole = n - n % 8;
  for (int64_t i = 0; i < whole; i += 8) {
    const __m256 x = _mm256_loadu_ps(t + i);
    const __m256 ok = _mm256_andnot_ps(_mm256_cmp_ps(x, excluded, _CMP_GE_OQ), _mm256_cmp_ps(x, x, _CMP_ORD_Q));
    const __m256i oki = _mm256_castps_si256(ok);
    edges = _mm256_sub_epi32(edges, oki);
    over = _mm256_sub_epi32(over, _mm256_castps_si256(_mm256_and_ps(ok, _mm256_cmp_ps(x, above, _CMP_GE_OQ))));
    const __m256 kept = _mm256_and_ps(ok, x);  // 0 where not counted
    max_bits = _mm256_max_epi32(max_bits, _mm256_castps_si256(kept));
    const __m256d lo = _mm256_round_pd(_mm256_mul_pd(_mm256_cvtps_pd(_mm256_castps256_ps128(kept)), units),
                                       _MM_FROUND_TO_ZERO | _MM_FROUND_NO_EXC);
    const __m256d hi = _mm256_round_pd(_mm256_mul_pd(_mm256_cvtps_pd(_mm256_extractf128_ps(kept, 1)), units),
                                       _MM_FROUND_TO_ZERO | _MM_FROUND_NO_EXC);
    sum_lo = _mm256_add_epi64(sum_lo, _mm256_sub_epi64(_mm256_castpd_si256(_mm256_add_pd(lo, magic)), magic_bits));
    sum_hi = _mm256_add_epi64(sum_hi, _mm256_sub_epi64(_mm256_castpd_si256(_mm256_add_pd(hi, magic)), magic_bits));
    if (_mm256_movemask_ps(_mm256_cmp_ps(kept, ten, _CMP_GE_OQ)) == 0) continue;
    for (int k = 1; k < AngleTally::kBins; ++k)
      reach[k] = _mm256_sub_epi32(
          reach[k], _mm256_castps_si256(_mm256_cmp_ps(kept, _mm256_set1_ps(b.bin[k]), _CMP_GE_OQ)));
  }
  auto lanes32 = [](__m256i v) __attribute__((target("avx2"))) {
    alignas(32) int32_t a[8];
    _mm256_store_si256(reinterpret_cast<__m256i*>(a), v);
    int64_t s = 0;
    for (int32_t x : a) s += x;
    return s;
  };
  alignas(32) int64_t s[8];
  _mm256_store_si256(reinterpret_cast<__m256i*>(s), sum_lo);
  _mm256_store_si256(reinterpret_cast<__m256i*>(s + 4), sum_hi);
  for (int64_t x : s) out.sum += x;
  alignas(32) int32_t m[8];
  _mm256_store_si256(reinterpret_cast<__m256i*>(m), max_bits);
  float block_max = 0;
  for (int32_t bits : m) {
    float f;
    std::memcpy(&f, &bits, sizeof f);
    block_max = std::max(block_max, f);
  }
  out.max = std::max(out.max, block_max);
  const int64_t counted = lanes32(edges);
  out.edges += counted;
  out.above += lanes32(over);
  // Bin k holds the angles that reach bound k but not k + 1; the last bin
  // all that reach it.
  int64_t reached[AngleTally::kBins + 1] = {};
  reached[0] = counted;
  for (int k = 1; k < AngleTally::kBins; ++k) reached[k] = lanes32(reach[k]);
  for (int k = 0; k < AngleTally::kBins; ++k) out.hist[k] += reached[k] - reached[k + 1];
}
#endif

#if ITEAS_X86_FEATURES
namespace {
// summarize_angles' edges of corners [c, end), sixteen corners at a time
// while |near| and |others| have room for sixteen more. An interior edge at
// its first corner c (opp[c] > c) whose other face lies before |f1| (a face
// of the block [f0, f1)) is listed as the offsets of its faces' normals in
// the block's cache: 3 (c / 3 - f0) in |near_a|, 3 (opp[c] / 3 - f0) in
// |near_b|. One whose other face lies at or after f1 goes to |others| as its
// corner. |opp| holds the opposites from corner |base| on. Returns the first
// corner not looked at.
__attribute__((target("avx512f"))) int32_t list_block_edges_avx512(const int32_t* opp, int32_t base, int32_t c,
                                                                   int32_t end, int32_t f0, int32_t f1,
                                                                   int32_t* near_a, int32_t* near_b, int& n_near,
                                                                   int near_room, int32_t* others, int& n_others,
                                                                   int others_room) {
  const __m512i past = _mm512_set1_epi32(3 * f1), first = _mm512_set1_epi32(f0);
  for (; c + 16 <= end && n_near + 16 <= near_room && n_others + 16 <= others_room; c += 16) {
    const __m512i at = sixteen_from(c);
    const __m512i d = _mm512_loadu_si512(opp + (c - base));
    const __mmask16 edge = _mm512_cmpgt_epi32_mask(d, at);  // (a boundary's -1 is not)
    const __mmask16 near = _mm512_mask_cmplt_epi32_mask(edge, d, past);
    const __mmask16 later = edge & __mmask16(~near);
    if (near) {
      const __m512i fa = _mm512_sub_epi32(div3_epi32_avx512(at), first),
                    fb = _mm512_sub_epi32(div3_epi32_avx512(d), first);
      _mm512_mask_compressstoreu_epi32(near_a + n_near, near, _mm512_add_epi32(fa, _mm512_add_epi32(fa, fa)));
      _mm512_mask_compressstoreu_epi32(near_b + n_near, near, _mm512_add_epi32(fb, _mm512_add_epi32(fb, fb)));
      n_near += __builtin_popcount(near);
    }
    if (later) {
      _mm512_mask_compressstoreu_epi32(others + n_others, later, at);
      n_others += __builtin_popcount(later);
    }
  }
  return c;
}

// summarize_angles' angles with theta given: the angle of each interior
// edge's first corner c (opp[c] > c) of corners [c, end), appended to |ts| in
// corner order, sixteen corners at a time while |ts| has room for sixteen
// more (|n| advances). |opp| holds the opposites from corner |base| on.
// Returns the first corner not looked at. (One corner at a time, the listing
// took half of the summary of bunny-npm's angles, AMD Zen 5 class.)
__attribute__((target("avx512f"))) int32_t list_first_angles_avx512(const int32_t* opp, int32_t base,
                                                                    const float* theta, int32_t c, int32_t end,
                                                                    float* ts, int& n, int room) {
  for (; c + 16 <= end && n + 16 <= room; c += 16) {
    const __m512i at = sixteen_from(c);
    const __mmask16 first = _mm512_cmpgt_epi32_mask(_mm512_loadu_si512(opp + (c - base)), at);
    _mm512_mask_compressstoreu_ps(ts + n, first, _mm512_loadu_ps(theta + c));
    n += __builtin_popcount(first);
  }
  return c;
}

// The listed edges' normals, from the block's cache into the six arrays of
// summarize_angles (the first face's x, y, z, then the other's). Sixteen
// edges at a time, each normal read as four floats (its x, y, z and the next
// float, which the cache holds one more of), four normals to a register, and
// the four registers transposed: edge 4e + l lands in lane 4l + e, for both
// faces alike, an order the tally does not depend on. The last few edges
// (under sixteen) copied one by one in order. (Sixteen-lane gathers before:
// one took 4.9 ns here, AMD Zen 5 class, against 0.16 ns a scalar indexed
// load. The summary with the quality, one thread: bunny-npm level 1 0.128
// -> 0.113 ms, level 3 1.90 -> 1.61 ms, level 4 8.46 -> 7.59 ms.)
__attribute__((target("avx512f"))) void gather_block_normals_avx512(const float* normals, const int32_t* near_a,
                                                                    const int32_t* near_b, int n,
                                                                    float* const* soa) {
  int i = 0;
  for (; i + 16 <= n; i += 16) {
    for (int side = 0; side < 2; ++side) {
      const int32_t* at = (side == 0 ? near_a : near_b) + i;
      __m512 r[4];
      for (int e = 0; e < 4; ++e)
        r[e] = four_points(normals + at[4 * e], normals + at[4 * e + 1], normals + at[4 * e + 2],
                           normals + at[4 * e + 3]);
      // (Masked forms throughout: GCC 12 warns of the plain ones'
      // undefined pass-through operand.)
      const __m512d t0 = _mm512_castps_pd(_mm512_maskz_unpacklo_ps(0xFFFF, r[0], r[1]));
      const __m512d t1 = _mm512_castps_pd(_mm512_maskz_unpackhi_ps(0xFFFF, r[0], r[1]));
      const __m512d t2 = _mm512_castps_pd(_mm512_maskz_unpacklo_ps(0xFFFF, r[2], r[3]));
      const __m512d t3 = _mm512_castps_pd(_mm512_maskz_unpackhi_ps(0xFFFF, r[2], r[3]));
      float* const* out = soa + 3 * side;
      _mm512_storeu_ps(out[0] + i, _mm512_castpd_ps(_mm512_maskz_unpacklo_pd(0xFF, t0, t2)));
      _mm512_storeu_ps(out[1] + i, _mm512_castpd_ps(_mm512_maskz_unpackhi_pd(0xFF, t0, t2)));
      _mm512_storeu_ps(out[2] + i, _mm512_castpd_ps(_mm512_maskz_unpacklo_pd(0xFF, t1, t3)));
    }
  }
  for (; i < n; ++i)
    for (int k = 0; k < 3; ++k) {
      soa[k][i] = normals[near_a[i] + k];
      soa[3 + k][i] = normals[near_b[i] + k];
    }
}
}  // namespace
#endif

namespace {
// Where summarize's edges find their other corner: every corner's opposite
// (|all|), or a uniform split's parent's (|parent|, |parent_corners|), the
// children's made for a block of faces at a time (split_opposites).
struct OppositeSource {
  const int32_t* all = nullptr;
  const int32_t* parent = nullptr;
  int64_t parent_corners = 0;
};

AngleSummary summarize(const Mesh& mesh, const OppositeSource& source, const Array<float>* theta, double threshold,
                       double exclude, int threads, QualitySummary* quality) {
  // The sum of the angles is kept exactly (AngleTally). Counts, the
  // maximum and an exact sum do not depend on the order in which they are
  // gathered, so each piece of the loop adds its own into the total under a
  // lock, whatever the pieces (fixed chunks of 8192 faces combined in order
  // left a small level on one thread or two uneven ones).
  // Without theta, the piece computes its faces' normals in blocks into a
  // small cache; an edge whose other face is in a later block of the piece
  // waits for it (about 6 % of a subdivided level's edges: subdivision keeps
  // a parent's children together), one whose other face is in another piece
  // computes that face's normal on the spot. Memory: O(threads) for the
  // blocks, 16 bytes per waiting edge.
  const int64_t nc = 3 * int64_t(mesh.num_faces());
  constexpr int64_t kFaces = 8192;
  const int64_t nf = nc / 3;
  std::mutex mutex;
  AngleTally all;
  // The triangle quality too, when asked for and the normals are computed
  // here: each face's points gathered once for both.
  const bool with_quality = quality && !theta;
  QualityTallies quality_tallies(with_quality ? threads : 1);
#if ITEAS_X86_FEATURES
  const bool wide = cpu_has(CpuFeature::kAvx2);
  const bool wide512 = cpu_has(CpuFeature::kAvx512);
  const TallyBounds bounds(threshold, exclude);
#endif
  // Angles into a piece's tally.
  auto count_into = [&](AngleTally& tally, const float* angles, int n) {
    int i = 0;
#if ITEAS_X86_FEATURES
    if (wide) {
      i = n - n % 8;
      tally_avx2(angles, i, bounds, tally);
    }
#endif
    for (; i < n; ++i) tally.add(angles[i], threshold, exclude);
  };
  // Without theta, on several threads, up to kWholeFaces faces: every face's
  // normal (and quality) first, into one array, then the edges by ranges of
  // corners, each reading both normals from it. (In pieces of kFaces, an
  // edge whose other face lies in a later piece computed that normal on the
  // spot: a level in its parents' order has such edges all through it, and
  // the first pieces hold most of them. bunny-npm uniform level 1 with the
  // statistics on two threads, in a loop: 0.196 -> 0.170 ms.) Up to two
  // pieces' worth, the array takes no more than the pieces' own caches did
  // (level 1 on two threads: peak heap growth 649 -> 625 KB). Up to 65,536
  // faces (768 KB): level 2's 58,784 on two threads 0.617 -> 0.516-0.529 ms,
  // its peak heap growth 27.8 -> 33.4 bytes an output triangle (under the
  // 40 the benchmark allows since the last uniform level makes no corner
  // table for its summary; before that, 37.9 -> 45.5). Larger levels keep
  // the pieces (level 3's 235,136 faces would take 2.8 MB, 12 bytes an
  // output triangle more).
  constexpr int64_t kWholeFaces = 8 * kFaces;
  const bool whole = !theta && resolve_threads(threads) > 1 && nf > kFaces && nf <= kWholeFaces;
  Array<float> whole_normals(whole ? 3 * size_t(nf) + 1 : 0);  // one float more: read four at a time
  if (whole) {
    whole_normals.back() = 0;
    parallel_for(nf, threads, [&](int64_t b, int64_t e) {
      PointBlock points;
      std::optional<QualityTallies::Lease> lease;
      if (with_quality) lease.emplace(quality_tallies);
      for (int64_t g0 = b; g0 < e; g0 += PointBlock::kSize) {
        const int k = int(std::min<int64_t>(PointBlock::kSize, e - g0));
        points.gather(mesh, nullptr, g0, k);
        normals_of_points(points.at, k, whole_normals.data() + 3 * size_t(g0));
        if (lease) lease->tally().add(points, k);
      }
    }, 2048);
  }
  parallel_for(nf, threads, [&](int64_t b, int64_t e) {
    // Per block: the faces' normals, then per edge the sine and cosine of
    // the angle, then the angles (a vectorised loop), in edge order. The
    // sines and cosines go through small blocks on the stack.
    constexpr int kBlock = 1024;
    float ys[kBlock], xs[kBlock], ts[kBlock];
    // (The cache holds one float more: the edges' normals are read four
    // floats at a time.)
    Array<float> cache(theta || whole ? 0 : 3 * std::min(kFaces, e - b) + 1), gathered(theta ? 0 : 6 * kBlock);  // written before read
    if (!cache.empty()) cache.back() = 0;
    // Both normals of each edge of a block, one array per coordinate (none
    // when theta is given).
    float* soa[6] = {};
    if (!theta)
      for (int j = 0; j < 6; ++j) soa[j] = gathered.data() + j * kBlock;
    // A block's opposites: the table's, or the children's of its parents
    // (from corner |base| on).
    Array<int32_t> split(source.parent ? 12 * ((std::min(kFaces, e - b) + 3) / 4 + 1) : 0);
    // An edge whose other face lies in a later block of this piece waits for
    // that block, with its first face's normal (the other face's normal,
    // computed on the spot, cost several cache misses an edge, and about 6 %
    // of a subdivided level's edges cross blocks); one in another piece is
    // computed on the spot.
    struct Waiting {
      int32_t face;
      float n[3];
    };
    std::vector<std::vector<Waiting>> waiting(theta || whole ? 0 : size_t((e - b + kFaces - 1) / kFaces));
    AngleTally tally;
    std::optional<QualityTallies::Lease> lease;  // (whole: tallied above)
    if (with_quality && !whole) lease.emplace(quality_tallies);
    auto count = [&](const float* angles, int n) { count_into(tally, angles, n); };
    for (int64_t f0 = b; f0 < e; f0 += kFaces) {
      const int64_t f1 = std::min(e, f0 + kFaces);
      const int32_t* opp = source.all;
      int32_t base = 0;
      if (source.parent) {
        const int64_t p0 = f0 / 4, p1 = (f1 + 3) / 4;
        split_opposites(source.parent, source.parent_corners, p0, p1, split.data(), true);
        opp = split.data();
        base = int32_t(12 * p0);
      }
      if (theta) {
        // Each edge at its smaller corner (not at a boundary's -1), listed
        // without a branch: which corner is an edge's first follows no pattern.
        const float* th = theta->data();
        int n = 0;
        int32_t c = int32_t(3 * f0);
#if ITEAS_X86_FEATURES
        if (wide512)
          for (;;) {
            c = list_first_angles_avx512(opp, base, th, c, int32_t(3 * f1), ts, n, kBlock);
            if (c + 16 > int32_t(3 * f1)) break;
            count(ts, n);
            n = 0;
          }
#endif
        for (; c < int32_t(3 * f1); ++c) {
          ts[n] = th[c];
          n += opp[c - base] > c;
          if (n == kBlock) {
            count(ts, n);
            n = 0;
          }
        }
        count(ts, n);
        continue;
      }
      // |normals| holds the normals of faces [h0, h1): the block's, or
      // every face's (whole, computed above with the quality).
      const int64_t h0 = whole ? 0 : f0, h1 = whole ? nf : f1;
      if (!whole && with_quality) {
        PointBlock points;
        for (int64_t g0 = f0; g0 < f1; g0 += PointBlock::kSize) {
          const int k = int(std::min<int64_t>(PointBlock::kSize, f1 - g0));
          points.gather(mesh, nullptr, g0, k);
          normals_of_points(points.at, k, cache.data() + 3 * size_t(g0 - f0));
          lease->tally().add(points, k);
        }
      } else if (!whole) {
        face_normals_or_nan(mesh, f0, f1, cache.data());
      }
      int n = 0;
      auto flush = [&] {
        sine_cosine(soa, n, ys, xs);
        atan2_degrees(ys, xs, ts, n);
        count(ts, n);
        n = 0;
      };
      // The normals' arrays as locals: the stores below may alias anything
      // in memory, and read through soa the pointers were reloaded per edge.
      float *const ax = soa[0], *const ay = soa[1], *const az = soa[2];
      float *const gx = soa[3], *const gy = soa[4], *const gz = soa[5];
      const float* const normals = whole ? whole_normals.data() : cache.data();
      auto push = [&](const float* n1, const float* ng) {
        ax[n] = n1[0]; ay[n] = n1[1]; az[n] = n1[2];
        gx[n] = ng[0]; gy[n] = ng[1]; gz[n] = ng[2];
        if (++n == kBlock) flush();
      };
      if (!whole) {
        std::vector<Waiting>& here = waiting[size_t((f0 - b) / kFaces)];
        for (const Waiting& w : here) push(w.n, normals + 3 * size_t(w.face - f0));
        std::vector<Waiting>().swap(here);
      }
      // The edge at corner c, its first (d = opp[c] > c).
      auto edge = [&](int32_t c, int32_t d) {
        const int64_t g = d / 3;
        const float* n1 = normals + 3 * size_t(c / 3 - h0);
        if (g < h1) {
          push(n1, normals + 3 * size_t(g - h0));
        } else if (g < e) {
          waiting[size_t((g - b) / kFaces)].push_back({int32_t(g), {n1[0], n1[1], n1[2]}});
        } else {
          float far[3];
          face_normals_or_nan(mesh, g, g + 1, far);
          push(n1, far);
        }
      };
      int32_t c = int32_t(3 * f0);
      const int32_t c_end = int32_t(3 * f1);
#if ITEAS_X86_FEATURES
      if (wide512) {
        // Sixteen corners at a time: the edges whose faces are both in the
        // block listed by their normals' offsets, their normals gathered a
        // list at a time; the others (the second face in a later block or
        // piece) one at a time, as below. The tally does not depend on the
        // order of the edges. (One at a time, the loop branches on whether a
        // corner is its edge's first, which follows no pattern. Uniform jobs
        // with the statistics, one thread, medians: bunny-npm level 1 0.627 ->
        // 0.571 ms, level 4 29.6 -> 28.4 ms, bunny level 2 4.42 -> 3.99 ms.)
        int32_t near_a[kBlock], near_b[kBlock], others[256];
        int n_near = 0, n_others = 0;
        for (;;) {
          c = list_block_edges_avx512(opp, base, c, c_end, int32_t(h0), int32_t(h1), near_a, near_b, n_near,
                                      kBlock, others, n_others, 256);
          const bool last = c + 16 > c_end;
          if (last || n_others + 16 > 256) {
            for (int i = 0; i < n_others; ++i) edge(others[i], opp[others[i] - base]);
            n_others = 0;
          }
          if (last || n_near + 16 > kBlock) {
            flush();  // the pushed edges first: the gathered take the arrays
            gather_block_normals_avx512(normals, near_a, near_b, n_near, soa);
            n = n_near;
            flush();
            n_near = 0;
          }
          if (last) break;
        }
      }
#endif
      for (; c < c_end; ++c) {
        const int32_t d = opp[c - base];
        if (d < c) continue;
        edge(c, d);
      }
      flush();
    }
    std::lock_guard<std::mutex> lock(mutex);
    all.merge(tally);
  }, theta ? 2048 : kFaces);  // normals: a block a piece (outside it, one more each)
  if (with_quality) *quality = quality_tallies.summary();
  AngleSummary total;
  total.edges = all.edges;
  total.above = all.above;
  total.max = double(all.max);
  for (int k = 0; k < AngleTally::kBins; ++k) total.histogram[k] = all.hist[k];
  total.mean = total.edges ? double(all.sum) / AngleTally::kUnits / double(total.edges) : 0;
  return total;
}
}  // namespace

AngleSummary summarize_angles(const Mesh& mesh, const CornerTable& ct, const Array<float>* theta,
                              double threshold, double exclude, int threads, QualitySummary* quality) {
  OppositeSource source;
  source.all = ct.opposites().data();
  return summarize(mesh, source, theta, threshold, exclude, threads, quality);
}

#if ITEAS_X86_FEATURES
namespace {
// count_angles_above over corners [c, end) sixteen at a time, with the
// tally's comparisons (TallyBounds): a first corner's angle counts when it
// reaches |above| and does not reach |excluded| (a NaN angle reaches
// neither; a NaN bound is reached by none). Returns the count; |c| advances
// to the first corner not looked at.
__attribute__((target("avx512f"))) int64_t count_above_avx512(const int32_t* opp, const float* theta, int32_t& c,
                                                               int32_t end, float above, float excluded) {
  const __m512 a = _mm512_set1_ps(above), x = _mm512_set1_ps(excluded);
  int64_t count = 0;
  for (; c + 16 <= end; c += 16) {
    const __m512i at = sixteen_from(c);
    const __mmask16 first = _mm512_cmpgt_epi32_mask(_mm512_loadu_si512(opp + c), at);
    const __m512 t = _mm512_loadu_ps(theta + c);
    const __mmask16 kept = __mmask16(~_mm512_cmp_ps_mask(t, x, _CMP_GE_OQ));
    const __mmask16 hit = _mm512_mask_cmp_ps_mask(first, t, a, _CMP_GE_OQ) & kept;
    count += __builtin_popcount(hit);
  }
  return count;
}
}  // namespace
#endif

int64_t count_angles_above(const CornerTable& ct, const Array<float>& theta, double threshold, double exclude,
                           int threads) {
  const int32_t* opp = ct.opposites().data();
  const float* th = theta.data();
#if ITEAS_X86_FEATURES
  const bool wide512 = cpu_has(CpuFeature::kAvx512);
  const TallyBounds bounds(threshold, exclude);
#endif
  std::atomic<int64_t> total{0};
  parallel_for(ct.num_corners(), threads, [&](int64_t b, int64_t e) {
    int64_t count = 0;
    int32_t c = int32_t(b);
#if ITEAS_X86_FEATURES
    if (wide512) count = count_above_avx512(opp, th, c, int32_t(e), bounds.above, bounds.excluded);
#endif
    for (; c < int32_t(e); ++c) {
      const float t = th[c];
      count += opp[c] > c && AngleTally::counted(t, exclude) && double(t) > threshold;
    }
    total.fetch_add(count, std::memory_order_relaxed);
  }, 16384);
  return total.load(std::memory_order_relaxed);
}

AngleSummary summarize_split_angles(const Mesh& children, const Array<int32_t>& parent_opposites, double threshold,
                                    double exclude, int threads, QualitySummary* quality) {
  OppositeSource source;
  source.parent = parent_opposites.data();
  source.parent_corners = int64_t(parent_opposites.size());
  return summarize(children, source, nullptr, threshold, exclude, threads, quality);
}

std::string ThresholdSpec::text() const {
  std::ostringstream o;
  switch (kind) {
    case Kind::kMean: return "mean";
    case Kind::kMedian: return "median";
    case Kind::kPercentile: o << 'p' << value; return o.str();
    case Kind::kDegrees: o << value; return o.str();
  }
  return "mean";
}

double compute_threshold(const ThresholdSpec& spec, const Mesh& mesh, const CornerTable& ct,
                         const Array<float>& theta, double exclude, int threads) {
  if (spec.kind == ThresholdSpec::Kind::kDegrees) return spec.value;
  if (spec.kind == ThresholdSpec::Kind::kMean)
    return summarize_angles(mesh, ct, &theta, 0, exclude, threads).mean;
  std::vector<float> values;
  const int32_t nc = ct.num_corners();
  for (int32_t c = 0; c < nc; ++c) {
    if (ct.opposite(c) < c) continue;
    const float t = theta[c];
    if (std::isnan(t) || (exclude > 0 && t >= exclude)) continue;
    values.push_back(t);
  }
  if (values.empty()) return 0;
  const double q = spec.kind == ThresholdSpec::Kind::kMedian ? 50.0 : spec.value;
  // Nearest-rank percentile: deterministic and an actual edge angle.
  size_t rank = size_t(std::ceil(q / 100.0 * double(values.size())));
  rank = std::min(values.size(), std::max<size_t>(1, rank)) - 1;
  std::nth_element(values.begin(), values.begin() + rank, values.end());
  return values[rank];
}

double smallest_angle_sin2(const double* p, const double* q, const double* r) {
  double u[3], w[3], z[3];
  for (int i = 0; i < 3; ++i) { u[i] = q[i] - p[i]; w[i] = r[i] - p[i]; z[i] = r[i] - q[i]; }
  const double cr[3] = {u[1] * w[2] - u[2] * w[1], u[2] * w[0] - u[0] * w[2], u[0] * w[1] - u[1] * w[0]};
  const double e0 = z[0] * z[0] + z[1] * z[1] + z[2] * z[2];
  const double e1 = w[0] * w[0] + w[1] * w[1] + w[2] * w[2];
  const double e2 = u[0] * u[0] + u[1] * u[1] + u[2] * u[2];
  const double prod = e0 * e1 * e2;
  if (prod <= 0) return -1;
  return (cr[0] * cr[0] + cr[1] * cr[1] + cr[2] * cr[2]) * std::min(e0, std::min(e1, e2)) / prod;
}

ITEAS_SELECTS_VECTORISE ITEAS_WIDE_CLONES void smallest_angle_sin2s(const double* const* pqr, int n, double* out) {
  const double *__restrict px = pqr[0], *__restrict py = pqr[1], *__restrict pz = pqr[2];
  const double *__restrict qx = pqr[3], *__restrict qy = pqr[4], *__restrict qz = pqr[5];
  const double *__restrict rx = pqr[6], *__restrict ry = pqr[7], *__restrict rz = pqr[8];
  double* __restrict o = out;
  for (int i = 0; i < n; ++i) {
    const double u0 = qx[i] - px[i], u1 = qy[i] - py[i], u2 = qz[i] - pz[i];
    const double w0 = rx[i] - px[i], w1 = ry[i] - py[i], w2 = rz[i] - pz[i];
    const double z0 = rx[i] - qx[i], z1 = ry[i] - qy[i], z2 = rz[i] - qz[i];
    const double c0 = u1 * w2 - u2 * w1, c1 = u2 * w0 - u0 * w2, c2 = u0 * w1 - u1 * w0;
    const double e0 = z0 * z0 + z1 * z1 + z2 * z2;
    const double e1 = w0 * w0 + w1 * w1 + w2 * w2;
    const double e2 = u0 * u0 + u1 * u1 + u2 * u2;
    const double prod = e0 * e1 * e2;
    const double m12 = e2 < e1 ? e2 : e1, emin = m12 < e0 ? m12 : e0;  // std::min's selects
    const double v = (c0 * c0 + c1 * c1 + c2 * c2) * emin / prod;
    o[i] = prod <= 0 ? -1.0 : v;
  }
}

QualitySummary triangle_quality(const Mesh& mesh, int threads) {
  // Smallest angle per face; the 1st percentile comes from a histogram of
  // 0.01-degree bins over [0, 60]. The smallest angle lies opposite the
  // shortest edge: with squared edge lengths e and twice the area |cr|,
  // tan = |cr| / ((e_a + e_b - e_min) / 2) — one square root and the
  // polynomial atan2, no inverse sine.
  // Each thread counts into a histogram of its own (QualityTallies): counts
  // and a minimum do not depend on the order in which they are gathered, so
  // the pieces may be any size (a small level is split over the threads too,
  // where fixed chunks of 32768 faces left it on one).
  const int32_t nf = mesh.num_faces();
  QualityTallies tallies(threads);
  parallel_for(nf, threads, [&](int64_t b, int64_t e) {
    // Per block of faces: the points gathered, the atan2 arguments (double
    // arithmetic) and the angles (vectorised loops), then the minimum and
    // the histogram.
    PointBlock points;
    QualityTallies::Lease lease(tallies);
    for (int32_t f0 = int32_t(b); f0 < int32_t(e); f0 += PointBlock::kSize) {
      const int n = int(std::min(int64_t(PointBlock::kSize), e - f0));
      points.gather(mesh, nullptr, f0, n);
      lease.tally().add(points, n);
    }
  }, 2048);
  return tallies.summary();
}

}  // namespace iteas
