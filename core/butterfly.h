// Modified Butterfly stencils (Zorin, Schröder, Sweldens 1996, "Interpolating
// subdivision for meshes with arbitrary topology"), SPEC §2.4. A stencil is a
// list of (vertex, weight) terms over the *old* level; the caller applies it
// to positions and to any per-vertex data (morph deltas), OpenSubdiv style.
#pragma once

#include <algorithm>
#include <cstdint>
#include <utility>
#include <vector>

#include "core/corner_table.h"
#include "core/mesh.h"

namespace iteas {

struct StencilTerm {
  int32_t vertex;
  double weight;
};

// Per-vertex facts the rules need, computed once per level.
struct VertexClass {
  std::vector<int32_t> valence;   // number of incident edges
  // Non-zero when the fan is closed and has no sharp (crease) edge: kRegular
  // when the valence is also 6, else kComplete (the regular stencil then
  // tests one byte per endpoint instead of reading two arrays).
  std::vector<uint8_t> complete;
  static constexpr uint8_t kComplete = 1, kRegular = 3;
  static uint8_t flags(bool complete, int32_t valence) {
    return complete ? (valence == 6 ? kRegular : kComplete) : 0;
  }
};

// The rings of extraordinary vertices (complete, valence other than 6) with an
// index below a limit: per fan step from the vertex's corner, the corner and
// the neighbour it leads to. Uniform levels make no new extraordinary
// vertices, so with the input's vertex count as the limit this covers them
// all; the extraordinary rule then reads its ring instead of walking the fan
// once per edge (same terms in the same order).
constexpr int kRingPad = 8;  // entries after the last ring, for a fixed-width search

// A stretch of a RingTable's storage, read and written like an array; an
// empty one's data() is null.
template <typename T>
class RingPart {
 public:
  T* data() const { return p_; }
  size_t size() const { return n_; }
  bool empty() const { return n_ == 0; }
  T& operator[](size_t i) const { return p_[i]; }
  T* begin() const { return p_; }
  T* end() const { return p_ + n_; }
  friend bool operator==(const RingPart& a, const RingPart& b) {
    return a.n_ == b.n_ && std::equal(a.p_, a.p_ + a.n_, b.p_);
  }

 private:
  friend struct RingTable;
  T* p_ = nullptr;
  size_t n_ = 0;
};

struct RingTable {
  RingPart<int32_t> offset;  // per vertex below the limit: start in corner/neighbour, -1 = none
  RingPart<int32_t> corner, neighbour;  // corner has kRingPad entries of -1 after the last ring
  // Set by carry_rings: offset and corner hold the rings of the next uniform
  // level (same vertices, same order); build_rings then only fills in the rest.
  bool carried = false;
  // Per ring entry, the extraordinary rule's point (3 floats) for the edge
  // from the vertex to that neighbour, from the positions build_rings saw.
  RingPart<float> point;  // no zero fill (every entry is written)
  // Every complete extraordinary vertex of the level has its ring (the
  // input's vertices all below the limit, none left without; carried with
  // the rings, as uniform levels make no such vertex).
  bool complete = false;
  // Built by build_level_rings for a level's green pairs (the rules of a
  // context with green pairs read only such a table).
  bool walked_green = false;
  // Per corner of the level, where the rings cover an eighth of the corners
  // or more (the first uniform levels of a typical mesh) and |complete|:
  // the ring entry whose point is the extraordinary rule, for the edge
  // opposite the corner, of that edge's first vertex (the vertex after the
  // corner, towards the vertex before it), -1 where that vertex has no ring.
  // The edge of corner c thus finds its two ends' entries at c and at its
  // opposite, without dividing by 3. Empty otherwise (the rules then look
  // the corner up in its ring).
  RingPart<int32_t> slot;
  static bool dense(int64_t entries, int64_t corners) { return 8 * entries >= corners; }

  // Storage: |kept| holds offset (and corner, once carried); |block| the
  // parts a level builds afresh, one after another: corner (unless
  // carried), neighbour, slot, point. One block, so that the caller can take
  // its memory for the level's next large array once the rings are done
  // (release_block): refinement writes the children's corners there, where
  // a new array came from fresh pages (level 1 of a 3,674-face mesh: 43 of
  // its 107 fresh pages, and the heap trimmed in between). |side| holds the
  // one part that would make the block larger than that array (its excess
  // would stay with the array after the rings are gone).
  Array<int32_t> kept, block, side;

  RingTable() = default;
  RingTable(const RingTable& o) { *this = o; }
  RingTable& operator=(const RingTable& o);
  RingTable(RingTable&& o) noexcept { swap(o); }
  RingTable& operator=(RingTable&& o) noexcept {
    RingTable(std::move(o)).swap(*this);
    return *this;
  }
  void swap(RingTable& o) noexcept;

  // A new |kept| for the offsets (per vertex below |limit|) and, when
  // |corners| > 0, that many ring corners after them; neither written.
  void lay_out_kept(int32_t limit, int64_t corners);
  // A new block for |entries| ring entries: corner (unless carried, with its
  // kRingPad -1s after the rings), neighbour, slot (|slot_corners| entries,
  // all -1; 0: none) and point. With |at_least| > 0, the block has room for
  // exactly that many int32s, for release_block, when the parts fit or one
  // of them set aside makes them fit; else it is their size. Every part but
  // corner and slot is left unwritten.
  void lay_out_block(int64_t entries, int64_t slot_corners, int64_t at_least);
  // Drops the slots (their memory stays in the block).
  void drop_slots() { slot = RingPart<int32_t>(); }
  // The block's memory, the table emptied.
  Array<int32_t> release_block();
};

struct ButterflyContext {
  const Mesh* mesh = nullptr;
  const CornerTable* ct = nullptr;
  // sharp[c] != 0 when the edge opposite corner c is a boundary or a crease;
  // an empty array means no creases (sharp = boundary).
  const std::vector<uint8_t>* sharp = nullptr;
  VertexClass vclass;
  double tension = 0;  // w of the 10-point stencil, 0 <= w <= 1/16
  // Green pairs (per face: 1 = first child (a, m, c), 2 = second (m, b, c));
  // null or empty when there are none. Stencils see a green pair as its
  // parent (a, b, c): the bisecting edge (m, c) is not part of any ring.
  const std::vector<uint8_t>* green = nullptr;
  // Optional (null: walk the fans); valid only for the level, positions and
  // green pairs it was built on. With green pairs only a table made by
  // build_level_rings (RingTable::walked_green) is read.
  const RingTable* rings = nullptr;
  // The routines for wider registers where the processor has them: regular
  // stencils and rule points summed with AVX (the same bits as SSE2, fewer
  // instructions), the rings' offsets with AVX-512, and the uniform level's
  // loops that read it (refine.cpp); false: the baseline ones, for tests.
  // The refinement hands it on to build_rings.
  bool wide = true;
};

// Removes the bisecting edges of green pairs from the apex valences.
void discount_green_apices(const Mesh& mesh, const std::vector<uint8_t>& green, VertexClass& vclass);

// Marks boundary edges and, when crease_angle > 0 and theta is given, edges
// with theta >= it. Returns true when only boundary edges can be marked (no
// crease was asked for): what classify_vertices' |sharp_is_boundary| wants.
bool mark_sharp_edges(const CornerTable& ct, const Array<float>* theta, double crease_angle,
                      std::vector<uint8_t>& sharp, int threads = 1);

// |sharp_is_boundary|: the sharp flags mark boundary edges only (no crease);
// the fans the corner table recorded are then used instead of walking. Empty
// |sharp|: no flags, the boundary edges are the sharp ones.
void classify_vertices(const Mesh& mesh, const CornerTable& ct, const std::vector<uint8_t>& sharp,
                       VertexClass& out, int threads = 1, bool sharp_is_boundary = false);

// Rings of the extraordinary vertices below |limit| on the current level:
// carried over from the level before (|out|.carried), else read from the fans
// the corner table recorded (CornerTable::fan_order), else walked.
// |wide| as in ButterflyContext (false: the baseline routines, for tests).
// |slots|: make RingTable::slot where it applies; false when only the
// general path will read the rings (creases or tension), which never reads them.
// |at_least|: int32s the table's block should have room for, for the caller
// to take with RingTable::release_block after the rings are used.
void build_rings(const Mesh& mesh, const CornerTable& ct, const VertexClass& vclass, int32_t limit, RingTable& out,
                 int threads = 1, bool wide = true, bool slots = true, int64_t at_least = 0);

// Rings of every extraordinary vertex of an adaptive level, walked as the
// extraordinary rule walks its fan: skipping the bisecting edge at the apex
// of each green pair of |green| (null or empty: none), with the valences of
// |vclass| (discount_green_apices'). A vertex whose walk of K steps does not
// close its fan gets no ring (the rule then walks). RingTable::walked_green
// is set: a ButterflyContext with these green pairs may then read it.
void build_level_rings(const Mesh& mesh, const CornerTable& ct, const VertexClass& vclass,
                       const std::vector<uint8_t>* green, RingTable& out, int threads = 1, bool wide = true);

// After a uniform split of this level (children of face f are 4f..4f+3, child
// k keeping corner k): keeps only the rings' corners, moved to the children,
// for build_rings on the next level. Valid only while the vertex classes are
// carried over too (uniform levels without creases).
void carry_rings(RingTable& rings, int threads);

// No green pairs, no tension and no sharp flags (sharp = boundary): then
// butterfly_points takes its plain loop, the only one that reads ring slots.
bool plain_stencils(const ButterflyContext& ctx);

// The stencil of the new vertex on the edge opposite corner c. Rules:
//  * sharp edge (boundary or crease): 4-point curve rule -1/16, 9/16, 9/16, -1/16
//    along the curve; at a curve end (a vertex with other than two sharp edges)
//    the missing point is extrapolated linearly (2 v1 - v2).
//  * interior edge, both endpoints complete: regular 8-point (10-point with
//    tension) when both have valence 6; the extraordinary rule of the
//    irregular endpoint; the average of both rules when both are irregular.
//  * interior edge touching a boundary or crease (our documented rule): the
//    extraordinary rule of the complete endpoint if exactly one is complete;
//    if neither is, the 8-point stencil with every wing that lies across a
//    sharp edge replaced by its parallelogram completion (the point a regular
//    planar grid would have there), so flat regions stay flat.
void butterfly_stencil(const ButterflyContext& ctx, int32_t c, std::vector<StencilTerm>& out);

// The same rule applied to |positions| (3 floats per vertex) without building
// the term list. Equal to the sum of butterfly_stencil's terms up to rounding
// (the regular case sums by weight class; an extraordinary rule is summed on
// its own, rounded to float, then scaled in, and read from the ring table's
// points where it has them); every refinement path computes positions with
// it, so the paths agree bit for bit.
void butterfly_point(const ButterflyContext& ctx, int32_t c, const float* positions, float out[3]);
// butterfly_point for |count| edges at once: out[3 i .. 3 i + 2] for corners[i].
void butterfly_points(const ButterflyContext& ctx, const int32_t* corners, int64_t count, const float* positions,
                      float* out);

}  // namespace iteas
