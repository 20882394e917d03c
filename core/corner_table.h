// Corner table (Rossignac; Draco's mesh/corner_table.h): corner c of face c/3,
// next/previous by arithmetic, one opposite array (-1 = boundary), one corner
// per vertex. Non-manifold edges (3+ faces) and edges whose two faces disagree
// in orientation are cut into boundary edges; vertices whose corners form more
// than one fan (non-manifold vertices) are split into one vertex per fan. All of
// it is counted, never asserted.
#pragma once

#include <climits>
#include <cstdint>
#include <functional>
#include <vector>

#if defined(__GNUC__) && defined(__x86_64__)
#include <immintrin.h>
#elif defined(__SSE2__)
#include <emmintrin.h>
#endif

#include "core/mesh.h"

namespace iteas {

// Corners c >= 0. Arithmetic, not a choice: GCC compiled the conditional
// forms into branches on c % 3, which has no pattern where corners come in no
// order (uniform levels 2 and 3 ran 5-12 % faster without them).
inline int32_t next_corner(int32_t c) {
  const uint32_t r = uint32_t(c) % 3u;
  return c + 1 - 3 * int32_t(r >> 1);  // r == 2: back to the face's first corner
}
inline int32_t prev_corner(int32_t c) {
  const uint32_t r = uint32_t(c) % 3u;
  return c - 1 + 3 * int32_t((r - 1u) >> 31);  // r == 0: on to the face's last corner
}

#if defined(__GNUC__) && defined(__x86_64__)
// next_corner and prev_corner of eight corners in an AVX2 register, without
// division by 3 (c mod 3 from the high half of c * 0xAAAAAAAB; c >= 0).
__attribute__((target("avx2"), always_inline)) inline void next_prev_corners_avx2(const __m256i& c, __m256i& next,
                                                                                   __m256i& prev) {
  const __m256i magic = _mm256_set1_epi32(int32_t(0xAAAAAAABu));
  const __m256i q_even = _mm256_srli_epi64(_mm256_mul_epu32(c, magic), 33);
  const __m256i q_odd = _mm256_srli_epi64(_mm256_mul_epu32(_mm256_srli_epi64(c, 32), magic), 33);
  const __m256i q = _mm256_blend_epi32(q_even, _mm256_slli_epi64(q_odd, 32), 0xAA);
  const __m256i r3 = _mm256_sub_epi32(c, _mm256_add_epi32(q, _mm256_add_epi32(q, q)));
  const __m256i one = _mm256_set1_epi32(1);
  next = _mm256_add_epi32(_mm256_add_epi32(c, one),
                          _mm256_and_si256(_mm256_cmpeq_epi32(r3, _mm256_set1_epi32(2)), _mm256_set1_epi32(-3)));
  prev = _mm256_add_epi32(_mm256_sub_epi32(c, one),
                          _mm256_and_si256(_mm256_cmpeq_epi32(r3, _mm256_setzero_si256()), _mm256_set1_epi32(3)));
}

// floor(v / 3) of sixteen lanes 0 <= v < 2^31 in an AVX-512 register, from the
// high half of v * 0xAAAAAAAB (>> 33), even and odd lanes. (The masked forms:
// GCC 12 warns of the plain ones' undefined pass-through operand.)
__attribute__((target("avx512f"), always_inline)) inline __m512i div3_epi32_avx512(const __m512i& v) {
  const __m512i magic = _mm512_set1_epi32(int32_t(0xAAAAAAABu));
  const __m512i q_even = _mm512_maskz_srli_epi64(0xFF, _mm512_maskz_mul_epu32(0xFF, v, magic), 33);
  const __m512i q_odd =
      _mm512_maskz_srli_epi64(0xFF, _mm512_maskz_mul_epu32(0xFF, _mm512_maskz_srli_epi64(0xFF, v, 32), magic), 33);
  return _mm512_mask_blend_epi32(0xAAAA, q_even, _mm512_maskz_slli_epi64(0xFF, q_odd, 32));
}
#endif

// Uniform 1:4 split, children of face f numbered 4f+j (child j < 3 keeps the
// parent's corner j, child 3 is the centre): where parent corner c, at a kept
// vertex, lands (corner k of face f becomes corner k of child k). The rings and
// the vertices' corners follow their corners through a level with it.
inline int32_t kept_child_corner(int32_t c) { return 3 * (4 * (c / 3) + c % 3) + c % 3; }

// The children's opposites of a uniform split (uniform_level's numbering:
// face f's children are 4f + j, child j < 3 keeping the parent's corner j,
// child 3 the centre) of parent faces [f0, f1), from the parent's opposites
// |opp| (|nc| corners) alone: out[i] is child corner 12 f0 + i's. With
// |wide|, four faces at a time where the processor has AVX-512.
void split_opposites(const int32_t* opp, int64_t nc, int64_t f0, int64_t f1, int32_t* out, bool wide);

// Bit i set when p[i] == x, for i < n <= 8. Reads 8 entries whatever n is (the
// caller pads its arrays): one SSE2 compare instead of a branch per entry,
// whose outcome varies from call to call and was mispredicted.
inline unsigned equal_mask8(const int32_t* p, int32_t x, int n) {
  const unsigned keep = (1u << n) - 1;
#if defined(__SSE2__)
  const __m128i v = _mm_set1_epi32(x);
  const __m128i lo = _mm_loadu_si128(reinterpret_cast<const __m128i*>(p));
  const __m128i hi = _mm_loadu_si128(reinterpret_cast<const __m128i*>(p + 4));
  return (unsigned(_mm_movemask_ps(_mm_castsi128_ps(_mm_cmpeq_epi32(lo, v)))) |
          unsigned(_mm_movemask_ps(_mm_castsi128_ps(_mm_cmpeq_epi32(hi, v)))) << 4) &
         keep;
#else
  unsigned m = 0;
  for (int i = 0; i < 8; ++i) m |= unsigned(p[i] == x) << i;
  return m & keep;
#endif
}

// Each edge's canonical corner: c with opposite[c] < 0 or c < opposite[c]
// (one unsigned comparison, a boundary's -1 being the largest). Over the
// corners [begin, end): how many (count_canonical_corners), or the list of
// them in order into |out|, which has room for end - begin
// (list_canonical_corners, returns how many). |wide|: 16 corners at a time
// where the processor has AVX-512; false: one at a time, for tests (the same
// answers).
int64_t count_canonical_corners(const int32_t* opposite, int64_t begin, int64_t end, bool wide = true);
int64_t list_canonical_corners(const int32_t* opposite, int64_t begin, int64_t end, int32_t* out, bool wide = true);

struct TopologyReport {
  int64_t boundary_edges = 0;         // edges with one face after cutting
  int64_t non_manifold_edges = 0;     // undirected edges used by 3+ faces (each cut)
  int64_t orientation_conflicts = 0;  // 2-face edges whose faces disagree (cut)
  int64_t split_vertices = 0;         // extra vertices made for non-manifold fans
};

class CornerTable {
 public:
  // Builds opposites for |mesh|. Splits non-manifold vertices in |mesh| (adding
  // vertices with the same position, wedges follow) when |split_vertices|.
  // |record_order|: also keep each vertex's fan in walk order (fan_order()).
  // |wide|: runs of 3-8 corners matched in AVX2 registers where the
  // processor has AVX2; false: SSE2 only, for tests (the same table).
  // |beside|, if given, runs once, on another thread while this one sorts
  // the corners by vertex (a serial step), or after it on this one when
  // there is no other; it is done before the matching starts. It may read
  // |mesh| (nothing writes it until then) and must not start parallel loops
  // of more than one thread.
  TopologyReport build(Mesh& mesh, bool split_vertices, int threads = 1, bool record_order = false, bool wide = true,
                       const std::function<void()>& beside = nullptr);

  // The table of |mesh| made from this one, that of the mesh it was refined
  // from, equal to what build(mesh, false) gives: |kept_from| per face of
  // |mesh|, the face of the old mesh it copies unchanged (same corners in the
  // same order, kept faces in their old relative order) or -1; |touched| per
  // vertex of |mesh|, 1 when a face round it changed or it is new (old
  // vertices keep their numbers). Only the runs of touched vertices are
  // matched; the rest is renumbered. The old table must be build(old, false)'s
  // (no vertices split). False, the table unchanged, when the maps do not fit it.
  bool update(const Mesh& mesh, const std::vector<int32_t>& kept_from, const std::vector<uint8_t>& touched,
              int threads = 1);

  int32_t opposite(int32_t c) const { return opposite_[c]; }
  // For a boundary vertex: the corner whose fan walk by swing_right() covers
  // the whole fan (its previous edge is a boundary edge). -1 for unused vertices.
  int32_t vertex_corner(int32_t v) const { return vertex_corner_[v]; }
  int32_t num_corners() const { return static_cast<int32_t>(opposite_.size()); }

  // The corner at the same vertex in the neighbouring face across the edge
  // (c, next(c))'s opposite side; -1 at a boundary. Walks the fan one way.
  int32_t swing_right(int32_t c) const {
    const int32_t o = opposite_[next_corner(c)];
    return o < 0 ? -1 : next_corner(o);
  }
  int32_t swing_left(int32_t c) const {
    const int32_t o = opposite_[prev_corner(c)];
    return o < 0 ? -1 : prev_corner(o);
  }

  // Per vertex, the faces of the fan that starts at vertex_corner(): n for a
  // closed fan, -n for an open one, 0 for an unused vertex, kUnknownFan where
  // the walk found a malformed fan. Recorded by build() from the walk it makes
  // anyway, so that classifying vertices needs no second walk; empty once the
  // table is changed by other means (forget_fans()).
  static constexpr int32_t kUnknownFan = INT32_MIN;
  const std::vector<int32_t>& fans() const { return fan_; }
  // With |record_order|: the corners of the recorded fan of vertex v (below
  // the vertex count build() started with), from vertex_corner(v) turning
  // right, |fans()[v]| or |-fans()[v]| of them; null when not recorded.
  const int32_t* fan_order(int32_t v) const {
    if (size_t(v) + 1 >= fan_offset_.size() || fan_[v] == 0 || fan_[v] == kUnknownFan) return nullptr;
    const int32_t* order = fan_corner_.data() + fan_offset_[v];
    return order[0] == vertex_corner_[v] ? order : nullptr;
  }
  // With fan_order(v): the vertex after each of those corners in its face
  // (the ring of v in walk order); null when not recorded or when vertices
  // were split.
  const int32_t* fan_neighbours(int32_t v) const {
    return fan_next_.empty() ? nullptr : fan_next_.data() + fan_offset_[v];
  }
  // With |record_order|: the number of corners vertex v had when the table
  // was built (its run, before any vertex was split off it); -1 when not
  // recorded. Equal to |fans()[v]| when v's recorded fan holds all of them.
  int32_t recorded_corners(int32_t v) const {
    return size_t(v) + 1 < fan_offset_.size() ? fan_offset_[v + 1] - fan_offset_[v] : -1;
  }
  // The recorded fans as arrays, for loops over many vertices: per vertex
  // below |vertices| (0 when not recorded), |offset[v]| to |offset[v + 1]|
  // in |corner| and |next| (next null when fan_neighbours() is).
  struct Recorded {
    const int32_t* offset;
    const int32_t* corner;
    const int32_t* next;
    int32_t vertices;
  };
  Recorded recorded() const {
    return {fan_offset_.data(), fan_corner_.data(), fan_next_.empty() ? nullptr : fan_next_.data(),
            fan_offset_.empty() ? 0 : int32_t(fan_offset_.size() - 1)};
  }
  void forget_fans() {
    std::vector<int32_t>().swap(fan_);
    std::vector<int32_t>().swap(fan_offset_);
    Array<int32_t>().swap(fan_corner_);
    Array<int32_t>().swap(fan_next_);
  }

  Array<int32_t>& opposites() { return opposite_; }
  const Array<int32_t>& opposites() const { return opposite_; }
  std::vector<int32_t>& vertex_corners() { return vertex_corner_; }
  const std::vector<int32_t>& vertex_corners() const { return vertex_corner_; }

 private:
  Array<int32_t> opposite_;
  std::vector<int32_t> vertex_corner_;
  std::vector<int32_t> fan_;
  std::vector<int32_t> fan_offset_;  // record_order: per vertex + 1, into fan_corner_
  Array<int32_t> fan_corner_;        // record_order: the fans' corners in walk order
  Array<int32_t> fan_next_;          // record_order: the vertex after each of those in its face
};

}  // namespace iteas
