#include "core/corner_table.h"

#include <algorithm>
#include <atomic>
#include <unordered_map>

#include "core/cpu_features.h"
#include "core/parallel.h"

#if ITEAS_X86_FEATURES
#include <immintrin.h>
#define ITEAS_AVX2_MATCH 1
#else
#define ITEAS_AVX2_MATCH 0
#endif

namespace iteas {
namespace {

// Loops over vertices walk a fan each (several corners): smaller pieces than
// the per-corner loops still pay for a thread.
constexpr int64_t kVertexGrain = 512;
// Chunks of a compaction in two passes (parallel_count_fill).
constexpr int64_t kCompactChunk = 4096;

// Corners grouped by vertex in two passes (count, prefix sum, fill), as
// meshoptimizer builds adjacency. Next to each corner, the vertices before
// and after it in its face: a vertex's run then holds both its outgoing edges
// (v -> next) and its incoming ones (prev -> v), so the edge matching below
// reads one contiguous run per vertex and nothing else.
struct VertexCorners {
  static constexpr size_t kPad = 8;
  // Per entry: its corner, and in one 8-byte pair the vertices after and
  // before that corner in its face. The fill then makes two stores per corner
  // where three arrays took three, each to a line of its own (bunny-npm,
  // 11,022 corners: 16.0 against 19.1 us), and the AVX-512 matcher takes a
  // run's next and previous vertices from one register.
  struct Pair {
    int32_t next, prev;
  };
  std::vector<int32_t> offset;  // nv + 1
  Array<int32_t> corners;
  Array<Pair> pairs;
  int32_t corner(int64_t i) const { return corners[size_t(i)]; }
  int32_t next(int64_t i) const { return pairs[size_t(i)].next; }
  int32_t prev(int64_t i) const { return pairs[size_t(i)].prev; }
  // Room for |n| entries, then kPad entries matching no vertex: a run of up
  // to 8 is then compared 8 at a time without reading past the arrays. The
  // n entries are left for the fill to write.
  void size_for(size_t n) {
    corners.resize(n + kPad);
    pairs.resize(n + kPad);
    for (size_t i = n; i < n + kPad; ++i) {
      corners[i] = -1;
      pairs[i] = Pair{-1, -1};
    }
  }
  // Counting sort, on the calling thread whatever the threads. Split between
  // two threads it was slower than on one (bunny-npm: 17 µs on one thread):
  // by faces, a vertex's run held corners from both threads and its lines
  // went back and forth between the cores (36 µs); by ranges of vertices,
  // each thread reading every corner, the input written by the caller had to
  // come over to the other core (31 µs; bun_zipper 0.71 against 0.54 ms).
  // The idle worker spins through the fill and joins the matching.
  void build(const Array<int32_t>& corner_vertex, int32_t nv) {
    const int32_t nc = static_cast<int32_t>(corner_vertex.size());
    offset.resize(size_t(nv) + 1);
    size_for(size_t(nc));
    const int32_t* cv = corner_vertex.data();
    // at[v]: the count of v, then where its next corner goes.
    std::vector<int32_t> at(size_t(nv), 0);
    for (int32_t c = 0; c < nc; ++c) ++at[cv[c]];
    int32_t total = 0;
    for (int32_t v = 0; v < nv; ++v) {
      offset[v] = total;
      total += at[v];
      at[v] = offset[v];
    }
    offset[nv] = total;
    int32_t* co = corners.data();
    Pair* pa = pairs.data();
    int32_t* a = at.data();
    for (int32_t f = 0; f < nc; f += 3) {
      const int32_t x = cv[f], y = cv[f + 1], z = cv[f + 2];
      int32_t i = a[x]++;
      co[i] = f;
      pa[i] = Pair{y, z};
      i = a[y]++;
      co[i] = f + 1;
      pa[i] = Pair{z, x};
      i = a[z]++;
      co[i] = f + 2;
      pa[i] = Pair{x, y};
    }
  }
  // The runs of some vertices only: run r holds the corners of the vertex v
  // with id[v] == r, in corner order as build() has them; |at| lists every
  // corner of those vertices in corner order.
  void build_some(const Array<int32_t>& corner_vertex, const Array<int32_t>& at, const Array<int32_t>& id,
                  int32_t runs) {
    offset.assign(size_t(runs) + 1, 0);
    for (int32_t c : at) ++offset[size_t(id[corner_vertex[c]]) + 1];
    for (int32_t r = 0; r < runs; ++r) offset[r + 1] += offset[r];
    size_for(at.size());
    std::vector<int32_t> fill(offset.begin(), offset.end() - 1);
    for (int32_t c : at) {
      const int32_t i = fill[id[corner_vertex[c]]]++;
      corners[i] = c;
      pairs[i] = Pair{corner_vertex[next_corner(c)], corner_vertex[prev_corner(c)]};
    }
  }
};

// Set bits of a byte (a table: without -mpopcnt the builtin is a library call).
struct BitCounts {
  uint8_t n[256];
  constexpr BitCounts() : n() {
    for (int i = 1; i < 256; ++i) n[i] = uint8_t(n[i >> 1] + (i & 1));
  }
  constexpr uint8_t operator[](unsigned i) const { return n[i]; }
};
constexpr BitCounts kBits;

// In a run of n entries whose previous and next vertices are |prevs| and
// |nexts| (at least 8 readable): how many entries have prev b (edges
// b -> a, |reverse|; |match| the index in the run of the last) and how many
// have next b (edges a -> b, |same|). Runs of up to 8 (nearly every vertex)
// are compared 8 at a time.
inline void count_edges(const int32_t* prevs, const int32_t* nexts, int32_t n, int32_t b, int32_t& reverse,
                        int32_t& same, int32_t& match) {
  if (n <= 8) {
    const unsigned r = equal_mask8(prevs, b, n), s = equal_mask8(nexts, b, n);
    reverse = kBits[r];
    same = kBits[s];
    match = r ? 31 - __builtin_clz(r) : -1;
    return;
  }
  for (int32_t j = 0; j < n; ++j) {
    if (prevs[j] == b) { ++reverse; match = j; }
    same += nexts[j] == b;
  }
}

// The fan of a run of n entries whose matching |right| (entry -> the entry
// turning right from it) is a permutation: the walk from right[0] is a
// cycle of |faces| <= n steps. It takes n steps whatever its length (no
// exit to mispredict), counting those before it returns to |first|; order
// entries past the cycle are written too, never read (a fan order is read
// only as far as the fan's recorded size).
__attribute__((always_inline)) inline void walk_fan(const int32_t* corners, const int32_t* nexts,
                                                    const int32_t* right, int n, int32_t* order, int32_t* order_next,
                                                    int32_t& first, int32_t& faces) {
  first = right[0];
  int32_t x = first, count = 0;
  bool back = false;
  for (int step = 0; step < n; ++step) {
    if (order) {
      order[step] = corners[x];
      order_next[step] = nexts[x];
    }
    x = right[x];
    count += !back;
    back |= x == first;
  }
  faces = count;
}

// A run of N corners (3 <= N <= 8) whose every edge is matched once each way,
// as at nearly every vertex: the matching below with N known to the compiler.
// Its loops are unrolled (no exit to mispredict: N varies from vertex to
// vertex). False when some edge is not matched once each way; the generic
// pass then rewrites this run's opposites. Otherwise |right| is a
// permutation (two entries matching the same one would share their next
// vertex), and walk_fan follows it.
// kMax 8: n <= 8 (in match_manifold, n a constant after inlining); kMax 16:
// 9 <= n <= 16, read as two compares of eight per entry (16 entries of each
// array: n >= 9 and kPad after the last run keep that inside them).
template <int kMax>
__attribute__((always_inline)) inline bool match_manifold_n(const VertexCorners& vc, int32_t rb, int n,
                                                            int32_t* opposite, int32_t* order, int32_t* order_next,
                                                            int32_t& first, int32_t& faces) {
  static_assert(kMax == 8 || kMax == 16, "runs of up to 8 or 9-16");
  // The run's next and previous vertices apart (entries from n on belong to
  // other runs or to the padding: read, never used).
  const int32_t* corners = vc.corners.data() + rb;
  int32_t nexts[kMax], prevs[kMax];
  for (int i = 0; i < kMax; ++i) {
    nexts[i] = vc.next(rb + i);
    prevs[i] = vc.prev(rb + i);
  }
  int32_t right[kMax];
  unsigned bad = 0, matched = 0;
  for (int i = 0; i < n; ++i) {
    const int32_t b = nexts[i];
    const unsigned r = kMax == 8 ? equal_mask8(prevs, b, n)
                                 : equal_mask8(prevs, b, 8) | equal_mask8(prevs + 8, b, n - 8) << 8;
    bad |= (r & (r - 1)) | unsigned(r == 0);
    const int m = __builtin_ctz(r | 1u << (kMax - 1));  // the last when r == 0 (then bad)
    matched |= 1u << m;
    opposite[prev_corner(corners[i])] = next_corner(corners[m]);
    right[m] = i;
  }
  // Each b -> a matched once; each a -> b occurring once is then the same as
  // every entry being matched (two entries with the same next b would match
  // the same entry, leaving another unmatched).
  if (bad | (matched ^ ((1u << n) - 1))) return false;
  walk_fan(corners, nexts, right, n, order ? order + rb : nullptr, order ? order_next + rb : nullptr, first, faces);
  return true;
}

template <int N>
inline bool match_manifold(const VertexCorners& vc, int32_t rb, int32_t* opposite, int32_t* order,
                           int32_t* order_next, int32_t& first, int32_t& faces) {
  return match_manifold_n<8>(vc, rb, N, opposite, order, order_next, first, faces);
}

// match_manifold for runs of 9-16 corners (vertices of high valence: about
// one in forty of a typical mesh's, which the generic pass below matched in
// a quarter of the matching's time), n known at run time.
inline bool match_manifold_16(const VertexCorners& vc, int32_t rb, int n, int32_t* opposite, int32_t* order,
                              int32_t* order_next, int32_t& first, int32_t& faces) {
  return match_manifold_n<16>(vc, rb, n, opposite, order, order_next, first, faces);
}

#if ITEAS_AVX2_MATCH
// Rotations within a run of n (3..8) entries: lane i of kRot.r[n][k] is
// (i + k) mod n (lanes from n on: themselves, never read).
struct Rotations {
  alignas(32) int32_t r[9][8][8];
  constexpr Rotations() : r() {
    for (int n = 0; n < 9; ++n)
      for (int k = 0; k < 8; ++k)
        for (int i = 0; i < 8; ++i) r[n][k][i] = (n >= 3 && i < n) ? (i + k) % n : i;
  }
};
constexpr Rotations kRot;

// walk_fan for the register matchers: |right| (lane j: the entry turning
// right from entry j) a permutation of the n valid lanes. The walk by
// doubling: lane s of |at| is the entry s steps from right[0] (steps of 1, 2
// and 4 where s has those bits), without the chain of n loads, each waiting
// on the one before. Writes the fan's corners and next vertices (|C|, |X|
// in walk order) where |order| is not null.
__attribute__((target("avx2"), always_inline)) inline void walk_fan_avx2(const __m256i& right, const __m256i& C,
                                                                          const __m256i& X, const __m256i& valid,
                                                                          unsigned keep, int n, int32_t* order,
                                                                          int32_t* order_next, int32_t& first,
                                                                          int32_t& faces) {
  first = _mm256_cvtsi256_si32(right);
  const __m256i right2 = _mm256_permutevar8x32_epi32(right, right);
  const __m256i right4 = _mm256_permutevar8x32_epi32(right2, right2);
  const __m256i start = _mm256_set1_epi32(first);
  __m256i at = _mm256_blend_epi32(start, _mm256_permutevar8x32_epi32(right, start), 0xAA);
  at = _mm256_blend_epi32(at, _mm256_permutevar8x32_epi32(right2, at), 0xCC);
  at = _mm256_blend_epi32(at, _mm256_permutevar8x32_epi32(right4, at), 0xF0);
  if (order) {
    _mm256_maskstore_epi32(order, valid, _mm256_permutevar8x32_epi32(C, at));
    _mm256_maskstore_epi32(order_next, valid, _mm256_permutevar8x32_epi32(X, at));
  }
  // The cycle's length: the first step s >= 1 back at right[0], else n.
  const unsigned back = unsigned(_mm256_movemask_ps(_mm256_castsi256_ps(_mm256_cmpeq_epi32(at, start)))) & keep & ~1u;
  faces = back ? int32_t(__builtin_ctz(back)) : n;
}

// The next and previous vertices of the eight entries from |p| on, lane i
// holding entry i's: the pairs' even and odd lanes, put in order.
__attribute__((target("avx2"), always_inline)) inline void load_pairs_avx2(const VertexCorners::Pair* p, __m256i& X,
                                                                            __m256i& P) {
  const __m256i a = _mm256_loadu_si256(reinterpret_cast<const __m256i*>(p));      // pairs 0-3
  const __m256i b = _mm256_loadu_si256(reinterpret_cast<const __m256i*>(p + 4));  // pairs 4-7
  const __m256i even = _mm256_setr_epi32(0, 2, 4, 6, 1, 3, 5, 7);
  const __m256i sa = _mm256_permutevar8x32_epi32(a, even), sb = _mm256_permutevar8x32_epi32(b, even);
  X = _mm256_permute2x128_si256(sa, sb, 0x20);
  P = _mm256_permute2x128_si256(sa, sb, 0x31);
}

// match_manifold for a run of n (3..8) entries in registers of eight lanes:
// every entry's next vertex against the previous vertex of the entry k
// places further round the run, for k = 0..n-1 (n compares for the whole
// run, where match_manifold makes two per entry behind a dispatch on n,
// which varies from vertex to vertex). Accepts exactly the runs match_manifold
// accepts (every entry matched once each way) and writes the same
// opposites, fan order and fan size.
__attribute__((target("avx2"))) inline bool match_manifold_avx2(const VertexCorners& vc, int32_t rb, int n,
                                                                  int32_t* opposite, int32_t* order,
                                                                  int32_t* order_next, int32_t& first,
                                                                  int32_t& faces) {
  const __m256i C = _mm256_loadu_si256(reinterpret_cast<const __m256i*>(vc.corners.data() + rb));
  __m256i X, P;
  load_pairs_avx2(vc.pairs.data() + rb, X, P);
  const __m256i lane = _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7);
  const __m256i valid = _mm256_cmpgt_epi32(_mm256_set1_epi32(n), lane);
  __m256i hits = _mm256_setzero_si256(), hits_j = hits, offset = hits, right = hits;
  for (int k = 0; k < n; ++k) {
    const __m256i rot = _mm256_load_si256(reinterpret_cast<const __m256i*>(kRot.r[n][k]));
    const __m256i back = _mm256_load_si256(reinterpret_cast<const __m256i*>(kRot.r[n][k == 0 ? 0 : n - k]));
    // eq lane i: entry (i + k) mod n's previous vertex is entry i's next.
    const __m256i eq = _mm256_and_si256(valid, _mm256_cmpeq_epi32(X, _mm256_permutevar8x32_epi32(P, rot)));
    hits = _mm256_add_epi32(hits, eq);
    offset = _mm256_add_epi32(offset, _mm256_and_si256(eq, _mm256_set1_epi32(k)));
    // Seen from entry j = (i + k) mod n: matched by entry (j - k) mod n.
    const __m256i eq_j = _mm256_permutevar8x32_epi32(eq, back);
    hits_j = _mm256_add_epi32(hits_j, eq_j);
    right = _mm256_add_epi32(right, _mm256_and_si256(eq_j, back));
  }
  const __m256i minus_one = _mm256_set1_epi32(-1);
  const __m256i once = _mm256_and_si256(_mm256_cmpeq_epi32(hits, minus_one), _mm256_cmpeq_epi32(hits_j, minus_one));
  const unsigned keep = (1u << n) - 1;
  if ((unsigned(_mm256_movemask_ps(_mm256_castsi256_ps(once))) & keep) != keep) return false;
  // m = (i + offset) mod n.
  __m256i m = _mm256_add_epi32(lane, offset);
  m = _mm256_sub_epi32(m, _mm256_and_si256(_mm256_cmpgt_epi32(m, _mm256_set1_epi32(n - 1)), _mm256_set1_epi32(n)));
  __m256i next, prev;
  next_prev_corners_avx2(C, next, prev);
  alignas(32) int32_t before[8], after[8];
  _mm256_store_si256(reinterpret_cast<__m256i*>(before), prev);
  _mm256_store_si256(reinterpret_cast<__m256i*>(after), _mm256_permutevar8x32_epi32(next, m));
  for (int i = 0; i < n; ++i) opposite[before[i]] = after[i];
  walk_fan_avx2(right, C, X, valid, keep, n, order ? order + rb : nullptr, order ? order_next + rb : nullptr,
                first, faces);
  return true;
}

// Lanes 0-7 of row r: entry 2r's previous vertex, lanes 8-15: entry
// 2r + 1's (lanes 4r + 1 and 4r + 3 of the run's pairs), across a register
// of the run's next vertices twice over.
struct PairRows {
  alignas(64) int32_t r[4][16];
  constexpr PairRows() : r() {
    for (int k = 0; k < 4; ++k)
      for (int i = 0; i < 16; ++i) r[k][i] = 2 * (2 * k + (i >> 3)) + 1;
  }
};
constexpr PairRows kPairRows;

// match_manifold_avx2 with the whole n x n comparison at once: four compares
// of sixteen lanes give the matrix whose byte j holds the entries i whose
// next vertex is entry j's previous one. Every entry is matched once each way
// when each of the n rows holds one bit and the rows cover the n columns;
// right[j] is then the one bit of row j (its exponent as a float). The same
// runs accepted, the same opposites, fan order and fan size.
__attribute__((target("avx512f,avx512vl,avx2"))) inline bool match_manifold_avx512(
    const VertexCorners& vc, int32_t rb, int n, int32_t* opposite, int32_t* order, int32_t* order_next,
    int32_t& first, int32_t& faces) {
  const __m256i C = _mm256_loadu_si256(reinterpret_cast<const __m256i*>(vc.corners.data() + rb));
  // The run's eight pairs in one register: the next vertices its even lanes,
  // the previous ones its odd lanes. XX: the next vertices twice over; X its
  // low half (a shuffle: GCC 12's casts and conversions to 256 bits start from
  // an undefined register, which it reports as maybe uninitialised).
  const __m512i pair = _mm512_loadu_si512(vc.pairs.data() + rb);
  const __m512i XX = _mm512_maskz_permutexvar_epi32(
      0xFFFF, _mm512_setr_epi32(0, 2, 4, 6, 8, 10, 12, 14, 0, 2, 4, 6, 8, 10, 12, 14), pair);
  using V16 = int32_t __attribute__((vector_size(64)));
  const __m256i X = __m256i(__builtin_shufflevector(V16(XX), V16(XX), 0, 1, 2, 3, 4, 5, 6, 7));
  uint64_t matrix = 0;
  for (int k = 0; k < 4; ++k) {
    const __m512i rows = _mm512_load_si512(kPairRows.r[k]);
    const __mmask16 eq = _mm512_cmpeq_epi32_mask(XX, _mm512_maskz_permutexvar_epi32(0xFFFF, rows, pair));
    matrix |= uint64_t(_cvtmask16_u32(eq)) << (16 * k);
  }
  const unsigned keep = (1u << n) - 1;
  // Rows and columns from n on belong to other runs.
  matrix &= (n == 8 ? ~uint64_t(0) : (uint64_t(1) << (8 * n)) - 1) & (0x0101010101010101ull * keep);
  uint64_t columns = matrix | matrix >> 32;
  columns |= columns >> 16;
  columns |= columns >> 8;
  const __m256i row = _mm256_cvtepu8_epi32(_mm_cvtsi64_si128(int64_t(matrix)));
  const __m256i zero = _mm256_setzero_si256();
  const __m256i one_bit = _mm256_andnot_si256(
      _mm256_cmpeq_epi32(row, zero),
      _mm256_cmpeq_epi32(_mm256_and_si256(row, _mm256_sub_epi32(row, _mm256_set1_epi32(1))), zero));
  if ((unsigned(_mm256_movemask_ps(_mm256_castsi256_ps(one_bit))) & keep) != keep || (columns & 0xff) != keep)
    return false;
  const __m256i right = _mm256_sub_epi32(_mm256_srli_epi32(_mm256_castps_si256(_mm256_cvtepi32_ps(row)), 23),
                                         _mm256_set1_epi32(127));
  const __m256i lane = _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7);
  const __m256i valid = _mm256_cmpgt_epi32(_mm256_set1_epi32(n), lane);
  // Entry j's corner's next is the opposite of the corner before entry
  // right[j]'s; scattered under a mask (a loop of n stores mispredicted its
  // exit, n varying from vertex to vertex).
  __m256i next, prev;
  next_prev_corners_avx2(C, next, prev);
  _mm256_mask_i32scatter_epi32(opposite, __mmask8(keep), _mm256_permutevar8x32_epi32(prev, right), next, 4);
  walk_fan_avx2(right, C, X, valid, keep, n, order ? order + rb : nullptr, order ? order_next + rb : nullptr,
                first, faces);
  return true;
}
#endif

// Runs longer than this are matched in a buffer from the heap.
struct RunScratch {
  static constexpr int32_t kLocal = 64;
  int32_t local[4 * kLocal];
  std::vector<int32_t> large;
};

// The matching of one vertex's run of corners [rb, re) (see build()): writes
// the opposite of the corner before each of the run's corners, the vertex's
// corner and its fan size. False, with |split|, for a vertex whose corners
// form several fans (left to the splitting pass, nothing recorded for it).
// |cut_kind| (per corner, may be null) says why a corner got no opposite;
// |cuts| counts those corners and notes whether any was cut for another
// reason than the boundary (non-manifold or orientation conflict).
struct Cuts {
  int64_t corners = 0;
  bool not_boundary = false;
};
// kWidth: 0 SSE2, 1 AVX2, 2 AVX-512 (runs of 3-8 in registers).
template <int kWidth>
__attribute__((always_inline)) inline bool match_run(const VertexCorners& vc, int32_t rb, int32_t re, int32_t* opposite,
                                                     int32_t* order, int32_t* order_next, uint8_t* cut_kind,
                                                     Cuts* cuts, bool split,
                                                     int32_t& vertex_corner, int32_t& fan, RunScratch& scratch) {
  const int32_t n = re - rb;
  int32_t first = 0, faces = 0;
  bool manifold = false;
  if constexpr (kWidth == 2) {
#if ITEAS_AVX2_MATCH
    if (n >= 3 && n <= 8) manifold = match_manifold_avx512(vc, rb, n, opposite, order, order_next, first, faces);
#endif
  } else if constexpr (kWidth == 1) {
#if ITEAS_AVX2_MATCH
    if (n >= 3 && n <= 8) manifold = match_manifold_avx2(vc, rb, n, opposite, order, order_next, first, faces);
#endif
  } else {
    switch (n) {
      case 3: manifold = match_manifold<3>(vc, rb, opposite, order, order_next, first, faces); break;
      case 4: manifold = match_manifold<4>(vc, rb, opposite, order, order_next, first, faces); break;
      case 5: manifold = match_manifold<5>(vc, rb, opposite, order, order_next, first, faces); break;
      case 6: manifold = match_manifold<6>(vc, rb, opposite, order, order_next, first, faces); break;
      case 7: manifold = match_manifold<7>(vc, rb, opposite, order, order_next, first, faces); break;
      case 8: manifold = match_manifold<8>(vc, rb, opposite, order, order_next, first, faces); break;
      default: break;
    }
  }
  if (n > 8 && n <= 16) manifold = match_manifold_16(vc, rb, n, opposite, order, order_next, first, faces);
  if (manifold) {  // closed fans, as the generic walk below would find
    if (split && faces != n) return false;
    vertex_corner = vc.corner(rb + first);
    fan = faces;
    return true;
  }
  // right, left, then the run's next and previous vertices (8 at least:
  // count_edges reads 8).
  const int32_t m = std::max<int32_t>(n, 8);
  if (m > RunScratch::kLocal) scratch.large.resize(4 * size_t(m));
  int32_t* right = m > RunScratch::kLocal ? scratch.large.data() : scratch.local;
  int32_t* left = right + m;
  int32_t* nexts = left + m;
  int32_t* prevs = nexts + m;
  for (int32_t i = 0; i < m; ++i) {
    right[i] = -1;
    nexts[i] = i < n ? vc.next(rb + i) : -1;
    prevs[i] = i < n ? vc.prev(rb + i) : -1;
  }
  bool open = false;
  for (int32_t i = 0; i < n; ++i) {
    const int32_t b = nexts[i], c = prev_corner(vc.corner(rb + i));
    int32_t reverse = 0, same = 0, match = -1;  // b -> a edges; a -> b edges, c's own included
    count_edges(prevs, nexts, n, b, reverse, same, match);
    if (reverse == 1 && same == 1) {
      opposite[c] = next_corner(vc.corner(rb + match));
      left[i] = match;
      right[match] = i;
      continue;
    }
    opposite[c] = -1;
    left[i] = -1;
    open = true;
    const uint8_t kind = reverse + same >= 3 ? 1 : (same == 2 ? 2 : 0);
    if (cut_kind) cut_kind[c] = kind;
    if (cuts) {
      ++cuts->corners;
      cuts->not_boundary |= kind != 0;
    }
  }
  // Left links are one-to-one, so the walk left meets the start again or ends.
  if (!open) first = right[0] >= 0 ? right[0] : 0;
  else
    for (int32_t x = left[0]; x >= 0 && x != 0; x = left[x]) first = x;
  bool closed = false;
  for (int32_t x = first;;) {
    if (order && faces < n) {
      order[rb + faces] = vc.corner(rb + x);
      order_next[rb + faces] = nexts[x];
    }
    ++faces;
    const int32_t s = right[x];
    if (s < 0) break;
    if (s == first) { closed = true; break; }
    if (faces > n) break;
    x = s;
  }
  if (split && faces != n) return false;
  vertex_corner = vc.corner(rb + first);
  fan = faces > n ? CornerTable::kUnknownFan : (closed ? faces : -faces);
  return true;
}

// The matching of runs [begin, end), run r being vertex r's (or, with
// |vertex_of|, vertex vertex_of[r]'s); true when some vertex has several
// fans (recorded in |several| when |split|).
template <int kWidth>
__attribute__((always_inline)) inline bool match_range(const VertexCorners& vc, int64_t begin, int64_t end,
                                                       const int32_t* vertex_of, int32_t* opposite, int32_t* order,
                                                       int32_t* order_next, uint8_t* cut_kind, Cuts* cuts, bool split,
                                                       int32_t* vertex_corner, int32_t* fan, uint8_t* several) {
  RunScratch scratch;
  bool found = false;
  for (int64_t r = begin; r < end; ++r) {
    const int32_t rb = vc.offset[r], re = vc.offset[r + 1];
    if (re == rb) continue;
    const int64_t a = vertex_of ? vertex_of[r] : r;
    if (!match_run<kWidth>(vc, rb, re, opposite, order, order_next, cut_kind, cuts, split, vertex_corner[a], fan[a],
                          scratch)) {
      several[a] = 1;
      found = true;
    }
  }
  return found;
}

#if ITEAS_AVX2_MATCH
__attribute__((target("avx2"))) bool match_range_avx2(const VertexCorners& vc, int64_t begin, int64_t end,
                                                       const int32_t* vertex_of, int32_t* opposite, int32_t* order,
                                                       int32_t* order_next, uint8_t* cut_kind, Cuts* cuts, bool split,
                                                       int32_t* vertex_corner, int32_t* fan, uint8_t* several) {
  return match_range<1>(vc, begin, end, vertex_of, opposite, order, order_next, cut_kind, cuts, split,
                        vertex_corner, fan, several);
}

__attribute__((target("avx512f,avx512vl,avx2"))) bool match_range_avx512(
    const VertexCorners& vc, int64_t begin, int64_t end, const int32_t* vertex_of, int32_t* opposite, int32_t* order,
    int32_t* order_next, uint8_t* cut_kind, Cuts* cuts, bool split, int32_t* vertex_corner, int32_t* fan,
    uint8_t* several) {
  return match_range<2>(vc, begin, end, vertex_of, opposite, order, order_next, cut_kind, cuts, split,
                        vertex_corner, fan, several);
}
#endif

// match_range with the compares of runs of 3-8 in AVX-512 or AVX2 registers
// where |wide| and the processor has them (the same table every way).
bool match_runs(bool wide, const VertexCorners& vc, int64_t begin, int64_t end, const int32_t* vertex_of,
                int32_t* opposite, int32_t* order, int32_t* order_next, uint8_t* cut_kind, Cuts* cuts, bool split,
                int32_t* vertex_corner, int32_t* fan, uint8_t* several) {
#if ITEAS_AVX2_MATCH
  if (wide && cpu_has(CpuFeature::kAvx512))
    return match_range_avx512(vc, begin, end, vertex_of, opposite, order, order_next, cut_kind, cuts, split,
                              vertex_corner, fan, several);
  if (wide && cpu_has(CpuFeature::kAvx2))
    return match_range_avx2(vc, begin, end, vertex_of, opposite, order, order_next, cut_kind, cuts, split,
                            vertex_corner, fan, several);
#else
  (void)wide;
#endif
  return match_range<0>(vc, begin, end, vertex_of, opposite, order, order_next, cut_kind, cuts, split,
                        vertex_corner, fan, several);
}

}  // namespace

TopologyReport CornerTable::build(Mesh& mesh, bool split_vertices, int threads, bool record_order, bool wide,
                                  const std::function<void()>& beside) {
  TopologyReport report;
  const Array<int32_t>& cv = mesh.corner_vertex;
  const int32_t nc = static_cast<int32_t>(cv.size());
  VertexCorners vc;
  if (beside && resolve_threads(threads) > 1) {
    // The sort as piece 0 (the caller's share), |beside| as piece 1 (the
    // worker's, or the caller's after the sort when the worker is late).
    parallel_for_chunks(2, 2, [&](int64_t b, int64_t e) {
      for (int64_t k = b; k < e; ++k) {
        if (k == 0) vc.build(cv, mesh.num_vertices());
        else beside();
      }
    });
  } else {
    vc.build(cv, mesh.num_vertices());
    if (beside) beside();
  }
  opposite_.resize(nc);  // every entry is written below

  // Per corner c: its edge runs a = v(next c) -> b = v(prev c); its corner at
  // a is y = next(c), and the entry of y in a's run has next b. The opposite
  // face has the edge b -> a: an entry of a's run whose prev is b (corner y'),
  // and the opposite corner is next(y'). Both directions are counted to detect
  // cuts: an edge stays only when each direction occurs once. Per vertex, so
  // each corner is written by exactly one vertex (that of next(c)). With
  // several matches the last in corner order is kept, as in the corner-order
  // pass this replaced (the results are the same).
  // The same matching links the vertex's corners into its fans: the entry
  // whose incoming edge b -> a is matched is followed, turning right round a,
  // by the entry whose outgoing edge is a -> b (right/left below, indices into
  // the run). Each vertex's fan is then walked on its own run, in cache,
  // instead of chasing opposites written by other vertices.
  // A vertex's corner is the start of the fan holding its first corner: for a
  // vertex with only closed fans (no corner lacks a left neighbour) the corner
  // right of the first one, else the end of the walk left from it. The fan
  // from there is walked once: its size tells a non-manifold vertex (left, when
  // splitting, to the pass below, in order) and is recorded for classifying
  // vertices.
  const int32_t nv = mesh.num_vertices();
  // Per corner without an opposite (others are not read): 0 boundary, 1
  // non-manifold, 2 orientation conflict.
  Array<uint8_t> cut_kind(nc);
  std::vector<uint8_t> several(split_vertices ? nv : 0, 0);
  vertex_corner_.assign(nv, -1);
  fan_.assign(nv, 0);
  std::vector<int32_t>().swap(fan_offset_);
  Array<int32_t>().swap(fan_corner_);
  Array<int32_t>().swap(fan_next_);
  if (record_order) {
    fan_offset_ = vc.offset;
    fan_corner_.resize(nc);
    fan_next_.resize(nc);
  }
  int32_t* order = record_order ? fan_corner_.data() : nullptr;
  int32_t* order_next = record_order ? fan_next_.data() : nullptr;
  std::atomic<int64_t> cut_corners{0};
  std::atomic<bool> odd_cuts{false}, any_several{false};
  parallel_for(nv, threads, [&](int64_t begin, int64_t end) {
    Cuts cuts;
    const bool found = match_runs(wide, vc, begin, end, nullptr, opposite_.data(), order, order_next, cut_kind.data(),
                                  &cuts, split_vertices, vertex_corner_.data(), fan_.data(), several.data());
    if (found) any_several.store(true, std::memory_order_relaxed);
    if (cuts.corners) cut_corners.fetch_add(cuts.corners, std::memory_order_relaxed);
    if (cuts.not_boundary) odd_cuts.store(true, std::memory_order_relaxed);
  }, kVertexGrain);
  // Every corner without an opposite is a boundary edge after cutting; the
  // edges cut for another reason are told apart (each undirected edge counted
  // once, by its smallest corner) only when there are any.
  report.boundary_edges = cut_corners.load();
  if (odd_cuts.load()) {
    std::unordered_map<uint64_t, uint8_t> seen;
    for (int32_t c = 0; c < nc; ++c) {
      if (opposite_[c] >= 0 || cut_kind[c] == 0) continue;
      int32_t a = cv[next_corner(c)], b = cv[prev_corner(c)];
      if (a > b) std::swap(a, b);
      const uint64_t key = (uint64_t(uint32_t(a)) << 32) | uint32_t(b);
      if (seen.emplace(key, cut_kind[c]).second) {
        if (cut_kind[c] == 1) ++report.non_manifold_edges;
        else ++report.orientation_conflicts;
      }
    }
  }
  if (!split_vertices || !any_several.load()) return report;  // no vertex to split
  // Fans: walk each vertex's corners; every fan after the first gets a new vertex.
  std::vector<uint8_t> visited(nc, 0);
  std::vector<int32_t> fan;
  std::unordered_map<uint64_t, int32_t> clone_of;
  for (int32_t v = 0; v < nv; ++v) {
    if (!several[v]) continue;
    for (int32_t i = vc.offset[v]; i < vc.offset[v + 1]; ++i) {
      const int32_t start = vc.corner(i);
      if (visited[start]) continue;
      // Walk left to the start of an open fan (or all the way round).
      int32_t first = start;
      for (int32_t c = swing_left(start); c >= 0 && c != start; c = swing_left(c)) first = c;
      fan.clear();
      int32_t c = first;
      do {
        fan.push_back(c);
        visited[c] = 1;
        c = swing_right(c);
      } while (c >= 0 && c != first && !visited[c]);
      const int32_t faces = int32_t(fan.size());
      const int32_t fan_of = c == first ? faces : (c < 0 ? -faces : kUnknownFan);
      int32_t target = v;
      if (vertex_corner_[v] >= 0) {
        target = mesh.num_vertices();
        for (int k = 0; k < 3; ++k) mesh.positions.push_back(mesh.positions[3 * size_t(v) + k]);
        for (VertexChannel& ch : mesh.vertex_channels)
          for (int k = 0; k < 3; ++k) ch.data.push_back(ch.data[3 * size_t(v) + k]);
        vertex_corner_.push_back(-1);
        fan_.push_back(0);
        ++report.split_vertices;
      }
      vertex_corner_[target] = first;
      fan_[target] = fan_of;
      if (target == v) continue;
      for (int32_t fc : fan) {
        mesh.corner_vertex[fc] = target;
        if (!mesh.has_wedges()) continue;
        // Wedges belong to one vertex: clone a wedge shared across fans.
        const int32_t w = mesh.corner_wedge[fc];
        const uint64_t key = (uint64_t(uint32_t(w)) << 32) | uint32_t(target);
        auto it = clone_of.find(key);
        int32_t nw;
        if (it != clone_of.end()) {
          nw = it->second;
        } else {
          nw = mesh.add_wedge(target);
          for (Channel& ch : mesh.channels)
            for (int k = 0; k < ch.components; ++k)
              ch.data[size_t(nw) * ch.components + k] = ch.data[size_t(w) * ch.components + k];
          clone_of.emplace(key, nw);
        }
        mesh.corner_wedge[fc] = nw;
      }
    }
  }
  // A split vertex renumbered the corners of its other fans: the next
  // vertices recorded before then may be stale.
  if (report.split_vertices) Array<int32_t>().swap(fan_next_);
  return report;
}

#if ITEAS_X86_FEATURES
namespace {
// split_opposites four faces at a time: each corner's opposite d as 12 (d / 3)
// plus the child corner its half-edges land on (a table by d mod 3), -1 at
// the boundary; the 48 opposites picked from those two registers by three
// fixed permutations, the inner edges' (the face's own children) blended
// in. Returns the first face left to the caller.
struct OppositePick {
  alignas(64) int32_t idx[3][16];    // from A (0-15) or C (16-31): see kOppositeOf
  alignas(64) int32_t inner[3][16];  // 12 t + the inner corner where |inner_mask| is set
  uint16_t inner_mask[3];
  constexpr OppositePick() : idx(), inner(), inner_mask() {
    // Child corner j of a face: the inner edge's corner (>= 0), else -1 - k
    // for the first half (A) or -4 - k for the second half (C) of the parent
    // edge opposite corner k.
    constexpr int kOppositeOf[12] = {9, -4 - 1, -1 - 2, -1 - 0, 10, -4 - 2, -4 - 0, -1 - 1, 11, 0, 4, 8};
    for (int i = 0; i < 48; ++i) {
      const int t = i / 12, j = i % 12, o = kOppositeOf[j];
      if (o >= 0) {
        inner[i / 16][i % 16] = 12 * t + o;
        inner_mask[i / 16] = uint16_t(inner_mask[i / 16] | (1u << (i % 16)));
      } else {
        idx[i / 16][i % 16] = o >= -3 ? 3 * t + (-1 - o) : 16 + 3 * t + (-4 - o);
      }
    }
  }
};
constexpr OppositePick kOppositePick;

__attribute__((target("avx512f"))) int64_t split_opposites_avx512(const int32_t* opp, int64_t b, int64_t e,
                                                                   int64_t nc, int32_t* no) {
  // 3 kPrev[l] + l and 3 kNext[l] + l for l = d mod 3 (split_opposites' tables).
  const __m512i first_half = _mm512_setr_epi32(6, 1, 5, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0);
  const __m512i second_half = _mm512_setr_epi32(3, 7, 2, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0);
  const __m512i zero = _mm512_setzero_si512();
  const __m512i minus_one = _mm512_set1_epi32(-1);
  int64_t f = b;
  for (; f + 4 <= e && 3 * f + 16 <= nc; f += 4) {
    const __m512i d = _mm512_loadu_si512(opp + 3 * f);
    const __mmask16 boundary = _mm512_cmplt_epi32_mask(d, zero);
    const __m512i q = div3_epi32_avx512(d);  // (at a boundary's -1, not used)
    const __m512i l = _mm512_sub_epi32(d, _mm512_mullo_epi32(q, _mm512_set1_epi32(3)));
    const __m512i g12 = _mm512_mullo_epi32(q, _mm512_set1_epi32(12));
    const __m512i a = _mm512_mask_mov_epi32(
        _mm512_add_epi32(g12, _mm512_maskz_permutexvar_epi32(0xFFFF, l, first_half)), boundary, minus_one);
    const __m512i c = _mm512_mask_mov_epi32(
        _mm512_add_epi32(g12, _mm512_maskz_permutexvar_epi32(0xFFFF, l, second_half)), boundary, minus_one);
    const __m512i base = _mm512_set1_epi32(int32_t(12 * f));
    int32_t* out = no + 12 * (f - b);
    for (int z = 0; z < 3; ++z) {
      const __m512i picked = _mm512_permutex2var_epi32(a, _mm512_load_si512(kOppositePick.idx[z]), c);
      const __m512i inner = _mm512_add_epi32(base, _mm512_load_si512(kOppositePick.inner[z]));
      _mm512_storeu_si512(out + 16 * z, _mm512_mask_blend_epi32(kOppositePick.inner_mask[z], picked, inner));
    }
  }
  return f;
}

}  // namespace
#endif

void split_opposites(const int32_t* opp, int64_t nc, int64_t f0, int64_t f1, int32_t* out, bool wide) {
  static constexpr int kNext[3] = {1, 2, 0}, kPrev[3] = {2, 0, 1};
  int64_t from = f0;
#if ITEAS_X86_FEATURES
  if (wide && cpu_has(CpuFeature::kAvx512)) from = split_opposites_avx512(opp, f0, f1, nc, out);
#else
  (void)wide;
  (void)nc;
#endif
  for (int64_t f = from; f < f1; ++f) {
    const int32_t p = int32_t(3 * f), base = int32_t(12 * f);  // first corner of child 0
    int32_t* no = out + 12 * (f - f0);  // child corner base + i at no[i]
    for (int k = 0; k < 3; ++k) {
      // Inner edges: child k's corner k faces the centre's corner k.
      no[3 * k + k] = base + 9 + k;
      no[9 + k] = base + 3 * k + k;
      // The halves of the parent edge opposite corner k lie in children
      // k+1 and k+2 at local corner k; their twins in the neighbour's children.
      const int32_t d = opp[p + k];
      const int a = 3 * kNext[k] + k, c = 3 * kPrev[k] + k;
      if (d < 0) {
        no[a] = no[c] = -1;
      } else {
        const int32_t l = d % 3, g4 = 4 * (d - l);  // 12 (d / 3) = 4 (d - l)
        no[a] = g4 + 3 * kPrev[l] + l;
        no[c] = g4 + 3 * kNext[l] + l;
      }
    }
  }
}

#if ITEAS_X86_FEATURES
namespace {
// count_canonical_corners (kList false) and list_canonical_corners over the
// whole blocks of sixteen corners from |begin|: one unsigned compare of the
// opposites against the corners' own numbers, its mask counted, and the
// corners it keeps packed to the front of a register (stored whole: n <= c -
// begin, so the lanes past the kept ones are overwritten later or lie in the
// list's spare room). Adds to |n|; returns the first corner left.
template <bool kList>
__attribute__((target("avx512f"))) int64_t canonical_blocks_avx512(const int32_t* opp, int64_t begin, int64_t end,
                                                                    int32_t* out, int64_t& n) {
  __m512i at = _mm512_add_epi32(_mm512_set1_epi32(int32_t(begin)),
                                _mm512_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15));
  const __m512i sixteen = _mm512_set1_epi32(16);
  int64_t c = begin;
  for (; c + 16 <= end; c += 16) {
    const __mmask16 canonical = _mm512_cmpgt_epu32_mask(_mm512_loadu_si512(opp + c), at);
    if (kList) _mm512_storeu_si512(out + n, _mm512_maskz_compress_epi32(canonical, at));
    n += __builtin_popcount(canonical);
    at = _mm512_add_epi32(at, sixteen);
  }
  return c;
}
}  // namespace
#endif

namespace {
// count_canonical_corners, or with |kList| list_canonical_corners: the
// blocks of 16 where |wide| and the processor has AVX-512, the rest (or all)
// one corner at a time.
template <bool kList>
int64_t canonical_corners(const int32_t* opp, int64_t begin, int64_t end, int32_t* out, bool wide) {
  int64_t n = 0, c = begin;
#if ITEAS_X86_FEATURES
  if (wide && cpu_has(CpuFeature::kAvx512)) c = canonical_blocks_avx512<kList>(opp, begin, end, out, n);
#else
  (void)wide;
#endif
  for (; c < end; ++c) {
    if constexpr (kList) out[n] = int32_t(c);  // kept only when canonical (no branch)
    n += uint32_t(opp[c]) > uint32_t(c);
  }
  return n;
}
}  // namespace

int64_t count_canonical_corners(const int32_t* opp, int64_t begin, int64_t end, bool wide) {
  return canonical_corners<false>(opp, begin, end, nullptr, wide);
}

int64_t list_canonical_corners(const int32_t* opp, int64_t begin, int64_t end, int32_t* out, bool wide) {
  return canonical_corners<true>(opp, begin, end, out, wide);
}

bool CornerTable::update(const Mesh& mesh, const std::vector<int32_t>& kept_from, const std::vector<uint8_t>& touched,
                         int threads) {
  const Array<int32_t>& cv = mesh.corner_vertex;
  const int32_t nc = static_cast<int32_t>(cv.size()), nf = nc / 3, nv = mesh.num_vertices();
  const int32_t old_nf = num_corners() / 3, old_nv = static_cast<int32_t>(vertex_corner_.size());
  if (int32_t(kept_from.size()) != nf || int32_t(touched.size()) != nv || nv < old_nv ||
      int32_t(fan_.size()) != old_nv)
    return false;
  // Where each kept face went (each old face is kept once at most).
  Array<int32_t> moved(old_nf);
  std::atomic<bool> consistent{true};
  parallel_for(old_nf, threads, [&](int64_t b, int64_t e) { std::fill(moved.begin() + b, moved.begin() + e, -1); });
  parallel_for(nf, threads, [&](int64_t b, int64_t e) {
    bool ok = true;
    for (int64_t f = b; f < e; ++f) {
      const int32_t from = kept_from[f];
      if (from < 0) continue;
      if (from >= old_nf) { ok = false; continue; }
      moved[from] = int32_t(f);
    }
    if (!ok) consistent.store(false, std::memory_order_relaxed);
  });
  if (!consistent.load()) return false;
  auto remap = [&](int32_t c) { return c < 0 ? -1 : 3 * moved[c / 3] + c % 3; };
  // An untouched vertex's faces are all kept, so its run is the one it had,
  // renumbered in the same order: the opposites of the corners before its
  // corners, its corner and its fan follow. Every corner whose next is
  // untouched is therefore in a kept face.
  // Per face, which of its corners' vertices are touched (bit k: corner k),
  // the face's three flags read once for both uses.
  Array<int32_t> opposite(nc);
  Array<uint8_t> touched_corners(nf);
  parallel_for(nf, threads, [&](int64_t b, int64_t e) {
    const int32_t* fv = cv.data();
    const uint8_t* tv = touched.data();
    const int32_t* kept = kept_from.data();
    const int32_t* old = opposite_.data();
    int32_t* out = opposite.data();
    uint8_t* mask = touched_corners.data();
    bool ok = true;
    for (int64_t f = b; f < e; ++f) {
      const bool t[3] = {tv[fv[3 * f]] != 0, tv[fv[3 * f + 1]] != 0, tv[fv[3 * f + 2]] != 0};
      mask[f] = uint8_t(t[0] | t[1] << 1 | t[2] << 2);
      const int32_t from = kept[f];
      for (int k = 0; k < 3; ++k) {
        if (t[k == 2 ? 0 : k + 1]) continue;  // the corner's next vertex
        if (from < 0) { ok = false; continue; }
        const int32_t o = old[3 * from + k];
        ok &= o < 0 || moved[o / 3] >= 0;
        out[3 * f + k] = ok ? remap(o) : -1;
      }
    }
    if (!ok) consistent.store(false, std::memory_order_relaxed);
  });
  if (!consistent.load()) return false;
  // Untouched vertices keep their corner (renumbered) and fan; touched ones
  // are numbered in vertex order (id: their run) for the matching below.
  // (id, vertex_of and at below: no zero fill, every entry is written.)
  std::vector<int32_t> vertex_corner(nv), fan(nv);
  Array<int32_t> id(nv), vertex_of;
  const uint8_t* tv = touched.data();
  const int32_t runs = int32_t(parallel_count_fill(
      nv, threads, kCompactChunk,
      [tv](int64_t b, int64_t e) {
        int64_t n = 0;
        for (int64_t v = b; v < e; ++v) n += tv[v] != 0;
        return n;
      },
      [&vertex_of](int64_t total) { vertex_of.resize(size_t(total)); },
      [&](int64_t b, int64_t e, int64_t at) {
        bool ok = true;
        for (int64_t v = b; v < e; ++v) {
          if (tv[v]) {
            id[v] = int32_t(at);
            vertex_of[size_t(at++)] = int32_t(v);
            vertex_corner[v] = -1;
            fan[v] = 0;
            continue;
          }
          id[v] = -1;
          ok &= v < old_nv;  // new vertices are touched
          vertex_corner[v] = v < old_nv ? remap(vertex_corner_[v]) : -1;
          fan[v] = v < old_nv ? fan_[v] : 0;
        }
        if (!ok) consistent.store(false, std::memory_order_relaxed);
      }));
  if (!consistent.load()) return false;
  // The touched vertices matched as build() matches every vertex: their
  // corners listed in corner order, without branches (on a level that
  // changed much, whether a corner is touched follows no pattern) while the
  // chunk has room for a face's three stores (the spare ones are written
  // over by the next entries).
  Array<int32_t> at;
  const uint8_t* mask = touched_corners.data();
  parallel_count_fill(
      nf, threads, kCompactChunk,
      [mask](int64_t b, int64_t e) {
        int64_t n = 0;
        for (int64_t f = b; f < e; ++f) n += kBits[mask[f]];
        return n;
      },
      [&at](int64_t total) { at.resize(size_t(total)); },
      [&at, mask](int64_t b, int64_t e, int64_t n, int64_t end) {
        int32_t* list = at.data();
        for (int64_t f = b; f < e; ++f) {
          const unsigned m = mask[f];
          if (m == 0) continue;  // after the first levels nearly every face
          if (end - n >= 3) {
            for (int k = 0; k < 3; ++k) {
              list[n] = int32_t(3 * f + k);
              n += m >> k & 1;
            }
          } else {
            for (int k = 0; k < 3; ++k)
              if (m >> k & 1) list[n++] = int32_t(3 * f + k);
          }
        }
      });
  VertexCorners vc;
  vc.build_some(cv, at, id, runs);
  parallel_for(runs, threads, [&](int64_t begin, int64_t end) {
    match_runs(true, vc, begin, end, vertex_of.data(), opposite.data(), nullptr, nullptr, nullptr, nullptr, false,
               vertex_corner.data(), fan.data(), nullptr);
  }, kVertexGrain);
  opposite_.swap(opposite);
  vertex_corner_.swap(vertex_corner);
  fan_.swap(fan);
  std::vector<int32_t>().swap(fan_offset_);
  Array<int32_t>().swap(fan_corner_);
  Array<int32_t>().swap(fan_next_);
  return true;
}

}  // namespace iteas
