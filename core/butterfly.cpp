#include "core/butterfly.h"

#include <algorithm>
#include <atomic>
#include <cmath>
#include <type_traits>

#if defined(__GNUC__) && defined(__x86_64__)
#include <immintrin.h>
#endif

#include "core/cpu_features.h"
#include "core/parallel.h"

#define ITEAS_INLINE inline __attribute__((always_inline))

namespace iteas {

bool mark_sharp_edges(const CornerTable& ct, const Array<float>* theta, double crease_angle,
                      std::vector<uint8_t>& sharp, int threads) {
  const bool creases = crease_angle > 0 && theta;
  const int32_t nc = ct.num_corners();
  sharp.resize(nc);
  parallel_for(nc, threads, [&](int64_t b, int64_t e) {
    // Locals, and a loop per case: the byte stores may alias anything, and
    // the arrays' pointers were reloaded after each of them (no vectorising).
    const int32_t* opp = ct.opposites().data();
    uint8_t* out = sharp.data();
    if (creases) {
      const float* t = theta->data();
      const double limit = crease_angle;
      for (int64_t c = b; c < e; ++c) out[c] = uint8_t(int(opp[c] < 0) | int(t[c] >= limit));
    } else {
      for (int64_t c = b; c < e; ++c) out[c] = uint8_t(opp[c] < 0);
    }
  });
  return !creases;
}

void classify_vertices(const Mesh& mesh, const CornerTable& ct, const std::vector<uint8_t>& sharp,
                       VertexClass& out, int threads, bool sharp_is_boundary) {
  const int32_t nv = mesh.num_vertices();
  out.valence.assign(nv, 0);
  out.complete.assign(nv, 0);
  // The fans the corner table recorded: with no crease, a closed fan has no
  // sharp edge (each of its edges has a face on both sides), so the walk below
  // would find what they say.
  const bool recorded = sharp_is_boundary && ct.fans().size() == size_t(nv);
  parallel_for(nv, threads, [&](int64_t b, int64_t e) {
    for (int64_t v = b; v < e; ++v) {
      const int32_t first = ct.vertex_corner(int32_t(v));
      if (first < 0) continue;
      if (recorded && ct.fans()[v] != CornerTable::kUnknownFan) {
        const int32_t f = ct.fans()[v];
        out.valence[v] = f > 0 ? f : 1 - f;
        out.complete[v] = VertexClass::flags(f >= 3, out.valence[v]);
        continue;
      }
      int32_t faces = 0, c = first;
      bool closed = false, has_sharp = false;
      while (true) {
        ++faces;
        // outgoing edge v -> next (no flags: the boundary is what is sharp)
        if (sharp.empty() ? ct.opposite(prev_corner(c)) < 0 : sharp[prev_corner(c)] != 0) has_sharp = true;
        const int32_t s = ct.swing_right(c);
        if (s < 0) break;
        if (s == first) { closed = true; break; }
        if (faces > ct.num_corners()) break;  // defensive: malformed fan
        c = s;
      }
      out.valence[v] = closed ? faces : faces + 1;
      // The extraordinary rules need a ring of 3 or more (a closed fan of two
      // faces, from a doubled triangle, would get weights that do not sum to 1).
      out.complete[v] = VertexClass::flags(closed && !has_sharp && faces >= 3, out.valence[v]);
    }
  }, 512);  // a fan walk per vertex: smaller pieces than per-corner loops
}

namespace {
void ring_points(const Mesh& mesh, const VertexClass& vclass, RingTable& rings, int threads, bool wide);

// The extraordinary rule's walk round a vertex passes over the apex corners
// of second green children: their bisecting edge (c, m) is not in the
// parent's ring (discount_green_apices takes it from the valence). From
// corner x (-1: none) on, the first corner that is not such an apex.
// (extraordinary_terms walks so; build_level_rings stores that walk.)
inline int32_t past_green_apices(const CornerTable& ct, const uint8_t* green, int32_t x) {
  while (x >= 0 && green[x / 3] == 2 && x % 3 == 2) x = ct.swing_right(x);
  return x;
}
}  // namespace

namespace {
// Where each vertex below |limit| starts its ring in the ring table: -1 for
// a vertex without one (not complete, regular, valence under 3, or without a
// corner: then |unringed|), else the valences of the ringed vertices before
// it summed. Returns the entries of all rings.
int64_t ring_offsets_narrow(const VertexClass& vclass, const int32_t* vertex_corner, int32_t begin, int32_t limit,
                            int64_t total, int32_t* offset, bool& unringed) {
  for (int32_t v = begin; v < limit; ++v) {
    const int32_t k = vclass.valence[v];
    offset[v] = -1;
    if (!vclass.complete[v] || k == 6 || k < 3) continue;
    if (vertex_corner[v] < 0) { unringed = true; continue; }
    offset[v] = int32_t(total);
    total += k;
  }
  return total;
}

#if ITEAS_X86_FEATURES
// ring_offsets_narrow sixteen vertices at a time: the ringed vertices'
// valences summed across the register in four shifted adds (a prefix sum),
// the offsets stored whole. The vertices past the last full sixteen one at a time.
__attribute__((target("avx512f"))) int64_t ring_offsets_avx512(const VertexClass& vclass,
                                                                const int32_t* vertex_corner, int32_t limit,
                                                                int32_t* offset, bool& unringed) {
  int64_t total = 0;
  int32_t v = 0;
  const __m512i zero = _mm512_setzero_si512(), minus_one = _mm512_set1_epi32(-1);
  const __m512i three = _mm512_set1_epi32(3), six = _mm512_set1_epi32(6);
  __mmask16 missing = 0;
  for (; v + 16 <= limit; v += 16) {
    const __m512i k = _mm512_loadu_si512(vclass.valence.data() + v);
    const __m128i bytes = _mm_loadu_si128(reinterpret_cast<const __m128i*>(vclass.complete.data() + v));
    const __m512i complete = _mm512_maskz_cvtepu8_epi32(0xFFFF, bytes);
    const __m512i corner = _mm512_loadu_si512(vertex_corner + v);
    const __mmask16 ring = _mm512_test_epi32_mask(complete, complete) & _mm512_cmpneq_epi32_mask(k, six) &
                           _mm512_cmpge_epi32_mask(k, three);
    const __mmask16 no_corner = _mm512_cmplt_epi32_mask(corner, zero);
    missing |= ring & no_corner;
    const __mmask16 take = ring & ~no_corner;
    const __m512i x = _mm512_maskz_mov_epi32(take, k);
    __m512i sum = _mm512_add_epi32(x, _mm512_maskz_alignr_epi32(0xFFFF, x, zero, 15));  // lane i: x[i] + x[i - 1]
    sum = _mm512_add_epi32(sum, _mm512_maskz_alignr_epi32(0xFFFF, sum, zero, 14));
    sum = _mm512_add_epi32(sum, _mm512_maskz_alignr_epi32(0xFFFF, sum, zero, 12));
    sum = _mm512_add_epi32(sum, _mm512_maskz_alignr_epi32(0xFFFF, sum, zero, 8));  // inclusive prefix sums
    const __m512i before = _mm512_sub_epi32(sum, x);
    _mm512_storeu_si512(offset + v,
                        _mm512_mask_add_epi32(minus_one, take, _mm512_set1_epi32(int32_t(total)), before));
    total += _mm512_cvtsi512_si32(_mm512_maskz_permutexvar_epi32(1, _mm512_set1_epi32(15), sum));
  }
  if (missing) unringed = true;
  return ring_offsets_narrow(vclass, vertex_corner, v, limit, total, offset, unringed);
}
#endif

// ring_offsets_narrow for every vertex below |limit|, sixteen at a time where
// |wide| and the processor has AVX-512 (the same offsets).
int64_t ring_offsets(const VertexClass& vclass, const int32_t* vertex_corner, int32_t limit, int32_t* offset,
                     bool& unringed, bool wide) {
#if ITEAS_X86_FEATURES
  if (wide && cpu_has(CpuFeature::kAvx512)) return ring_offsets_avx512(vclass, vertex_corner, limit, offset, unringed);
#endif
  return ring_offsets_narrow(vclass, vertex_corner, 0, limit, 0, offset, unringed);
}
}  // namespace

namespace {
// What build_rings' copy reads and writes, as raw arrays.
struct RingCopy {
  const CornerTable& ct;
  CornerTable::Recorded fans;
  const int32_t* cv;
  const int32_t* valence;
  const int32_t* fan;
  const int32_t* vertex_corner;
  int32_t* offset;
  int32_t* corner;
  int32_t* neighbour;
  int32_t* slot;  // null: no slots
  // v's recorded fan and its ring in walk order, when it is the closed fan of
  // k faces the walk would take (the start of the run otherwise).
  ITEAS_INLINE int32_t recorded_ring(int32_t v, int32_t k) const {
    if (v >= fans.vertices || fan[v] != k || !fans.next) return -1;
    const int32_t o = fans.offset[v];
    return fans.corner[o] == vertex_corner[v] ? o : -1;
  }
};

// Vertex v's ring at |off| in the table, walked or read from a fan recorded
// without its neighbours. True when the slots may be incomplete (see
// build_rings).
bool copy_ring_slowly(const RingCopy& r, int32_t v, int32_t k, int32_t off) {
  const int32_t* order = r.ct.fan_order(v);
  if (order && r.fan[v] == k) {  // the closed fan of k faces the walk would take
    for (int32_t j = 0; j < k; ++j) {
      r.corner[off + j] = order[j];
      r.neighbour[off + j] = r.cv[next_corner(order[j])];
      if (r.slot) r.slot[prev_corner(order[j])] = off + j;
    }
    return r.ct.recorded_corners(v) != k;
  }
  int32_t x = r.ct.vertex_corner(v);
  for (int32_t j = 0; j < k; ++j) {
    if (x < 0) { r.offset[v] = -1; break; }  // defensive: not a closed fan of k faces
    r.corner[off + j] = x;
    r.neighbour[off + j] = r.cv[next_corner(x)];
    if (r.slot) r.slot[prev_corner(x)] = off + j;
    x = r.ct.swing_right(x);
  }
  return true;  // walked: its other corners unknown
}

#if ITEAS_X86_FEATURES
// A recorded ring of k <= 8 entries copied in masked AVX2 registers.
__attribute__((target("avx2"))) inline void copy_ring_avx2(const RingCopy& r, const int32_t* order,
                                                           const int32_t* next, int32_t k, int32_t off) {
  const __m256i mask = _mm256_cmpgt_epi32(_mm256_set1_epi32(k), _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7));
  _mm256_maskstore_epi32(r.corner + off, mask, _mm256_maskload_epi32(order, mask));
  _mm256_maskstore_epi32(r.neighbour + off, mask, _mm256_maskload_epi32(next, mask));
  if (r.slot)
    for (int32_t j = 0; j < k; ++j) r.slot[prev_corner(order[j])] = off + j;
}

// copy_ring_avx2 with the slots scattered under a mask (a loop of k stores
// mispredicted its exit, k varying from vertex to vertex).
__attribute__((target("avx512f,avx512vl,avx2"))) inline void copy_ring_avx512(const RingCopy& r, const int32_t* order,
                                                                             const int32_t* next, int32_t k,
                                                                             int32_t off) {
  const __mmask8 mask = __mmask8((1u << k) - 1);
  const __m256i corners = _mm256_maskz_loadu_epi32(mask, order);
  _mm256_mask_storeu_epi32(r.corner + off, mask, corners);
  _mm256_mask_storeu_epi32(r.neighbour + off, mask, _mm256_maskz_loadu_epi32(mask, next));
  if (!r.slot) return;
  __m256i next_corners, prev;  // the slots go at the corners before the ring's
  next_prev_corners_avx2(corners, next_corners, prev);
  const __m256i at = _mm256_add_epi32(_mm256_set1_epi32(off), _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7));
  _mm256_mask_i32scatter_epi32(r.slot, mask, prev, at, 4);
}
#endif

// The rings of vertices [b, e): true when the slots may be incomplete. A ring
// whose fan was recorded with its neighbours is copied from it (with
// kWidth 1 or 2, rings of up to 8 in masked AVX2 or AVX-512 registers).
template <int kWidth>
ITEAS_INLINE bool copy_ring_range(const RingCopy& r, int64_t b, int64_t e) {
  bool partial = false;
  for (int64_t v = b; v < e; ++v) {
    const int32_t off = r.offset[v];
    if (off < 0) continue;
    const int32_t k = r.valence[v];
    const int32_t o = r.recorded_ring(int32_t(v), k);
    if (o < 0) {
      partial |= copy_ring_slowly(r, int32_t(v), k, off);
      continue;
    }
    partial |= r.fans.offset[v + 1] - o != k;
    const int32_t* order = r.fans.corner + o;
    const int32_t* next = r.fans.next + o;
#if ITEAS_X86_FEATURES
    if constexpr (kWidth > 0) {
      if (k <= 8) {
        if constexpr (kWidth == 2) copy_ring_avx512(r, order, next, k, off);
        else copy_ring_avx2(r, order, next, k, off);
        continue;
      }
    }
#endif
    for (int32_t j = 0; j < k; ++j) {
      r.corner[off + j] = order[j];
      r.neighbour[off + j] = next[j];
      if (r.slot) r.slot[prev_corner(order[j])] = off + j;
    }
  }
  return partial;
}

#if ITEAS_X86_FEATURES
__attribute__((target("avx2"))) bool copy_ring_range_avx2(const RingCopy& r, int64_t b, int64_t e) {
  return copy_ring_range<1>(r, b, e);
}

__attribute__((target("avx512f,avx512vl,avx2"))) bool copy_ring_range_avx512(const RingCopy& r, int64_t b,
                                                                             int64_t e) {
  return copy_ring_range<2>(r, b, e);
}
#endif

bool copy_rings(const RingCopy& r, int64_t b, int64_t e, bool wide) {
#if ITEAS_X86_FEATURES
  if (wide && cpu_has(CpuFeature::kAvx512)) return copy_ring_range_avx512(r, b, e);
  if (wide && cpu_has(CpuFeature::kAvx2)) return copy_ring_range_avx2(r, b, e);
#else
  (void)wide;
#endif
  return copy_ring_range<0>(r, b, e);
}
}  // namespace

RingTable& RingTable::operator=(const RingTable& o) {
  if (this == &o) return *this;
  kept = o.kept;
  block = o.block;
  side = o.side;
  carried = o.carried;
  complete = o.complete;
  walked_green = o.walked_green;
  // Each part at the same place in its copied storage.
  auto rebase = [&](auto& part, const auto& from) {
    using T = std::remove_pointer_t<decltype(part.p_)>;
    part.n_ = from.n_;
    part.p_ = nullptr;
    if (!from.p_) return;
    const auto* f = reinterpret_cast<const int32_t*>(from.p_);
    for (auto [mine, theirs] : {std::pair<Array<int32_t>*, const Array<int32_t>*>{&kept, &o.kept},
                                {&block, &o.block},
                                {&side, &o.side}}) {
      if (theirs->empty() || f < theirs->data() || f >= theirs->data() + theirs->size()) continue;
      part.p_ = reinterpret_cast<T*>(mine->data() + (f - theirs->data()));
      return;
    }
  };
  rebase(offset, o.offset);
  rebase(corner, o.corner);
  rebase(neighbour, o.neighbour);
  rebase(point, o.point);
  rebase(slot, o.slot);
  return *this;
}

void RingTable::swap(RingTable& o) noexcept {
  // The storage's buffers move with it, and the parts with them.
  std::swap(offset, o.offset);
  std::swap(corner, o.corner);
  std::swap(neighbour, o.neighbour);
  std::swap(point, o.point);
  std::swap(slot, o.slot);
  std::swap(carried, o.carried);
  std::swap(complete, o.complete);
  std::swap(walked_green, o.walked_green);
  kept.swap(o.kept);
  block.swap(o.block);
  side.swap(o.side);
}

void RingTable::lay_out_kept(int32_t limit, int64_t corners) {
  const int64_t at = corners > 0 ? (int64_t(limit) + 15) & ~int64_t(15) : int64_t(limit);
  Array<int32_t>(size_t(at + corners)).swap(kept);
  offset.p_ = limit > 0 ? kept.data() : nullptr;
  offset.n_ = size_t(limit);
  corner = RingPart<int32_t>();
  if (corners > 0) {
    corner.p_ = kept.data() + at;
    corner.n_ = size_t(corners);
  }
}

void RingTable::lay_out_block(int64_t entries, int64_t slot_corners, int64_t at_least) {
  // Each part starts on a 64-byte line (16 int32s).
  auto round = [](int64_t n) { return (n + 15) & ~int64_t(15); };
  const int64_t size[4] = {carried ? 0 : entries + kRingPad, entries, slot_corners, 3 * entries};
  int64_t words = 0;
  for (int64_t n : size) words += round(n);
  // The smallest part whose room brings the block down to |at_least|.
  int aside = -1;
  if (at_least > 0 && words > at_least)
    for (int i = 0; i < 4; ++i)
      if (size[i] > 0 && round(size[i]) >= words - at_least && (aside < 0 || size[i] < size[aside])) aside = i;
  const bool fits = at_least > 0 && (words <= at_least || aside >= 0);
  Array<int32_t>().swap(block);
  Array<int32_t>(aside >= 0 ? size_t(size[aside]) : 0).swap(side);
  block.reserve(size_t(fits ? at_least : words));
  block.resize(size_t(aside >= 0 ? words - round(size[aside]) : words));
  int32_t* at = block.data();
  // (An empty part points nowhere: its data() is null, as an empty array's.)
  auto take = [&](int i, auto& part) {
    using T = std::remove_pointer_t<decltype(part.p_)>;
    part.n_ = size_t(size[i]);
    part.p_ = nullptr;
    if (size[i] == 0) return;
    if (i == aside) {
      part.p_ = reinterpret_cast<T*>(side.data());
      return;
    }
    part.p_ = reinterpret_cast<T*>(at);
    at += round(size[i]);
  };
  if (!carried) {
    take(0, corner);
    std::fill(corner.begin(), corner.end(), -1);  // the padding matches no corner
  }
  take(1, neighbour);
  take(2, slot);
  std::fill(slot.begin(), slot.end(), -1);
  // The points' floats live in int32 storage. They are written by
  // ring_points and read by the stencils, each in a loop of its own (a call
  // the compiler does not see through), and the children's corners written
  // over them later in another: no access of one type can be moved past
  // one of the other.
  take(3, point);
}

Array<int32_t> RingTable::release_block() {
  Array<int32_t> out;
  out.swap(block);
  RingTable().swap(*this);
  return out;
}

void build_rings(const Mesh& mesh, const CornerTable& ct, const VertexClass& vclass, int32_t limit, RingTable& out,
                 int threads, bool wide, bool slots, int64_t at_least) {
  const int32_t* cv = mesh.corner_vertex.data();
  const int64_t corners = int64_t(mesh.corner_vertex.size());
  // Slots where wanted, the rings complete and dense.
  auto slot_corners = [&](int64_t entries) {
    return slots && out.complete && RingTable::dense(entries, corners) ? corners : 0;
  };
  if (out.carried) {
    const int64_t entries = int64_t(out.corner.size()) - kRingPad;
    out.lay_out_block(entries, slot_corners(entries), at_least);
    out.carried = false;
    int32_t* const slot = out.slot.data();  // null: no slots
    parallel_for(int64_t(out.neighbour.size()), threads, [&](int64_t b, int64_t e) {
      for (int64_t i = b; i < e; ++i) {
        const int32_t x = out.corner[i];
        out.neighbour[i] = x >= 0 ? cv[next_corner(x)] : -1;
        if (slot && x >= 0) slot[prev_corner(x)] = int32_t(i);
      }
    });
    ring_points(mesh, vclass, out, threads, wide);
    return;
  }
  out.walked_green = false;
  limit = std::max(std::min(limit, mesh.num_vertices()), 0);
  out.lay_out_kept(limit, 0);
  // A complete extraordinary vertex without a ring: at or above the limit
  // (uniform levels make none), or below it without a fan.
  bool unringed = false;
  for (size_t v = size_t(limit); v < vclass.complete.size(); ++v)
    unringed |= vclass.complete[v] == VertexClass::kComplete;
  const int64_t total = ring_offsets(vclass, ct.vertex_corners().data(), limit, out.offset.data(), unringed, wide);
  // Slots where the rings are dense: written with the rings, each corner at
  // most once (a corner is at one vertex). They need every corner of a
  // ringed vertex in its ring (else an edge at a corner outside it would
  // read as having no extraordinary end there): known where the table
  // recorded the vertex's fan and its corners, and the fan holds them all.
  out.complete = !unringed;
  out.lay_out_block(total, slot_corners(total), at_least);
  int32_t* const slot = out.slot.data();  // null: no slots
  // A ring walked rather than read from a recorded fan, or a recorded fan
  // without all its vertex's corners (a walked ring may also be dropped,
  // its corners' slots written already): then no slots.
  std::atomic<bool> partial{false};
  const RingCopy copy{ct,
                      ct.recorded(),
                      cv,
                      vclass.valence.data(),
                      ct.fans().data(),
                      ct.vertex_corners().data(),
                      out.offset.data(),
                      out.corner.data(),
                      out.neighbour.data(),
                      slot};
  parallel_for(limit, threads, [&](int64_t b, int64_t e) {
    if (copy_rings(copy, b, e, wide)) partial.store(true, std::memory_order_relaxed);
  }, 512);
  if (partial.load()) {
    out.complete = false;
    out.drop_slots();
  }
  ring_points(mesh, vclass, out, threads, wide);
}

void build_level_rings(const Mesh& mesh, const CornerTable& ct, const VertexClass& vclass,
                       const std::vector<uint8_t>* green, RingTable& out, int threads, bool wide) {
  const int32_t nv = mesh.num_vertices();
  out.carried = false;
  out.lay_out_kept(nv, 0);
  bool unringed = false;
  const int64_t total = ring_offsets(vclass, ct.vertex_corners().data(), nv, out.offset.data(), unringed, wide);
  out.complete = false;  // (slots are never made here)
  out.walked_green = true;
  out.lay_out_block(total, 0, 0);
  const int32_t* cv = mesh.corner_vertex.data();
  const uint8_t* g = green && !green->empty() ? green->data() : nullptr;
  // The extraordinary rule's walk (extraordinary_terms): from a corner at v,
  // K steps right round v, each first passing over green apices.
  auto skip = [&](int32_t x) { return g ? past_green_apices(ct, g, x) : x; };
  parallel_for(nv, threads, [&](int64_t b, int64_t e) {
    for (int64_t v = b; v < e; ++v) {
      const int32_t off = out.offset[v];
      if (off < 0) continue;
      const int32_t K = vclass.valence[v];
      const int32_t first = skip(ct.vertex_corner(int32_t(v)));
      int32_t x = first;
      for (int32_t j = 0; j < K && x >= 0; ++j) {
        out.corner[off + j] = x;
        out.neighbour[off + j] = cv[next_corner(x)];
        x = skip(ct.swing_right(x));
      }
      // Only a fan the walk closes in K steps: the walk from any of its
      // corners then takes the same K in the same cyclic order.
      if (x != first || first < 0) out.offset[v] = -1;
    }
  }, 512);
  ring_points(mesh, vclass, out, threads, wide);
}

void carry_rings(RingTable& rings, int threads) {
  // Vertex v's corner k of face f becomes corner k of child k; round v the
  // children follow one another as their parents did. On the threads that
  // built the rings, each mostly over the entries it wrote (bunny-npm level
  // 1 on one thread: 5.7 µs; serial after two threads built the rings, 17.5
  // µs, half the lines coming from the other core, and the idle worker then
  // fell asleep before the children's loop). The offsets and the moved
  // corners go to a new |kept| of their own size; the block goes (its
  // neighbours, slots and points are the next level's to make).
  const int64_t n = int64_t(rings.corner.size()) - kRingPad;
  RingTable next;
  next.lay_out_kept(int32_t(rings.offset.size()), n + kRingPad);
  std::copy(rings.offset.begin(), rings.offset.end(), next.offset.begin());
  const int32_t* from = rings.corner.data();
  int32_t* to = next.corner.data();
  parallel_for(n, threads, [from, to](int64_t b, int64_t e) {
    for (int64_t i = b; i < e; ++i) {
      const int32_t x = from[i];
      to[i] = x >= 0 ? kept_child_corner(x) : x;
    }
  });
  std::fill(to + n, to + n + kRingPad, -1);
  next.carried = true;
  next.complete = rings.complete;
  rings.swap(next);
}

void discount_green_apices(const Mesh& mesh, const std::vector<uint8_t>& green, VertexClass& vclass) {
  for (size_t f = 0; f < green.size(); ++f) {
    if (green[f] != 2) continue;
    const int32_t v = mesh.corner_vertex[3 * f + 2];
    --vclass.valence[v];
    vclass.complete[v] = VertexClass::flags(vclass.complete[v] != 0, vclass.valence[v]);
  }
}

namespace {

// What the rules read, as raw arrays. kGreens is false when the level has no
// green pairs (every uniform level): all of the green handling then compiles
// away and a stencil is a handful of loads.
template <bool kGreens_>
struct View {
  static constexpr bool kGreens = kGreens_;
  const CornerTable* ct;  // fan walks
  const int32_t* cv;
  const int32_t* opp;
  const uint8_t* sharp;
  const uint8_t* green;
  const int32_t* valence;
  const uint8_t* complete;
  double tension;
  int32_t ring_limit;  // 0 without a ring table (and with green pairs, unless it was walked past them)
  const int32_t* ring_offset;
  const int32_t* ring_corner;
  const int32_t* ring_neighbour;
  const float* ring_point;
  const int32_t* ring_slot;  // null without slots
  explicit View(const ButterflyContext& ctx)
      : ct(ctx.ct),
        cv(ctx.mesh->corner_vertex.data()),
        opp(ctx.ct->opposites().data()),
        sharp(ctx.sharp && !ctx.sharp->empty() ? ctx.sharp->data() : nullptr),
        green(ctx.green && !ctx.green->empty() ? ctx.green->data() : nullptr),
        valence(ctx.vclass.valence.data()),
        complete(ctx.vclass.complete.data()),
        tension(ctx.tension),
        ring_limit(ctx.rings && (!kGreens || ctx.rings->walked_green) ? int32_t(ctx.rings->offset.size()) : 0),
        ring_offset(ring_limit ? ctx.rings->offset.data() : nullptr),
        ring_corner(ring_limit ? ctx.rings->corner.data() : nullptr),
        ring_neighbour(ring_limit ? ctx.rings->neighbour.data() : nullptr),
        ring_point(ring_limit ? ctx.rings->point.data() : nullptr),
        ring_slot(ring_limit ? ctx.rings->slot.data() : nullptr) {}
  uint8_t green_of(int32_t corner) const { return kGreens ? green[corner / 3] : 0; }
  // No sharp flags (an empty array) means: sharp = boundary.
  bool is_sharp(int32_t x) const { return sharp ? sharp[x] != 0 : opp[x] < 0; }
  // The vertex at corner x as the parent of a green pair sees it: the midpoint
  // corner of each child stands for the parent's opposite vertex.
  int32_t vtx(int32_t x) const {
    if (kGreens) {
      const uint8_t g = green_of(x);
      if (g == 1 && x % 3 == 1) return cv[x + 3];  // b of the second child
      if (g == 2 && x % 3 == 0) return cv[x - 3];  // a of the first child
    }
    return cv[x];
  }
  // Is the edge opposite corner x one of the parent's own edges, (c, a) or (b, c)?
  bool parent_edge(int32_t x) const {
    if (!kGreens) return false;
    const uint8_t g = green_of(x);
    return (g == 1 && x % 3 == 1) || (g == 2 && x % 3 == 0);
  }
};

// Rules emit (vertex, weight) terms into a sink in a fixed order: a sink that
// collects them (butterfly_stencil) or one that sums positions directly
// (butterfly_point, for every case but the regular one).
struct TermList {
  std::vector<StencilTerm>& terms;
  void operator()(int32_t v, double w) { terms.push_back({v, w}); }
};
struct PointSum {
  const float* positions;
  double p[3] = {0, 0, 0};
  ITEAS_INLINE void operator()(int32_t v, double w) {
    const float* x = positions + 3 * size_t(v);
    for (int k = 0; k < 3; ++k) p[k] += w * x[k];
  }
};

// s_j for valence K (Zorin et al. 1996): K = 3 and 4 special, K >= 5 by formula.
// Tabulated once for K < 64; larger valences compute on the fly.
constexpr int kMaxTabulated = 64;
double formula_weight(int K, int j) { return (0.25 + std::cos(2.0 * M_PI * j / K) + 0.5 * std::cos(4.0 * M_PI * j / K)) / K; }
struct WeightTable {
  double w[kMaxTabulated][kMaxTabulated];
  WeightTable() {
    for (int K = 3; K < kMaxTabulated; ++K)
      for (int j = 0; j < K; ++j) {
        if (K == 3) w[K][j] = j == 0 ? 5.0 / 12.0 : -1.0 / 12.0;
        else if (K == 4) w[K][j] = j == 0 ? 3.0 / 8.0 : (j == 2 ? -1.0 / 8.0 : 0.0);
        else w[K][j] = formula_weight(K, j);
      }
  }
};
const WeightTable kWeights;  // immutable after static initialisation

#if ITEAS_X86_FEATURES
// Sums with AVX where the processor has it (regular stencils and ring
// points; the same bits as SSE2).
#define ITEAS_AVX_SUM 1
#endif

#if defined(__SSE2__)
// A point's x and y (two floats, any alignment) as a pair of doubles, and a
// pair rounded back to two floats. Lanes round as scalars do, so packed sums
// keep the bits of the same sums done one coordinate at a time.
ITEAS_INLINE __m128d load_xy(const float* p) {
  return _mm_cvtps_pd(_mm_castsi128_ps(_mm_loadl_epi64(reinterpret_cast<const __m128i*>(p))));
}
ITEAS_INLINE void store_xy(float* p, __m128d xy) {
  _mm_storel_epi64(reinterpret_cast<__m128i*>(p), _mm_castps_si128(_mm_cvtpd_ps(xy)));
}

// The extraordinary rule of each stored ring's vertex for each of its edges,
// summed as PointSum sums it (3/4 v first, then the ring in order, zero
// weights skipped), so a rule read from here has the walk's bits. The K points
// of a ring are summed side by side, weight after weight (each point still
// adds its terms in the walk's order, so the bits are the same): the sums no
// longer wait on one another, and each neighbour is converted once, not K times.
// Valences 3-10 (all but a few stored rings; valence 6 is never stored) have
// a function each, every loop's count known to the compiler: unrolled, no loop
// exit to predict (valences vary from vertex to vertex; the loops of one form
// for all mispredicted their exits). The sums are packed: x and y of a point
// as a pair, the z of two neighbouring points as a pair (the last pair of an
// odd valence carries one more sum, never stored). Without SSE2 every valence
// takes ring_points_any, whose sums are the same.
template <int K>
ITEAS_INLINE void ring_points_of(const float* pos, const float* x, const int32_t* nb, float* out) {
  const double* w = kWeights.w[K];
  __m128d xy[2 * K];  // the ring twice over: point i's j-th term is ring[i + j]
  alignas(16) double z[2 * K];
  for (int j = 0; j < K; ++j) {
    const float* p = pos + 3 * size_t(nb[j]);
    xy[j] = xy[j + K] = load_xy(p);
    z[j] = z[j + K] = double(p[2]);
  }
  constexpr int kPairs = (K + 1) / 2;
  __m128d sxy[K], sz[kPairs];
  const __m128d cxy = _mm_add_pd(_mm_setzero_pd(), _mm_mul_pd(_mm_set1_pd(0.75), load_xy(x)));
  const __m128d cz = _mm_set1_pd(0.0 + 0.75 * double(x[2]));
  for (int i = 0; i < K; ++i) sxy[i] = cxy;
  for (int i = 0; i < kPairs; ++i) sz[i] = cz;
  for (int j = 0; j < K; ++j) {
    const double s = w[j];
    if (s == 0.0) continue;  // valence 4's odd weights: a fixed outcome per j, predicted
    const __m128d sv = _mm_set1_pd(s);
    for (int i = 0; i < K; ++i) sxy[i] = _mm_add_pd(sxy[i], _mm_mul_pd(sv, xy[i + j]));
    for (int i = 0; i < kPairs; ++i) sz[i] = _mm_add_pd(sz[i], _mm_mul_pd(sv, _mm_loadu_pd(z + 2 * i + j)));
  }
  for (int i = 0; i < K; ++i) {
    store_xy(out + 3 * i, sxy[i]);
    const __m128d zz = i % 2 ? _mm_unpackhi_pd(sz[i / 2], sz[i / 2]) : sz[i / 2];
    out[3 * i + 2] = _mm_cvtss_f32(_mm_cvtsd_ss(_mm_setzero_ps(), zz));
  }
}
#endif

// Any valence: the ring's points one after another.
void ring_points_any(const float* pos, const float* x, int K, const int32_t* nb, float* out) {
  const double* w = K < kMaxTabulated ? kWeights.w[K] : nullptr;
  for (int i = 0; i < K; ++i) {
    double p[3] = {0, 0, 0};
    for (int k = 0; k < 3; ++k) p[k] += 0.75 * double(x[k]);
    for (int j = 0, r = i; j < K; ++j, r = r + 1 == K ? 0 : r + 1) {
      const double s = w ? w[j] : formula_weight(K, j);
      if (s == 0.0) continue;
      const float* y = pos + 3 * size_t(nb[r]);
      for (int k = 0; k < 3; ++k) p[k] += s * double(y[k]);
    }
    for (int k = 0; k < 3; ++k) out[3 * i + k] = float(p[k]);
  }
}

// The arrays ring_points reads and writes, as locals of its loop (the
// packed stores may alias anything that lives in memory).
struct RingArrays {
  const int32_t* offset;
  const int32_t* valence;
  const int32_t* neighbour;
  const float* pos;
  float* point;
};

// Calls kernel(std::integral_constant<int, K>()) for the valences that have
// a summing function of their own (false for the others).
template <typename F>
ITEAS_INLINE bool with_ring_kernel(int K, F&& kernel) {
  switch (K) {
    case 3: kernel(std::integral_constant<int, 3>()); return true;
    case 4: kernel(std::integral_constant<int, 4>()); return true;
    case 5: kernel(std::integral_constant<int, 5>()); return true;
    case 7: kernel(std::integral_constant<int, 7>()); return true;
    case 8: kernel(std::integral_constant<int, 8>()); return true;
    case 9: kernel(std::integral_constant<int, 9>()); return true;
    case 10: kernel(std::integral_constant<int, 10>()); return true;
    default: return false;
  }
}

// The rule points of the ringed vertices in [b, e): |sums|(pos, x, nb, out,
// valence constant) where it has a function for the valence, else
// ring_points_any.
template <typename Sums>
ITEAS_INLINE void ring_points_range(const RingArrays& r, int64_t b, int64_t e, Sums sums) {
  for (int64_t v = b; v < e; ++v) {
    const int32_t off = r.offset[v];
    if (off < 0) continue;
    const int K = r.valence[v];
    const int32_t* nb = r.neighbour + off;
    const float* x = r.pos + 3 * size_t(v);
    float* out = r.point + 3 * size_t(off);
    if (!with_ring_kernel(K, [&](auto k) { sums(r.pos, x, nb, out, k); })) ring_points_any(r.pos, x, K, nb, out);
  }
}

void ring_points_range_sse(const RingArrays r, int64_t b, int64_t e) {
#if defined(__SSE2__)
  ring_points_range(r, b, e, [](const float* pos, const float* x, const int32_t* nb, float* out, auto k) {
    ring_points_of<decltype(k)::value>(pos, x, nb, out);
  });
#else
  ring_points_range(r, b, e, [](const float* pos, const float* x, const int32_t* nb, float* out, auto k) {
    ring_points_any(pos, x, decltype(k)::value, nb, out);
  });
#endif
}

#if ITEAS_AVX_SUM
// ring_points_of with a point's x, y and z in one register of four doubles:
// the same operations in the same order on each coordinate, so the same bits.
template <int K>
__attribute__((target("avx"))) inline void ring_points_avx(const float* pos, const float* x, const int32_t* nb,
                                                           float* out) {
  const double* w = kWeights.w[K];
  const __m128i three = _mm_set_epi32(0, -1, -1, -1);  // x, y, z; the fourth float is not read
  __m256d p[2 * K];  // the ring twice over: point i's j-th term is ring[i + j]
  for (int j = 0; j < K; ++j) p[j] = p[j + K] = _mm256_cvtps_pd(_mm_maskload_ps(pos + 3 * size_t(nb[j]), three));
  const __m256d c =
      _mm256_add_pd(_mm256_setzero_pd(),
                    _mm256_mul_pd(_mm256_set1_pd(0.75), _mm256_cvtps_pd(_mm_maskload_ps(x, three))));
  __m256d sum[K];
  for (int i = 0; i < K; ++i) sum[i] = c;
  for (int j = 0; j < K; ++j) {
    const double s = w[j];
    if (s == 0.0) continue;
    const __m256d sv = _mm256_set1_pd(s);
    for (int i = 0; i < K; ++i) sum[i] = _mm256_add_pd(sum[i], _mm256_mul_pd(sv, p[i + j]));
  }
  for (int i = 0; i < K; ++i) {
    const __m128 f = _mm256_cvtpd_ps(sum[i]);
    _mm_storel_epi64(reinterpret_cast<__m128i*>(out + 3 * i), _mm_castps_si128(f));
    _mm_store_ss(out + 3 * i + 2, _mm_movehl_ps(f, f));
  }
}

__attribute__((target("avx"))) void ring_points_range_avx(const RingArrays r, int64_t b, int64_t e) {
  ring_points_range(r, b, e,
                    [](const float* pos, const float* x, const int32_t* nb, float* out, auto k)
                        __attribute__((target("avx"))) { ring_points_avx<decltype(k)::value>(pos, x, nb, out); });
}
#endif

void ring_points(const Mesh& mesh, const VertexClass& vclass, RingTable& rings, int threads, bool wide) {
  const RingArrays r{rings.offset.data(), vclass.valence.data(), rings.neighbour.data(), mesh.positions.data(),
                     rings.point.data()};
#if ITEAS_AVX_SUM
  wide = wide && cpu_has(CpuFeature::kAvx);
#else
  wide = false;
#endif
  parallel_for(int64_t(rings.offset.size()), threads, [&](int64_t b, int64_t e) {
#if ITEAS_AVX_SUM
    if (wide) {
      ring_points_range_avx(r, b, e);
      return;
    }
#endif
    ring_points_range_sse(r, b, e);
  }, 256);
}

// Where corner x0 sits in a stored ring of K corners (K if absent). Rings
// are padded with kRingPad entries that match no corner, so up to 8 are
// compared at once.
ITEAS_INLINE int ring_position(const int32_t* rc, int K, int32_t x0) {
  if (K <= 8) {
    const unsigned mask = equal_mask8(rc, x0, K);
    return mask ? __builtin_ctz(mask) : K;
  }
  int i = 0;
  while (i < K && rc[i] != x0) ++i;
  return i;
}

// Extraordinary rule at vertex v (corner x0 at v, whose next vertex is the
// other endpoint of the edge): 3/4 v + sum_j s_j e_j over the ring in order.
template <bool G, typename Sink>
void extraordinary_terms(const View<G>& m, int32_t x0, int32_t valence, double scale, Sink& out) {
  const int K = valence;
  const int32_t v = m.cv[x0];
  out(v, 0.75 * scale);
  const double* w = K >= 3 && K < kMaxTabulated ? kWeights.w[K] : nullptr;
  if (v < m.ring_limit && m.ring_offset[v] >= 0) {
    // The ring from x0 on is the stored ring rotated to x0's place.
    const int32_t* rc = m.ring_corner + m.ring_offset[v];
    const int32_t* nb = m.ring_neighbour + m.ring_offset[v];
    const int i0 = ring_position(rc, K, x0);
    if (i0 < K) {
      for (int j = 0, i = i0; j < K; ++j, i = i + 1 == K ? 0 : i + 1) {
        const double s = w ? w[j] : formula_weight(K, j);
        if (s != 0.0) out(nb[i], s * scale);
      }
      return;
    }
  }
  int32_t x = x0;
  for (int j = 0; j < K; ++j) {
    // The bisecting edge (c, m) of a green pair with this vertex as apex is
    // not in the parent's ring: skip it (classify discounted it from K).
    if (G) x = past_green_apices(*m.ct, m.green, x);
    const double s = w ? w[j] : formula_weight(K, j);
    if (s != 0.0) out(m.cv[next_corner(x)], s * scale);
    x = m.ct->swing_right(x);
  }
}

// x rounded to float. The empty asm makes the compiler keep the rounding: at
// -O3, GCC 12's SLP vectoriser dropped a plain double(float(x)) round trip
// here (the walk then disagreed with the ring table's stored floats).
ITEAS_INLINE float to_float(double x) {
  float f = float(x);
#if defined(__GNUC__) && (defined(__x86_64__) || defined(__i386__))
  asm("" : "+x"(f));
#elif defined(__GNUC__)
  asm("" : "+m"(f));
#endif
  return f;
}

// A point sums each rule on its own, rounds it to float (as the point itself
// would be: an edge with one irregular end gets the same bits as a single
// sum) and adds it scaled (1, or 1/2 for each of two irregular ends): the
// rule is then one value per vertex and edge, precomputed with the ring table
// (ring_points, 12 bytes an entry) and read here.
template <bool G, typename Sink>
ITEAS_INLINE void extraordinary(const View<G>& m, int32_t x0, int32_t valence, double scale, Sink& out) {
  if constexpr (std::is_same_v<Sink, PointSum>) {
    const int32_t v = m.cv[x0];
    if (v < m.ring_limit && m.ring_offset[v] >= 0) {
      const int32_t off = m.ring_offset[v];
      const int i = ring_position(m.ring_corner + off, valence, x0);
      if (i < valence) {
        const float* r = m.ring_point + 3 * (size_t(off) + size_t(i));
        for (int k = 0; k < 3; ++k) out.p[k] += scale * double(r[k]);
        return;
      }
    }
    PointSum rule{out.positions};
    extraordinary_terms(m, x0, valence, 1.0, rule);
    for (int k = 0; k < 3; ++k) out.p[k] += scale * double(to_float(rule.p[k]));
  } else {
    extraordinary_terms(m, x0, valence, scale, out);
  }
}

// The point on the far side of the edge opposite corner |x| (across a sharp
// edge it is replaced by the parallelogram completion of x's own triangle).
template <bool G, typename Sink>
ITEAS_INLINE void plain_wing(const View<G>& m, int32_t x, double w, Sink& out) {
  const int32_t o = m.opp[x];
  if (o >= 0 && !m.is_sharp(x)) {
    out(m.vtx(o), w);
  } else {
    out(m.vtx(next_corner(x)), w);
    out(m.vtx(prev_corner(x)), w);
    out(m.vtx(x), -w);
  }
}

// A wing of an edge whose face is |x|'s face. When that edge is a parent edge
// of a green pair (|parent_view|), the wings are the parent's: across its
// other parent edge (reached through the sibling), and across (a, b), where
// the neighbour is already split, by parallelogram completion a + b - c.
template <bool G, typename Sink>
ITEAS_INLINE void wing(const View<G>& m, int32_t x, bool parent_view, double w, Sink& out) {
  if (G && parent_view) {
    const uint8_t g = m.green_of(x);
    if (g != 0) {
      const int32_t k = x % 3, f0 = (g == 1 ? x / 3 : x / 3 - 1) * 3;  // first corner of the first child
      const int32_t a = m.cv[f0], b = m.cv[f0 + 4], c = m.cv[f0 + 2];
      if (k == 2) {  // across (a, m) or (m, b): across (a, b)
        out(a, w); out(b, w); out(c, -w);
        return;
      }
      if (g == 1 && k == 0) { plain_wing(m, f0 + 3, w, out); return; }  // across (b, c)
      if (g == 2 && k == 1) { plain_wing(m, f0 + 1, w, out); return; }  // across (c, a)
    }
  }
  plain_wing(m, x, w, out);
}

// Along a boundary or crease curve: the curve neighbour of v other than
// |other|, or -1 when v has other than two sharp edges.
template <bool G>
int32_t curve_neighbour(const View<G>& m, int32_t v, int32_t other) {
  const int32_t first = m.ct->vertex_corner(v);
  int32_t found = -1, count = 0, c = first, guard = 0;
  while (c >= 0) {
    if (m.is_sharp(prev_corner(c))) {  // outgoing edge v -> next(c)
      ++count;
      if (m.cv[next_corner(c)] != other) found = m.cv[next_corner(c)];
    }
    const int32_t s = m.ct->swing_right(c);
    if (s < 0) {  // open fan: its last incoming edge prev(c) -> v is a boundary
      ++count;
      if (m.cv[prev_corner(c)] != other) found = m.cv[prev_corner(c)];
      break;
    }
    if (s == first || ++guard > m.ct->num_corners()) break;
    c = s;
  }
  return count == 2 ? found : -1;
}

template <bool G, typename Sink>
void four_point(const View<G>& m, int32_t v1, int32_t v2, Sink& out) {
  out(v1, 9.0 / 16.0);
  out(v2, 9.0 / 16.0);
  const int32_t p = curve_neighbour(m, v1, v2);
  if (p >= 0) out(p, -1.0 / 16.0);
  else { out(v1, -2.0 / 16.0); out(v2, 1.0 / 16.0); }
  const int32_t q = curve_neighbour(m, v2, v1);
  if (q >= 0) out(q, -1.0 / 16.0);
  else { out(v2, -2.0 / 16.0); out(v1, 1.0 / 16.0); }
}

template <bool G, typename Sink>
ITEAS_INLINE void rules(const View<G>& m, int32_t c, Sink& out) {
  const int32_t v1 = m.cv[next_corner(c)], v2 = m.cv[prev_corner(c)];
  const int32_t d = m.opp[c];
  if (d < 0 || m.is_sharp(c)) {
    four_point(m, v1, v2, out);
    return;
  }
  const bool c1 = m.complete[v1], c2 = m.complete[v2];
  const bool pf = m.parent_edge(c), pg = m.parent_edge(d);
  const int32_t k1 = m.valence[v1], k2 = m.valence[v2];
  // Corner at v1 whose next vertex is v2 is next(c); at v2 whose next is v1: next(d).
  if (c1 && c2) {
    if (k1 == 6 && k2 == 6) {
      const double w = m.tension;
      out(v1, 0.5 - w);
      out(v2, 0.5 - w);
      out(m.vtx(c), 0.125 + 2 * w);
      out(m.vtx(d), 0.125 + 2 * w);
      wing(m, prev_corner(c), pf, -1.0 / 16.0 - w, out);  // across (a1, v1)
      wing(m, next_corner(c), pf, -1.0 / 16.0 - w, out);  // across (v2, a1)
      wing(m, prev_corner(d), pg, -1.0 / 16.0 - w, out);
      wing(m, next_corner(d), pg, -1.0 / 16.0 - w, out);
      if (w > 0) {
        // 10-point: the ring neighbours of v1 and v2 straight across from the
        // edge (three steps round a valence-6 ring).
        int32_t x = next_corner(c), y = next_corner(d);
        for (int j = 0; j < 3; ++j) { x = m.ct->swing_right(x); y = m.ct->swing_right(y); }
        out(m.cv[next_corner(x)], w);
        out(m.cv[next_corner(y)], w);
      }
      return;
    }
    if (k1 != 6 && k2 != 6) {
      extraordinary(m, next_corner(c), k1, 0.5, out);
      extraordinary(m, next_corner(d), k2, 0.5, out);
    } else if (k1 != 6) {
      extraordinary(m, next_corner(c), k1, 1.0, out);
    } else {
      extraordinary(m, next_corner(d), k2, 1.0, out);
    }
    return;
  }
  if (c1) { extraordinary(m, next_corner(c), k1, 1.0, out); return; }
  if (c2) { extraordinary(m, next_corner(d), k2, 1.0, out); return; }
  out(v1, 0.5);
  out(v2, 0.5);
  out(m.vtx(c), 0.125);
  out(m.vtx(d), 0.125);
  wing(m, prev_corner(c), pf, -1.0 / 16.0, out);
  wing(m, next_corner(c), pf, -1.0 / 16.0, out);
  wing(m, prev_corner(d), pg, -1.0 / 16.0, out);
  wing(m, next_corner(d), pg, -1.0 / 16.0, out);
}

// The regular stencil's sum over its eight points q: v1, v2, the two
// opposite vertices a and b, the four wings w1..w4.
// 1/2 (v1 + v2) + 1/8 (a + b) - 1/16 (w1 + w2 + w3 + w4), in double.
ITEAS_INLINE void regular_sum(const float* positions, const int32_t* q, float* out) {
#if defined(__SSE2__)
  // x and y as a pair of doubles, z alone: the same sums in the same order.
  struct P { __m128d xy, z; };
  auto load = [positions](int32_t v) {
    const float* p = positions + 3 * size_t(v);
    return P{load_xy(p), _mm_cvtss_sd(_mm_setzero_pd(), _mm_load_ss(p + 2))};
  };
  auto add = [](P a, P b) { return P{_mm_add_pd(a.xy, b.xy), _mm_add_sd(a.z, b.z)}; };
  auto mul = [](double s, P a) { return P{_mm_mul_pd(_mm_set1_pd(s), a.xy), _mm_mul_sd(_mm_set_sd(s), a.z)}; };
  const P e = add(load(q[0]), load(q[1])), f = add(load(q[2]), load(q[3]));
  const P g = add(add(add(load(q[4]), load(q[5])), load(q[6])), load(q[7]));
  const P r = add(add(mul(0.5, e), mul(0.125, f)), mul(-1.0 / 16.0, g));
  store_xy(out, r.xy);
  _mm_store_ss(out + 2, _mm_cvtsd_ss(_mm_setzero_ps(), r.z));
#else
  const float* p[8];
  for (int i = 0; i < 8; ++i) p[i] = positions + 3 * size_t(q[i]);
  for (int k = 0; k < 3; ++k) {
    const double e = double(p[0][k]) + double(p[1][k]), f = double(p[2][k]) + double(p[3][k]);
    const double g = ((double(p[4][k]) + double(p[5][k])) + double(p[6][k])) + double(p[7][k]);
    out[k] = float((0.5 * e + 0.125 * f) + (-1.0 / 16.0) * g);
  }
#endif
}

// The common case, spelled out: an interior edge between two complete
// valence-6 vertices, no tension, no wing across a sharp edge, no green pair
// involved. The eight points are summed by weight class (both paths that
// refine positions come through here, so every path gives the same bits).
// Returns false (nothing written) for anything else.
template <bool G>
ITEAS_INLINE bool regular_point(const View<G>& m, int32_t c, const float* positions, float* out) {
  if (m.tension != 0) return false;
  const int32_t d = m.opp[c];
  if (d < 0 || (m.sharp && m.sharp[c])) return false;
  if (G && (m.green_of(c) | m.green_of(d))) return false;
  const int32_t nc = next_corner(c), pc = prev_corner(c), nd = next_corner(d), pd = prev_corner(d);
  const int32_t v1 = m.cv[nc], v2 = m.cv[pc];
  if ((m.complete[v1] & m.complete[v2]) != VertexClass::kRegular) return false;
  const int32_t x[4] = {pc, nc, pd, nd};
  int32_t wv[4];
  for (int i = 0; i < 4; ++i) {
    const int32_t o = m.opp[x[i]];
    if (o < 0 || (m.sharp && m.sharp[x[i]])) return false;
    if (G && m.green_of(o)) return false;
    wv[i] = m.cv[o];
  }
  const int32_t q[8] = {v1, v2, m.cv[c], m.cv[d], wv[0], wv[1], wv[2], wv[3]};
  regular_sum(positions, q, out);
  return true;
}

// Calls f with the view that matches the level: with or without green pairs.
template <typename F>
void with_view(const ButterflyContext& ctx, F&& f) {
  if (ctx.green && !ctx.green->empty()) f(View<true>(ctx));
  else f(View<false>(ctx));
}

// regular_point's vertices where the level has no green pair, no crease
// flag and no tension (every uniform level without creases): the checks left
// are the fans' flags and, defensively, the boundary.
ITEAS_INLINE bool plain_regular_vertices(const int32_t* cv, const int32_t* opp, const uint8_t* complete, int32_t c,
                                         int32_t* q) {
  const int32_t nc = next_corner(c), pc = prev_corner(c);
  const int32_t v1 = cv[nc], v2 = cv[pc];
  if ((complete[v1] & complete[v2]) != VertexClass::kRegular) return false;
  const int32_t d = opp[c];
  if (d < 0) return false;
  const int32_t nd = next_corner(d), pd = prev_corner(d);
  const int32_t o0 = opp[pc], o1 = opp[nc], o2 = opp[pd], o3 = opp[nd];
  if ((o0 | o1 | o2 | o3) < 0) return false;
  q[0] = v1;
  q[1] = v2;
  q[2] = cv[c];
  q[3] = cv[d];
  q[4] = cv[o0];
  q[5] = cv[o1];
  q[6] = cv[o2];
  q[7] = cv[o3];
  return true;
}

struct SseSum {
  ITEAS_INLINE void operator()(const float* positions, const int32_t* q, float* out) const {
    regular_sum(positions, q, out);
  }
  // An edge with an extraordinary end, from the rings' points: entry a
  // alone, or the average of a and b (|both|), summed as rules() sums them
  // (0, then each rule scaled: 1, or 1/2 and 1/2).
  ITEAS_INLINE void ring(const float* point, int32_t a, int32_t b, bool both, float* out) const {
    const float *ra = point + 3 * size_t(a), *rb = point + 3 * size_t(b);
    for (int k = 0; k < 3; ++k) {
      double p = 0.0 + (both ? 0.5 : 1.0) * double(ra[k]);
      if (both) p += 0.5 * double(rb[k]);
      out[k] = float(p);
    }
  }
};

#if ITEAS_AVX_SUM
// regular_sum with x, y and z of a point in one register of four doubles:
// the same operations in the same order on each coordinate (no FMA: AVX
// alone has none), so the same bits, in half the instructions. A point is
// one masked load of its three floats (the fourth lane is not read, so the
// last point of an array is safe). Chosen at run time (plain_points_avx)
// where the processor has AVX.
struct AvxSum {
  __attribute__((target("avx"))) inline void operator()(const float* positions, const int32_t* q,
                                                        float* out) const {
    auto load = [positions](int32_t v) __attribute__((target("avx"))) {
      const float* p = positions + 3 * size_t(v);
      return _mm256_cvtps_pd(_mm_maskload_ps(p, _mm_set_epi32(0, -1, -1, -1)));
    };
    const __m256d e = _mm256_add_pd(load(q[0]), load(q[1]));
    const __m256d f = _mm256_add_pd(load(q[2]), load(q[3]));
    const __m256d g = _mm256_add_pd(_mm256_add_pd(_mm256_add_pd(load(q[4]), load(q[5])), load(q[6])), load(q[7]));
    const __m256d r = _mm256_add_pd(
        _mm256_add_pd(_mm256_mul_pd(_mm256_set1_pd(0.5), e), _mm256_mul_pd(_mm256_set1_pd(0.125), f)),
        _mm256_mul_pd(_mm256_set1_pd(-1.0 / 16.0), g));
    const __m128 rf = _mm256_cvtpd_ps(r);
    _mm_storel_epi64(reinterpret_cast<__m128i*>(out), _mm_castps_si128(rf));
    _mm_store_ss(out + 2, _mm_movehl_ps(rf, rf));
  }
  // SseSum::ring with x, y and z in one register and no branch (whether an
  // edge has one extraordinary end or two follows no pattern; GCC made a
  // blend of two sums into branches). One end: (0 + 1 a) + (+0), the same
  // as 0 + 1 a (which is never -0); two: (0 + a / 2) + b / 2.
  __attribute__((target("avx"))) inline void ring(const float* point, int32_t a, int32_t b, bool both,
                                                  float* out) const {
    const __m128i three = _mm_set_epi32(0, -1, -1, -1);
    const __m256d pa = _mm256_cvtps_pd(_mm_maskload_ps(point + 3 * size_t(a), three));
    const __m256d pb = _mm256_cvtps_pd(_mm_maskload_ps(point + 3 * size_t(b), three));
    const int64_t two = int64_t(both);
    const __m256d scale = _mm256_castsi256_pd(_mm256_set1_epi64x(0x3FF0000000000000LL - (two << 52)));  // 1 or 1/2
    const __m256d keep = _mm256_castsi256_pd(_mm256_set1_epi64x(-two));
    const __m256d first = _mm256_add_pd(_mm256_setzero_pd(), _mm256_mul_pd(scale, pa));
    const __m256d second = _mm256_and_pd(keep, _mm256_mul_pd(_mm256_set1_pd(0.5), pb));
    const __m128 rf = _mm256_cvtpd_ps(_mm256_add_pd(first, second));
    _mm_storel_epi64(reinterpret_cast<__m128i*>(out), _mm_castps_si128(rf));
    _mm_store_ss(out + 2, _mm_movehl_ps(rf, rf));
  }
};
#endif

// The point of the edge at corner c by the rules (any case but the
// regular stencil the loops below sum themselves), rounded to float.
template <bool G>
ITEAS_INLINE void rules_point(const View<G>& view, int32_t c, const float* positions, float* out) {
  PointSum sink{positions};
  rules(view, c, sink);
  for (int k = 0; k < 3; ++k) out[k] = float(sink.p[k]);
}

// The plain loop's points of an edge that takes no ring slot: the regular
// stencil, else the rules.
template <typename Sum>
ITEAS_INLINE void plain_point(const View<false>& view, int32_t c, const float* positions, float* out, Sum sum) {
  int32_t q[8];
  if (__builtin_expect(plain_regular_vertices(view.cv, view.opp, view.complete, c, q), 1)) {
    sum(positions, q, out);
    return;
  }
  rules_point(view, c, positions, out);
}

// The plain loop where the level has ring slots (every complete
// extraordinary vertex's ring stored): an interior edge with a slot at an
// end takes that end's rule (the other end is then regular or not
// complete), or both ends' average. Which edges do follows no pattern (at
// the first levels a third to nine tenths of them), so a block's edges are
// first sorted into the two kinds without a branch, then each kind runs as
// a loop of its own.
template <typename Sum>
ITEAS_INLINE void slotted_points(const View<false>& view, const int32_t* corners, int64_t count,
                                 const float* positions, float* out, Sum sum) {
  const int32_t* const opp = view.opp;
  const int32_t* const slot = view.ring_slot;
  const float* const ring_point = view.ring_point;
  constexpr int kBlock = 256;
  int32_t ring_at[kBlock], ring_a[kBlock], ring_b[kBlock], other_at[kBlock];
  for (int64_t b0 = 0; b0 < count; b0 += kBlock) {
    const int n = int(std::min<int64_t>(kBlock, count - b0));
    const int32_t* const block = corners + b0;
    float* const dst = out + 3 * b0;
    int nr = 0, no = 0;
    for (int j = 0; j < n; ++j) {
      const int32_t c = block[j], d = opp[c];
      const int32_t s1 = slot[c], s2 = slot[d < 0 ? c : d];
      // 1 when the edge is interior and one of its ends has a slot.
      const int32_t ring = int32_t(uint32_t(~(d | (s1 & s2))) >> 31);
      // a: s1 if it is a slot, else s2; b: s2 when both are slots, else -1.
      const int32_t both = ~((s1 | s2) >> 31);
      ring_at[nr] = j;
      ring_a[nr] = s2 ^ ((s1 ^ s2) & ~(s1 >> 31));
      ring_b[nr] = s2 | ~both;
      nr += ring;
      other_at[no] = j;
      no += 1 - ring;
    }
    for (int r = 0; r < nr; ++r) {
      const int32_t a = ring_a[r], b = ring_b[r];
      sum.ring(ring_point, a, b ^ ((b ^ a) & (b >> 31)), b >= 0, dst + 3 * ring_at[r]);
    }
    for (int o = 0; o < no; ++o) plain_point(view, block[other_at[o]], positions, dst + 3 * other_at[o], sum);
  }
}

// The points of a list of edges. Everything the loop reads is a local: the
// stores through |out| may alias anything in memory, and a view or captures
// read through a reference were reloaded after each of them. |sum| (kPlain
// only) sums a regular stencil's eight points.
template <bool G, bool kPlain, typename Sum = SseSum>
ITEAS_INLINE void points_of(const View<G>& view, const int32_t* corners, int64_t count, const float* positions,
                            float* out, Sum sum = Sum()) {
  if constexpr (kPlain) {
    if (view.ring_slot) {
      slotted_points(view, corners, count, positions, out, sum);
      return;
    }
  }
  const int32_t* const cv = view.cv;
  const int32_t* const opp = view.opp;
  const uint8_t* const complete = view.complete;
  // The faces across a few edges ahead are asked for early: an edge's
  // wings are read through its opposite (corner, opposite, its neighbours,
  // their vertices, one load waiting on the other), and on large levels
  // those faces are not in cache (level 4: about 6 % less time; 6 to 24
  // edges ahead measured alike; also asking for the positions was slower).
  constexpr int64_t kAhead = 12;
  for (int64_t i = 0; i < count; ++i) {
    if (i + kAhead < count) {
      const int32_t d = opp[corners[i + kAhead]];
      if (d >= 0) {
        __builtin_prefetch(opp + d);
        __builtin_prefetch(cv + d);
      }
    }
    const int32_t c = corners[i];
    if (kPlain) {
      int32_t q[8];
      if (__builtin_expect(plain_regular_vertices(cv, opp, complete, c, q), 1)) {
        sum(positions, q, out + 3 * i);
        continue;
      }
    } else if (regular_point(view, c, positions, out + 3 * i)) {
      continue;
    }
    rules_point(view, c, positions, out + 3 * i);
  }
}

void plain_points(const View<false>& view, const int32_t* corners, int64_t count, const float* positions,
                  float* out) {
  points_of<false, true>(view, corners, count, positions, out);
}

#if ITEAS_AVX_SUM
__attribute__((target("avx"))) void plain_points_avx(const View<false>& view, const int32_t* corners, int64_t count,
                                                     const float* positions, float* out) {
  points_of<false, true, AvxSum>(view, corners, count, positions, out);
}
#endif

}  // namespace

bool plain_stencils(const ButterflyContext& ctx) {
  return !(ctx.green && !ctx.green->empty()) && ctx.tension == 0 && !(ctx.sharp && !ctx.sharp->empty());
}

void butterfly_stencil(const ButterflyContext& ctx, int32_t c, std::vector<StencilTerm>& out) {
  out.clear();
  TermList sink{out};
  with_view(ctx, [&](const auto& view) { rules(view, c, sink); });
}

void butterfly_point(const ButterflyContext& ctx, int32_t c, const float* positions, float out[3]) {
  butterfly_points(ctx, &c, 1, positions, out);
}

void butterfly_points(const ButterflyContext& ctx, const int32_t* corners, int64_t count, const float* positions,
                      float* out) {
  if (plain_stencils(ctx)) {
    const View<false> view(ctx);
#if ITEAS_AVX_SUM
    if (ctx.wide && cpu_has(CpuFeature::kAvx)) {
      plain_points_avx(view, corners, count, positions, out);
      return;
    }
#endif
    plain_points(view, corners, count, positions, out);
    return;
  }
  with_view(ctx, [&](const auto& view) {
    points_of<std::decay_t<decltype(view)>::kGreens, false>(view, corners, count, positions, out);
  });
}

}  // namespace iteas
