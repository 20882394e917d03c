#include "core/refine.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <cstring>
#include <limits>
#include <numeric>
#include <stdexcept>
#include <type_traits>
#include <unordered_map>
#include <utility>

#include "core/butterfly.h"
#include "core/cpu_features.h"
#include "core/parallel.h"

#if ITEAS_X86_FEATURES
#include <immintrin.h>
#endif

namespace iteas {
namespace {

template <typename T, typename A>
int64_t vbytes(const std::vector<T, A>& v) { return int64_t(v.capacity() * sizeof(T)); }

// Fixed-size chunks make prefix sums (and so all numbering) independent of
// the thread count. (The numbering does not depend on their size either:
// small enough that a small level's data pass splits evenly over two threads.)
constexpr int64_t kChunk = 1024;
// Per-face loops of a uniform level write 12 entries a face: this many faces
// take longer than handing half of them to another thread.
constexpr int64_t kFaceGrain = 1024;

// ---------------------------------------------------------------------------
// Wedge data: blended along an edge on one side (SPEC §2 "Attributes").

void blend_skin(Mesh& m, const Channel& joints, Channel& weights, int32_t out, int32_t a, int32_t b) {
  struct Influence { float joint, weight; };
  Influence inf[8];
  int n = 0;
  const int jc = joints.components, wc = weights.components;
  for (int32_t src : {a, b}) {
    for (int k = 0; k < std::min(jc, wc); ++k) {
      const float j = joints.data[size_t(src) * jc + k], w = 0.5f * weights.data[size_t(src) * wc + k];
      if (w <= 0) continue;
      int i = 0;
      while (i < n && inf[i].joint != j) ++i;
      if (i == n) inf[n++] = {j, w};
      else inf[i].weight += w;
    }
  }
  // Top 4 by weight (ties: lower joint first), renormalised.
  auto before = [](const Influence& x, const Influence& y) {
    return x.weight != y.weight ? x.weight > y.weight : x.joint < y.joint;
  };
  for (int i = 1; i < n; ++i)  // at most 8 entries: insertion sort
    for (int j = i; j > 0 && before(inf[j], inf[j - 1]); --j) std::swap(inf[j], inf[j - 1]);
  n = std::min(n, std::min(4, std::min(jc, wc)));
  float sum = 0;
  for (int i = 0; i < n; ++i) sum += inf[i].weight;
  Channel& jout = m.channels[weights.pair];
  for (int k = 0; k < jc; ++k) jout.data[size_t(out) * jc + k] = k < n ? inf[k].joint : 0.0f;
  for (int k = 0; k < wc; ++k) weights.data[size_t(out) * wc + k] = (k < n && sum > 0) ? inf[k].weight / sum : 0.0f;
}

// New wedges out0, out0 + 1, ... blended from the pairs of older wedges
// src[0, n): a channel at a time, each in a loop of its own (the sources are
// never among the wedges written, so the order changes no value). Per wedge,
// with a switch on the channel inside, the blending took a fifth of a
// normal-and-tangent mesh's refinement.
using WedgePair = std::pair<int32_t, int32_t>;
void blend_wedges(Mesh& m, int32_t out0, const WedgePair* src, int64_t n) {
  for (Channel& ch : m.channels) {
    float* d = ch.data.data();
    // The mean of both sources in the first |take| of the channel's
    // components, the first source's in the rest (a tangent's handedness):
    // a loop for each count glTF has (1 to 4, known when compiled), and
    // one for any other (|fixed| 0).
    auto mean = [&](auto fixed, int components, int take) {
      constexpr int kFixed = decltype(fixed)::value;
      const int cc = kFixed > 0 ? kFixed : components;
      for (int64_t i = 0; i < n; ++i) {
        float* o = d + size_t(out0 + i) * cc;
        const float* x = d + size_t(src[i].first) * cc;
        const float* y = d + size_t(src[i].second) * cc;
        for (int k = 0; k < cc; ++k) o[k] = k < take ? 0.5f * (x[k] + y[k]) : x[k];
      }
    };
    auto mean_of = [&](int components, int take) {
      switch (components) {
        case 1: mean(std::integral_constant<int, 1>(), components, take); break;
        case 2: mean(std::integral_constant<int, 2>(), components, take); break;
        case 3: mean(std::integral_constant<int, 3>(), components, take); break;
        case 4: mean(std::integral_constant<int, 4>(), components, take); break;
        default: mean(std::integral_constant<int, 0>(), components, take);
      }
    };
    const int c = ch.components;
    switch (ch.kind) {
      case ChannelKind::kJoints:
        if (ch.pair < 0) mean_of(c, 0);  // no weights: nearest
        break;                           // otherwise written with its WEIGHTS channel
      case ChannelKind::kWeights:
        if (ch.pair >= 0)
          for (int64_t i = 0; i < n; ++i)
            blend_skin(m, m.channels[ch.pair], ch, out0 + int32_t(i), src[i].first, src[i].second);
        else
          mean_of(c, c);
        break;
      case ChannelKind::kTangent:
        mean_of(c, std::min(c, 3));  // the handedness (w) kept
        break;
      default:
        mean_of(c, c);
    }
  }
}

// ---------------------------------------------------------------------------

struct State {
  CornerTable ct;
  Array<float> theta;          // per corner (adaptive levels and creases)
  std::vector<uint8_t> sharp;  // per corner
  std::vector<uint8_t> green;  // per face: 0, 1 (first child), 2 (second child)
  // Stall detection (adaptive modes, stall > 0): per face, the largest θ its
  // parent had when it was split 1 -> 4 (infinity for faces never born so).
  double stall = 0;
  std::vector<float> born;
  // Geometric tolerances in model units (0 = off): see RefineOptions.
  double tolerance = 0, flat_limit = 0;
  ButterflyContext bctx;
  // Uniform levels: rings of the extraordinary vertices, all of which are
  // input vertices (index below ring_limit).
  RingTable rings;
  // Adaptive levels: the rings of every extraordinary vertex of the level
  // (build_level_rings), made where select_faces measures most edges afresh
  // and read by the level's Butterfly points until its data pass is done
  // (select_faces, close_selection's green test, adaptive_level).
  RingTable level_rings;
  const std::vector<uint8_t> no_flags{};  // empty: no sharp flags, no green pairs (ButterflyContext)
  // A last uniform level with statistics: the parent level's opposites, the
  // children's table not made (uniform_level); empty otherwise.
  Array<int32_t> split_from;
  int32_t ring_limit = 0;
  int threads = 1;
  int64_t peak = 0;
  // The uniform level derived sharp flags and vertex classes of the new level
  // by arithmetic (valid only without creases, which depend on geometry).
  bool classes_valid = false;
  // Adaptive modes: the squared sine of the smallest angle new triangles may
  // have (half the input's smallest angle); 0 = no guard (uniform mode).
  double floor_sin2 = 0;
  // Angles and deviations carried to the next adaptive level. An edge's θ
  // reads its two faces; its Butterfly point (and so its deviation) only the
  // faces round its two ends (their vertices, positions, green flags and the
  // sharpness of the edges at those ends); old vertices never move. So an
  // edge whose ends no changed face touches has the θ and deviation it had.
  // |theta|, |deviation|: per corner of the level just refined (deviation -1:
  // not computed; empty when no tolerance or flat limit is in use);
  // |kept_from|: per face of the new level, the face of that level it copies
  // unchanged (same corners in the same order; kept faces keep their relative
  // order, so an edge's first corner, from which it is computed, is the same
  // face's), or -1; |touched|: per vertex of the new level, 1 when a face
  // round it changed (or it is new).
  struct Carried {
    Array<float> theta;
    std::vector<float> deviation;
    std::vector<int32_t> kept_from;
    std::vector<uint8_t> touched;
    bool valid = false;
    // The test of a carried edge (no angles: those are the caller's).
    CarriedAngles edges() const {
      CarriedAngles e;
      e.kept_from = kept_from.data();
      e.touched = touched.data();
      return e;
    }
  } carried;
  // s.theta is that of the mesh as it is now (a level that changes the mesh
  // clears it; analyse then computes the angles again).
  bool theta_current = false;
  // The input's corner table split vertices: it was matched before they were
  // split, so an edge there may be cut by a face that no longer shares its
  // ends (a doubled triangle's), which the next level's table no longer
  // sees. Nothing is carried from that level.
  bool input_split = false;
  bool carry = true;  // RefineHooks::carry
  bool incremental_table = true;  // RefineHooks::incremental_table
  bool level_rings_on = true;     // RefineHooks::level_rings
  const std::function<void(const float*, int64_t)>* deviations_seen = nullptr;  // RefineHooks::deviations
  // Work another thread does beside a uniform level, reading the level's
  // corners and opposites (first_level_beside_input): uniform_level calls
  // finish() before it replaces them. |beside_bytes|: what that work holds.
  BesideWork* beside = nullptr;
  int64_t beside_bytes = 0;
};

void note_peak(State& s, const Mesh& m, int64_t extra) {
  const int64_t b = mesh_bytes(m) + vbytes(s.ct.opposites()) + vbytes(s.ct.vertex_corners()) + vbytes(s.ct.fans()) +
                    vbytes(s.theta) + vbytes(s.sharp) + vbytes(s.green) + vbytes(s.born) +
                    vbytes(s.bctx.vclass.valence) + vbytes(s.bctx.vclass.complete) + vbytes(s.rings.kept) +
                    vbytes(s.rings.block) + vbytes(s.rings.side) + vbytes(s.level_rings.kept) +
                    vbytes(s.level_rings.block) +
                    vbytes(s.carried.theta) + vbytes(s.carried.deviation) + vbytes(s.carried.kept_from) +
                    vbytes(s.carried.touched) + vbytes(s.split_from) + s.beside_bytes + extra;
  s.peak = std::max(s.peak, b);
}

// Applies the Butterfly stencil of the edge at corner c to the new vertex nv.
void apply_stencil(Mesh& m, const ButterflyContext& ctx, int32_t c, int32_t nv, std::vector<StencilTerm>& terms) {
  butterfly_point(ctx, c, m.positions.data(), &m.positions[3 * size_t(nv)]);
  if (m.vertex_channels.empty()) return;
  butterfly_stencil(ctx, c, terms);  // the same rule for the morph deltas
  for (VertexChannel& vc : m.vertex_channels) {
    double d[3] = {0, 0, 0};
    for (const StencilTerm& t : terms)
      for (int k = 0; k < 3; ++k) d[k] += t.weight * vc.data[3 * size_t(t.vertex) + k];
    for (int k = 0; k < 3; ++k) vc.data[3 * size_t(nv) + k] = float(d[k]);
  }
}

// The new vertices first, first + 1, ... of the edges at corners[0, n): with
// positions alone, all their points in one butterfly_points call; else one
// stencil each (applied to the morph deltas too).
void apply_stencils(Mesh& m, const ButterflyContext& ctx, const int32_t* corners, int64_t n, int32_t first,
                    std::vector<StencilTerm>& terms) {
  if (m.vertex_channels.empty()) {
    butterfly_points(ctx, corners, n, m.positions.data(), &m.positions[3 * size_t(first)]);
    return;
  }
  for (int64_t i = 0; i < n; ++i) apply_stencil(m, ctx, corners[i], first + int32_t(i), terms);
}

// The edges of a mesh of |faces| triangles with |boundary| boundary edges
// (cut edges included): a uniform level's new vertices, one per edge.
int64_t uniform_edges(int64_t faces, int64_t boundary) { return (3 * faces + boundary) / 2; }

void grow_vertices(Mesh& m, int64_t nv) {
  m.positions.resize(3 * size_t(nv));
  for (VertexChannel& vc : m.vertex_channels) vc.data.resize(3 * size_t(nv));
}

void grow_wedges(Mesh& m, int64_t nw) {
  m.wedge_vertex.resize(nw);
  for (Channel& ch : m.channels) ch.data.resize(size_t(nw) * ch.components);
}

// s.theta for the current mesh (ct must be valid), each edge carried from the
// level before where adaptive_level says it is unchanged.
void current_angles(State& s, const Mesh& m) {
  CarriedAngles from;
  if (s.carried.valid && !s.carried.theta.empty()) {
    from = s.carried.edges();
    from.theta = s.carried.theta.data();
  }
  edge_angles(m, s.ct, s.theta, s.threads, from);
  s.theta_current = true;
}

// Prepares the per-level analysis on the current mesh (ct must be valid).
void analyse(State& s, Mesh& m, const RefineOptions& o, bool need_theta) {
  s.bctx.mesh = &m;
  s.bctx.ct = &s.ct;
  s.bctx.sharp = &s.sharp;
  s.bctx.tension = o.tension;
  s.bctx.green = &s.green;
  if (need_theta && !s.theta_current) {
    current_angles(s, m);
  } else if (!need_theta) {
    Array<float>().swap(s.theta);
    s.theta_current = false;
  }
  Array<float>().swap(s.carried.theta);
  if (s.classes_valid && !need_theta) return;  // derived by the uniform level
  s.classes_valid = false;
  // Without angles there are no creases (the uniform path without
  // crease_angle): the sharp edges are the boundary, which the opposites
  // already tell, so no flags are made (as on the levels the uniform path derives).
  bool boundary_only = true;
  if (need_theta) boundary_only = mark_sharp_edges(s.ct, &s.theta, o.crease_angle, s.sharp, s.threads);
  else std::vector<uint8_t>().swap(s.sharp);
  classify_vertices(m, s.ct, s.sharp, s.bctx.vclass, s.threads, boundary_only);
  if (!s.green.empty()) discount_green_apices(m, s.green, s.bctx.vclass);
  // The Butterfly rules read "the sharp edges are the boundary" and "no
  // green pair" from empty arrays, and then take their fast path (the plain
  // stencils without those checks): an adaptive level's first, and any
  // without creases, gets it where the flags would say nothing more.
  if (boundary_only) s.bctx.sharp = &s.no_flags;
  if (std::none_of(s.green.begin(), s.green.end(), [](uint8_t g) { return g != 0; })) s.bctx.green = &s.no_flags;
}

#if ITEAS_X86_FEATURES
// The children's corners of faces [b, e) of a uniform level (see
// uniform_level) four faces at a time: their twelve corners and twelve edge
// points (|evert| at each edge's canonical corner, the smaller of the corner
// and its opposite, unsigned) in two registers, the children's 48 corners
// picked from them by three fixed permutations. Returns the first face left
// to the caller (the last ones, whose 16-corner loads would run past the arrays).
struct ChildPick {
  alignas(64) int32_t idx[3][16];
  constexpr ChildPick() : idx() {
    // Child corner j of a face: the parent's corner j / 4 at j = 0, 4, 8,
    // else the edge point m_k (16 + the face's corner k in the second register).
    constexpr int kEdge[12] = {-1, 2, 1, 2, -1, 0, 1, 0, -1, 0, 1, 2};
    for (int i = 0; i < 48; ++i) {
      const int t = i / 12, j = i % 12;
      idx[i / 16][i % 16] = kEdge[j] < 0 ? 3 * t + j / 4 : 16 + 3 * t + kEdge[j];
    }
  }
};
constexpr ChildPick kChildPick;

// With |ccw|, the children's wedges the same way, from the parent's corners'
// wedges (|pcw|) and the edge points' wedges on the face's side (|ewedge|,
// at every corner).
__attribute__((target("avx512f"))) int64_t children_avx512(const int32_t* pcv, const int32_t* opp,
                                                            const int32_t* evert, const int32_t* pcw,
                                                            const int32_t* ewedge, int64_t b, int64_t e, int64_t nc,
                                                            int32_t* ccv, int32_t* ccw) {
  const __m512i lane = _mm512_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15);
  const __m512i pick0 = _mm512_load_si512(kChildPick.idx[0]), pick1 = _mm512_load_si512(kChildPick.idx[1]),
                pick2 = _mm512_load_si512(kChildPick.idx[2]);
  int64_t f = b;
  for (; f + 4 <= e && 3 * f + 16 <= nc; f += 4) {
    const int64_t p = 3 * f;
    const __m512i corners = _mm512_loadu_si512(pcv + p);
    const __m512i corner = _mm512_add_epi32(_mm512_set1_epi32(int32_t(p)), lane);
    const __m512i edge = _mm512_maskz_min_epu32(0xFFFF, corner, _mm512_loadu_si512(opp + p));
    const __m512i m = _mm512_mask_i32gather_epi32(_mm512_setzero_si512(), 0x0FFF, edge, evert, 4);
    int32_t* out = ccv + 4 * p;
    _mm512_storeu_si512(out, _mm512_permutex2var_epi32(corners, pick0, m));
    _mm512_storeu_si512(out + 16, _mm512_permutex2var_epi32(corners, pick1, m));
    _mm512_storeu_si512(out + 32, _mm512_permutex2var_epi32(corners, pick2, m));
    if (ccw) {
      const __m512i cw = _mm512_loadu_si512(pcw + p), mw = _mm512_loadu_si512(ewedge + p);
      int32_t* wout = ccw + 4 * p;
      _mm512_storeu_si512(wout, _mm512_permutex2var_epi32(cw, pick0, mw));
      _mm512_storeu_si512(wout + 16, _mm512_permutex2var_epi32(cw, pick1, mw));
      _mm512_storeu_si512(wout + 32, _mm512_permutex2var_epi32(cw, pick2, mw));
    }
  }
  return f;
}
#endif

// ---------------------------------------------------------------------------
// Uniform level: every edge splits. Connectivity of the children, including
// their opposites, follows from the parent's by index arithmetic, so no
// adjacency is rebuilt. Children of face f are 4f+j: child j (< 3) keeps
// parent vertex j at local corner j, child 3 is the centre; the half of the
// parent edge opposite corner k next to vertex k+1 (k+2) is the edge opposite
// local corner k of child k+1 (k+2). Without |connectivity| (the last level)
// the children's corner table and vertex classes are not made: nothing would
// read them, and the statistics, with |split_summary|, take the children's
// opposites from the parent's (State::split_from), a block at a time.
void uniform_level(State& s, Mesh& m, LevelStats& ls, bool derive_classes, bool connectivity, bool more_levels,
                   bool split_summary) {
  const int32_t nf = m.num_faces(), nv = m.num_vertices();
  const int64_t nc = 3 * int64_t(nf);
  const int32_t* opp = s.ct.opposites().data();
  // opp[c] < 0 || c < opp[c], in one unsigned comparison (no branch: about
  // half the corners are canonical, in no order a predictor could learn).
  auto canonical = [opp](int64_t c) { return uint32_t(opp[c]) > uint32_t(c); };
  // The canonical corner of c's edge (the smaller of c and its opposite, a
  // boundary's -1 being the largest as unsigned).
  auto edge_of = [opp](size_t c) { return std::min(uint32_t(c), uint32_t(opp[c])); };
  derive_classes = derive_classes && s.green.empty() && connectivity;

  // Topology pass 1: number edges (canonical corners) in corner order.
  const int64_t chunks = (nc + kChunk - 1) / kChunk;
  std::vector<int64_t> edges_in(chunks + 1, 0), wedges_in(chunks + 1, 0);
  const bool wedges = m.has_wedges();
  const int32_t* cw_old = wedges ? m.corner_wedge.data() : nullptr;
  // Does the edge at corner c carry the same two wedges on both sides?
  auto shared = [cw_old](int32_t c, int32_t o) {
    return cw_old[next_corner(c)] == cw_old[prev_corner(o)] && cw_old[prev_corner(c)] == cw_old[next_corner(o)];
  };
  // Per canonical corner, with wedges: 2 where its edge's two sides carry
  // different wedges (the data pass makes two new wedges there), else 1.
  Array<uint8_t> made(wedges ? size_t(nc) : 0);
  parallel_for_chunks(chunks, s.threads, [&](int64_t b, int64_t e) {
    for (int64_t k = b; k < e; ++k) {
      int64_t ne = 0, nw = 0;
      const int64_t begin = k * kChunk, end = std::min(nc, (k + 1) * kChunk);
      if (!wedges) {
        ne = count_canonical_corners(opp, begin, end, s.bctx.wide);
      } else {
        for (int64_t c = begin; c < end; ++c) {
          if (!canonical(c)) continue;
          ++ne;
          const uint8_t w = (opp[c] < 0 || shared(int32_t(c), opp[c])) ? 1 : 2;
          made[size_t(c)] = w;
          nw += w;
        }
      }
      edges_in[k + 1] = ne;
      wedges_in[k + 1] = nw;
    }
  });
  for (int64_t k = 0; k < chunks; ++k) {
    edges_in[k + 1] += edges_in[k];
    wedges_in[k + 1] += wedges_in[k];
  }
  const int64_t ne = edges_in[chunks];
  const int32_t nw0 = m.wedge_count();
  grow_vertices(m, int64_t(nv) + ne);
  if (wedges) grow_wedges(m, int64_t(nw0) + wedges_in[chunks]);
  VertexClass& vclass = s.bctx.vclass;
  // Rings carried to the next level keep their corners; else their block
  // is made large enough for the children's corners, which take its memory
  // once the rings are done (see RingTable::block).
  const bool carry = derive_classes && more_levels;
  if (s.green.empty()) {
    // Slots only for the plain stencils' path (no creases, no tension).
    build_rings(m, s.ct, vclass, s.ring_limit, s.rings, s.threads, s.bctx.wide, plain_stencils(s.bctx),
                carry ? 0 : 12 * int64_t(nf));
    s.bctx.rings = &s.rings;
  }
  s.ct.forget_fans();  // the arithmetic below changes the table
  // No zero fill: every entry of these that is read is written below (evert
  // at canonical corners only; a corner reads its edge's, edge_of). Made
  // after the fans go, whose memory they then take (level 1 of a 3,674-face
  // mesh: 11 fresh pages fewer, and a lower peak while the rings are made).
  Array<int32_t> evert(nc), ewedge(wedges ? nc : 0);
  if (derive_classes) {
    vclass.valence.resize(size_t(nv) + ne);
    vclass.complete.resize(size_t(nv) + ne);
  }
  // The new vertices' fan corners are written by the data pass (the stencils
  // read only the old vertices' corners).
  std::vector<int32_t>& vc = s.ct.vertex_corners();
  if (connectivity) vc.resize(size_t(nv) + ne);

  // Data pass: stencils from the old level, a chunk of edges at a time; new
  // wedges blended per side.
  parallel_for_chunks(chunks, s.threads, [&](int64_t b, int64_t e) {
    Array<int32_t> list(kChunk);
    std::vector<StencilTerm> terms;
    std::vector<WedgePair> sources;  // the chunk's new wedges' (a, b)
    if (wedges) sources.reserve(2 * kChunk);
    for (int64_t k = b; k < e; ++k) {
      const int64_t n =
          list_canonical_corners(opp, k * kChunk, std::min(nc, (k + 1) * kChunk), list.data(), s.bctx.wide);
      const int32_t first = int32_t(nv + edges_in[k]);
      apply_stencils(m, s.bctx, list.data(), n, first, terms);
      // Raw pointers: the byte stores below may alias anything, which would
      // make the compiler reload every array's address after each of them.
      int32_t* ev = evert.data();
      const int32_t* listed = list.data();
      // Canonical corners only: the children pass reads its twin's through
      // edge_of. (Writing both sides here scattered a store to the
      // neighbour's face per edge; level 4 ran about 6 % longer.)
      for (int64_t i = 0; i < n; ++i) ev[listed[i]] = first + int32_t(i);
      if (connectivity) {
        // The new vertex on the edge opposite corner k of face f starts its
        // fan at corner k+1 of child k+2.
        int32_t* fan = vc.data() + first;
        for (int64_t i = 0; i < n; ++i) {
          const uint32_t f = uint32_t(listed[i]) / 3u, k = uint32_t(listed[i]) % 3u;
          fan[i] = int32_t(3 * (4 * f + (k + 2) % 3) + (k + 1) % 3);
        }
      }
      if (derive_classes) {
        // A midpoint of an interior edge has a closed fan of six faces; of a
        // boundary edge, an open fan of three (valence 4).
        int32_t* valence = vclass.valence.data() + first;
        uint8_t* complete = vclass.complete.data() + first;
        for (int64_t i = 0; i < n; ++i) {
          const bool interior = opp[listed[i]] >= 0;
          valence[i] = 4 + 2 * int32_t(interior);
          complete[i] = interior ? VertexClass::kRegular : 0;
        }
      }
      if (!wedges) continue;
      // The chunk's new wedges are w0, w0 + 1, ...: one per source pair.
      const int32_t w0 = int32_t(nw0 + wedges_in[k]);
      sources.clear();
      for (int64_t i = 0; i < n; ++i) {
        const int32_t c = list[i], o = opp[c], v = first + int32_t(i);
        const int32_t wf = w0 + int32_t(sources.size());
        m.wedge_vertex[wf] = v;
        sources.emplace_back(cw_old[next_corner(c)], cw_old[prev_corner(c)]);
        ewedge[c] = wf;
        if (o < 0) continue;
        if (made[size_t(c)] == 1) { ewedge[o] = wf; continue; }
        const int32_t wg = w0 + int32_t(sources.size());
        m.wedge_vertex[wg] = v;
        sources.emplace_back(cw_old[next_corner(o)], cw_old[prev_corner(o)]);
        ewedge[o] = wg;
      }
      blend_wedges(m, w0, sources.data(), int64_t(sources.size()));
    }
  });

  // The level's connectivity is about to change; the rings go before the
  // children's arrays come (peak memory), but for their corners when the next
  // level will want them (the larger next level sets the peak then). Their
  // block's memory, already the process's, becomes the children's corners.
  s.bctx.rings = nullptr;
  note_peak(s, m, vbytes(evert) + vbytes(ewedge) + vbytes(made));
  Array<uint8_t>().swap(made);
  Array<int32_t> spare;
  if (carry && !s.rings.offset.empty()) carry_rings(s.rings, s.threads);
  else spare = s.rings.release_block();

  // Topology pass 2: children. Then the new vertices' fan corners, while the
  // old opposites still tell canonical corners; then the old connectivity and
  // the edge maps go before the children's opposites are made (peak memory).
  Array<int32_t> cv, cw(wedges ? 12 * size_t(nf) : 0);
  // Only a block of the right size: any excess would stay with the corners.
  if (spare.capacity() == 12 * size_t(nf)) cv.swap(spare);  // no copy: every entry is written below
  Array<int32_t>().swap(spare);
  cv.resize(12 * size_t(nf));
  std::vector<int32_t> fg(m.face_group.empty() ? 0 : 4 * size_t(nf));
  const int32_t* pcv = m.corner_vertex.data();
  parallel_for(nf, s.threads, [&](int64_t b, int64_t e) {
    int32_t* ccv = cv.data();
    int32_t* ccw = cw.data();
    int64_t from = b;
#if ITEAS_X86_FEATURES
    if (fg.empty() && s.bctx.wide && cpu_has(CpuFeature::kAvx512))
      from = children_avx512(pcv, opp, evert.data(), cw_old, ewedge.data(), b, e, nc, ccv, wedges ? ccw : nullptr);
#endif
    for (int64_t f = from; f < e; ++f) {
      const size_t p = 3 * size_t(f), q = 12 * size_t(f);
      const int32_t m0 = evert[edge_of(p)], m1 = evert[edge_of(p + 1)], m2 = evert[edge_of(p + 2)];
      // Child j keeps vertex j; the centre child is (m0, m1, m2).
      ccv[q + 0] = pcv[p];     ccv[q + 1] = m2;         ccv[q + 2] = m1;
      ccv[q + 3] = m2;         ccv[q + 4] = pcv[p + 1]; ccv[q + 5] = m0;
      ccv[q + 6] = m1;         ccv[q + 7] = m0;         ccv[q + 8] = pcv[p + 2];
      ccv[q + 9] = m0;         ccv[q + 10] = m1;        ccv[q + 11] = m2;
      if (wedges) {
        const int32_t w0 = ewedge[p], w1 = ewedge[p + 1], w2 = ewedge[p + 2];
        ccw[q + 0] = cw_old[p];  ccw[q + 1] = w2;            ccw[q + 2] = w1;
        ccw[q + 3] = w2;         ccw[q + 4] = cw_old[p + 1]; ccw[q + 5] = w0;
        ccw[q + 6] = w1;         ccw[q + 7] = w0;            ccw[q + 8] = cw_old[p + 2];
        ccw[q + 9] = w0;         ccw[q + 10] = w1;           ccw[q + 11] = w2;
      }
      if (!fg.empty()) for (int j = 0; j < 4; ++j) fg[4 * size_t(f) + j] = m.face_group[f];
    }
  }, kFaceGrain);

  // The old vertices' corners follow: corner k of face f becomes corner k of
  // child k (still the start of an open fan).
  if (connectivity) parallel_for(nv, s.threads, [&](int64_t b, int64_t e) {
    for (int64_t v = b; v < e; ++v) {
      const int32_t c = vc[v];
      if (c >= 0) vc[v] = kept_child_corner(c);
    }
  });
  // The parent's corners and opposites are replaced below.
  if (s.beside) s.beside->finish();
  note_peak(s, m, vbytes(evert) + vbytes(ewedge) + vbytes(cv) + vbytes(cw) + vbytes(fg));
  Array<int32_t>().swap(evert);
  Array<int32_t>().swap(ewedge);
  m.corner_vertex.swap(cv);
  Array<int32_t>().swap(cv);
  if (wedges) { m.corner_wedge.swap(cw); Array<int32_t>().swap(cw); }
  if (!fg.empty()) m.face_group.swap(fg);
  std::vector<int32_t>().swap(fg);

  // Children's opposites from the parent's alone.
  Array<int32_t> nopp(connectivity ? 12 * size_t(nf) : 0);
  if (connectivity) parallel_for(nf, s.threads, [&](int64_t b, int64_t e) {
    split_opposites(opp, nc, b, e, nopp.data() + 12 * b, s.bctx.wide);
  }, kFaceGrain);
  note_peak(s, m, vbytes(nopp));
  if (connectivity) {
    s.ct.opposites().swap(nopp);
    Array<int32_t>().swap(nopp);
  } else {
    // The parent's opposites kept for the statistics, which make the
    // children's a block at a time (summarize_split_angles).
    if (split_summary) s.split_from.swap(s.ct.opposites());
    s.ct = CornerTable();  // stale: no use may follow
  }
  Array<float>().swap(s.theta);
  s.theta_current = false;
  // Without creases the next level's sharp edges are its boundary: no flags.
  std::vector<uint8_t>().swap(s.sharp);
  if (!derive_classes) {
    std::vector<int32_t>().swap(vclass.valence);
    std::vector<uint8_t>().swap(vclass.complete);
  }
  s.classes_valid = derive_classes;
  if (!s.green.empty()) s.green.assign(m.num_faces(), 0);

  ls.faces_selected = nf;
  ls.red_splits = nf;
  ls.vertices_added = ne;
}

// The input's angle statistics from its θ: the summary, T (the mean, or
// |spec|'s statistic when given) and the edges above T. Deterministic, so
// the same bits on any thread count, whichever thread takes them.
struct InputAngles {
  AngleSummary before;
  double threshold = 0;
};
InputAngles input_angles(const Mesh& m, const CornerTable& ct, const Array<float>& theta, double crease, int threads,
                         const ThresholdSpec* spec = nullptr) {
  InputAngles r;
  r.before = summarize_angles(m, ct, &theta, 0, crease, threads);
  r.threshold = spec ? compute_threshold(*spec, m, ct, theta, crease, threads) : r.before.mean;
  r.before.above = count_angles_above(ct, theta, r.threshold, crease, threads);
  return r;
}

// A uniform job's first level on this thread while another takes the
// input's angle statistics (input_angles), which nothing in the level reads.
// On two threads a small level gained little or nothing from the second
// thread, which then waited on the lines the first had written (bunny-npm
// level 1: 0.80-1.11x one thread's speed), while the statistics, on lines
// of their own, are work of about the same size. The statistics read the
// input's opposites where they are, until the level replaces them (it waits
// for them there), and a copy of its points and corners, made on their
// thread from where they are (the level appends points, whose array's size
// then changes, but never moves them: |points_kept| says the array has room
// for the level's points). With one thread, or the other not free, both run
// here in turn. The other thread's arrays (at most about 1 MB: refine_mesh
// takes this path for inputs under kSmallStepFaces faces) are outside a
// MemoryBudget of this thread, as the buffers of loops' pieces are.
InputAngles first_level_beside_input(State& s, Mesh& m, LevelStats& ls, bool connectivity, bool more_levels,
                                     bool split_summary, size_t points_kept) {
  if (m.positions.capacity() < points_kept) throw std::logic_error("first_level_beside_input: no room for the points");
  InputAngles out;
  const float* const points = m.positions.data();
  const size_t n_points = m.positions.size();
  const int32_t* const corners = m.corner_vertex.data();
  const size_t n_corners = m.corner_vertex.size();
  const CornerTable& table = s.ct;
  BesideWork work([&] {
    Mesh input;
    input.positions.assign(points, points + n_points);
    input.corner_vertex.assign(corners, corners + n_corners);
    Array<float> theta;
    edge_angles(input, table, theta, 1);
    out = input_angles(input, table, theta, 0, 1);  // (no creases: see refine_mesh)
  });
  // The copy and its θ.
  s.beside_bytes = int64_t(sizeof(float)) * int64_t(n_points + 2 * n_corners);
  const int threads = s.threads;
  s.threads = 1;
  s.beside = &work;
  struct Restore {  // on return and on a throw alike
    State& s;
    int threads;
    ~Restore() {
      s.threads = threads;
      s.beside = nullptr;
      s.beside_bytes = 0;
    }
  } restore{s, threads};
  // (The level always calls work.finish(), which rethrows what the work threw.)
  parallel_for_chunks(2, threads, [&](int64_t b, int64_t e) {
    for (int64_t k = b; k < e; ++k) {
      if (k == 0) uniform_level(s, m, ls, true, connectivity, more_levels, split_summary);
      else work.offer();
    }
  });
  return out;
}

// ---------------------------------------------------------------------------
// Adaptive level with red-green closure.

struct Plan {
  std::vector<uint8_t> split;   // per corner: its edge gets a new vertex
  std::vector<uint8_t> merged;  // per face (first green child): pair merged
  // Per chunk of kChunk faces, the faces the level makes of the faces
  // before it (chunks + 1 entries): where adaptive_level writes each chunk's.
  std::vector<int64_t> made_before;
  int64_t triangles = 0;
};

// How many faces adaptive_level makes of face f, given which of the level's
// corners have their edge split (split(c)): kept, 1; green bisection, 2;
// red 1 -> 4, 4; a green pair's faces counted at its first face: 2 kept, or
// merged back, its parent's four children, the two on the parent's old
// halves bisected when their outer edge splits (the pair's inner edge is
// not read).
template <typename Split>
inline int made_of(const uint8_t* green, const uint8_t* merged, const Split& split, int64_t f) {
  if (green[f] == 2) return 0;
  if (green[f] == 1) return merged[f] ? 2 + (split(3 * f + 2) ? 2 : 1) + (split(3 * f + 5) ? 2 : 1) : 2;
  const int sc = int(split(3 * f)) + int(split(3 * f + 1)) + int(split(3 * f + 2));
  return sc == 0 ? 1 : (sc == 1 ? 2 : 4);
}

// Is the smallest angle of triangle (p, q, r) under the floor whose squared
// sine is sin2? (A triangle with coinciding points is.)
bool below_floor(const double* p, const double* q, const double* r, double sin2) {
  return smallest_angle_sin2(p, q, r) < sin2;
}

void load_point(const Mesh& m, int32_t v, double* out) {
  for (int i = 0; i < 3; ++i) out[i] = m.positions[3 * size_t(v) + i];
}

// Displacement steps of the sliver guard: after step k the new vertex on edge
// (a, b) sits at the midpoint plus 2^-k of its Butterfly displacement, and at
// the midpoint itself after the last step.
constexpr int kGuardSteps = 4;
void guard_point(const double* a, const double* b, const float* butterfly, int step, double* out) {
  const double t = step >= kGuardSteps ? 0.0 : std::ldexp(1.0, -step);
  for (int k = 0; k < 3; ++k) {
    const double mid = 0.5 * (a[k] + b[k]);
    out[k] = mid + t * (double(butterfly[k]) - mid);
  }
}

// Would the later merge of a green pair — parent (a, b, c), midpoint m on
// (a, b) — make a triangle under the floor? When a neighbour asks for it, the
// pair is merged and its parent split 1 -> 4 around m: (a, m, ca), (m, b, bc),
// (ca, bc, c), (bc, ca, m), with ca and bc on the parent's other edges, and the
// halves (a, m) and (m, b) may then be bisected (the greens born inside that
// split). Checked with ca, bc and the halves' points at their midpoints, where
// the sliver guard of that later level can always put them: tri(p, q, r) is
// called for each of those eight triangles in turn, until it returns true.
template <typename F>
bool merge_triangles(const double* a, const double* m, const double* b, const double* c, F&& tri) {
  double ca[3], bc[3], am[3], mb[3];
  for (int i = 0; i < 3; ++i) {
    ca[i] = 0.5 * (c[i] + a[i]);
    bc[i] = 0.5 * (b[i] + c[i]);
    am[i] = 0.5 * (a[i] + m[i]);
    mb[i] = 0.5 * (m[i] + b[i]);
  }
  return tri(a, m, ca) || tri(m, b, bc) || tri(ca, bc, c) || tri(bc, ca, m) || tri(a, am, ca) || tri(am, m, ca) ||
         tri(m, mb, bc) || tri(mb, b, bc);
}
bool poor_merge(const double* a, const double* m, const double* b, const double* c, double f2) {
  return merge_triangles(a, m, b, c, [f2](const double* p, const double* q, const double* r) {
    return below_floor(p, q, r, f2);
  });
}

// Would bisecting face f at its one split edge (opposite its corner k) make
// a triangle whose smallest angle is under the floor, at any point the sliver
// guard may leave on that edge — or would the later merge of the pair around
// that point? Then the closure splits f 1 -> 4 instead (its children keep its
// shape).
bool poor_green(const State& s, const Mesh& m, int32_t f, int k) {
  if (s.floor_sin2 <= 0) return false;
  int32_t c = 3 * f + k;
  const int32_t o = s.ct.opposite(c);
  if (o >= 0 && o < c) c = o;  // the stencil as the level will evaluate it
  float bf[3];
  butterfly_point(s.bctx, c, m.positions.data(), bf);
  double apex[3], a[3], b[3];
  load_point(m, m.corner_vertex[3 * f + k], apex);
  load_point(m, m.corner_vertex[3 * f + (k + 1) % 3], a);
  load_point(m, m.corner_vertex[3 * f + (k + 2) % 3], b);
  // Every point the guard may leave on the edge (t = 1, 1/2, ..., 0 of the
  // displacement): the two green triangles and the pair's later merge. All
  // fifty triangles are listed, then measured in one vectorised loop
  // (smallest_angle_sin2's bits): nearly always none is under the floor,
  // and each would have been measured anyway.
  constexpr int kTriangles = 10 * (kGuardSteps + 1);
  double coords[9][kTriangles];
  int n = 0;
  auto add = [&](const double* p, const double* q, const double* r) {
    for (int k = 0; k < 3; ++k) {
      coords[k][n] = p[k];
      coords[3 + k][n] = q[k];
      coords[6 + k][n] = r[k];
    }
    ++n;
    return false;  // list them all
  };
  for (int step = 0; step <= kGuardSteps; ++step) {
    double mid[3];
    guard_point(a, b, bf, step, mid);
    add(a, mid, apex);
    add(mid, b, apex);
    merge_triangles(a, mid, b, apex, add);
  }
  const double* pqr[9];
  for (int j = 0; j < 9; ++j) pqr[j] = coords[j];
  double sin2[kTriangles];
  smallest_angle_sin2s(pqr, n, sin2);
  const double f2 = s.floor_sin2;
  for (int i = 0; i < n; ++i)
    if (sin2[i] < f2) return true;
  return false;
}

// The sliver guard of adaptive levels: a new triangle whose smallest angle is
// under the floor has the Butterfly displacement of its new vertices (from the
// edge midpoint) halved, round after round (1, 1/2, 1/4, 1/8, then 0: the
// midpoint, where a 1 -> 4 split reproduces its parent's shape). Rounds see the
// whole level at once, so the result does not depend on any order or on the
// thread count. Returns how many new vertices were moved. |kept_from|: per
// face of the new level, the old face it copies unchanged or -1 (Emitter::from).
int64_t guard_slivers(const State& s, Mesh& m, const Array<int32_t>& old_cv, const std::vector<int32_t>& edges,
                      int32_t nv, const std::vector<int32_t>& kept_from) {
  const int64_t ne = int64_t(edges.size());
  // Butterfly points of the vertices moved so far (few): memory stays at two
  // bytes per new vertex however large the level.
  std::unordered_map<int64_t, std::array<float, 3>> butterfly;
  std::vector<uint8_t> step(ne, 0), mark(ne), moved(ne, 0);
  // Only faces the level made can have a new vertex (a kept face has its
  // old ones, a kept green pair too): listed once, in face order.
  std::vector<int32_t> made;
  const int32_t nf = m.num_faces();
  const int32_t* from = kept_from.data();
  parallel_count_fill(
      nf, s.threads, kChunk,
      [from](int64_t b, int64_t e) {
        return int64_t(std::count_if(from + b, from + e, [](int32_t x) { return x < 0; }));
      },
      [&made](int64_t total) { made.resize(size_t(total)); },
      [from, &made](int64_t b, int64_t e, int64_t at) {
        for (int64_t f = b; f < e; ++f)
          if (from[f] < 0) made[size_t(at++)] = int32_t(f);
      });
  // Each round moves every marked vertex one step; a vertex stops at the
  // midpoint, so rounds end when no poor face has a vertex left to move.
  // After the first round only faces with a vertex the last round moved can
  // change their verdict, so only those are looked at again. The faces are
  // judged on all threads: a vertex is marked when any of its faces is poor
  // (the same byte stored by whichever thread finds one).
  for (int round = 0; round < 8 * kGuardSteps; ++round) {
    std::fill(mark.begin(), mark.end(), 0);
    std::atomic<bool> marked{false};
    parallel_for(int64_t(made.size()), s.threads, [&](int64_t b, int64_t e) {
      bool any = false;
      for (int64_t i = b; i < e; ++i) {
        const int32_t f = made[size_t(i)];
        // A new triangle, or a green pair with a new vertex whose later merge
        // would be poor (a pair born inside a merged pair's split was never
        // checked by the closure: its parent is itself new).
        const int32_t* v = &m.corner_vertex[3 * size_t(f)];
        const bool pair = s.green[f] == 1;  // (a, m, c) and (m, b, c)
        const int32_t q[4] = {v[0], v[1], v[2], pair ? m.corner_vertex[3 * size_t(f) + 4] : -1};
        bool fresh = false, touched = round == 0;
        for (int k = 0; k < 4; ++k)
          if (q[k] >= nv) {
            fresh = true;
            touched = touched || moved[q[k] - nv];
          }
        if (!fresh || !touched) continue;  // an old face, or as it was last round
        double p[4][3];
        for (int k = 0; k < (pair ? 4 : 3); ++k) load_point(m, q[k], p[k]);
        const bool poor = below_floor(p[0], p[1], p[2], s.floor_sin2) ||
                          (pair && poor_merge(p[0], p[1], p[3], p[2], s.floor_sin2));
        if (!poor) continue;
        for (int k = 0; k < 4; ++k)
          if (q[k] >= nv && step[q[k] - nv] < kGuardSteps) {
            __atomic_store_n(&mark[q[k] - nv], uint8_t(1), __ATOMIC_RELAXED);
            any = true;
          }
      }
      if (any) marked.store(true, std::memory_order_relaxed);
    }, 1024);
    if (!marked.load()) break;
    moved.swap(mark);  // every marked vertex moves now
    for (int64_t i = 0; i < ne; ++i) {
      if (!moved[i]) continue;
      float* p = &m.positions[3 * (size_t(nv) + i)];
      if (step[i] == 0) butterfly.emplace(i, std::array<float, 3>{p[0], p[1], p[2]});
      double a[3], b[3], q[3];
      load_point(m, old_cv[next_corner(edges[i])], a);
      load_point(m, old_cv[prev_corner(edges[i])], b);
      guard_point(a, b, butterfly.at(i).data(), ++step[i], q);
      for (int k = 0; k < 3; ++k) p[k] = float(q[k]);
    }
  }
  return std::count_if(step.begin(), step.end(), [](uint8_t x) { return x > 0; });
}

// Closure of a selection (least fixed point, so independent of order):
//  * a normal face with 2 split edges gets its third split (1 -> 4), and so
//    does one with 1 split edge whose green bisection would be a sliver;
//  * a green pair with any split edge or a selected member is merged back
//    into its parent, whose two other edges then split (it is split 1 -> 4).
// On several threads it is worked in rounds: each round looks at the faces whose
// edges the last one split, and a split is marked by whichever thread gets
// there first (an atomic exchange says who, and that thread lists the two
// faces of the edge for the next round). The marks only grow and every face
// is looked at again after each change to its edges, so the rounds end at
// the same least fixed point whatever the order or the threads.
void close_selection(const State& s, const Mesh& m, const std::vector<int32_t>& selected, Plan& plan) {
  const int32_t nf = m.num_faces();
  const uint8_t* green = s.green.data();
  plan.split.assign(3 * size_t(nf), 0);
  plan.merged.assign(nf, 0);
  std::vector<uint8_t> sel(nf, 0);
  uint8_t* split = plan.split.data();
  uint8_t* merged = plan.merged.data();
  auto is_split = [split](int64_t c) { return __atomic_load_n(&split[c], __ATOMIC_RELAXED) != 0; };
  // Sets a flag, saying whether it was set already (an atomic exchange, a
  // locked instruction, only where another thread may set it too).
  const bool threads = s.threads > 1;
  auto set = [threads](uint8_t* flag) {
    if (threads) return __atomic_exchange_n(flag, uint8_t(1), __ATOMIC_RELAXED) != 0;
    return std::exchange(*flag, uint8_t(1)) != 0;
  };
  // Marks the edge at corner c (both its corners); lists its faces when new.
  auto mark = [&](int32_t c, std::vector<int32_t>& next) {
    if (set(&split[c])) return;
    next.push_back(c / 3);
    const int32_t o = s.ct.opposite(c);
    if (o >= 0) {
      __atomic_store_n(&split[o], uint8_t(1), __ATOMIC_RELAXED);
      next.push_back(o / 3);
    }
  };
  // The rules at face f, on the splits as this thread sees them.
  auto close = [&](int32_t f, std::vector<int32_t>& next) {
    if (green[f]) {
      const int32_t first = green[f] == 1 ? f : f - 1;
      if (__atomic_load_n(&merged[first], __ATOMIC_RELAXED)) return;
      bool need = sel[first] || sel[first + 1];
      for (int k = 0; k < 6 && !need; ++k) need = is_split(3 * first + k);
      if (!need || set(&merged[first])) return;
      mark(3 * (first + 1) + 0, next);  // parent edge (b, c)
      mark(3 * first + 1, next);        // parent edge (c, a)
      return;
    }
    const bool x[3] = {is_split(3 * f), is_split(3 * f + 1), is_split(3 * f + 2)};
    const int sc = x[0] + x[1] + x[2];
    if (sc == 2 || (sc == 1 && poor_green(s, m, f, x[0] ? 0 : (x[1] ? 1 : 2))))
      for (int k = 0; k < 3; ++k) mark(3 * f + k, next);
  };
  // Each round's pieces list the next round's faces; the lists are joined
  // in piece order (the order changes no result, only which faces repeat).
  std::vector<int32_t> work;
  auto round = [&](int64_t n, const std::function<void(int64_t, std::vector<int32_t>&)>& step) {
    constexpr int64_t kPiece = 256;
    const int64_t pieces = (n + kPiece - 1) / kPiece;
    std::vector<std::vector<int32_t>> next(static_cast<size_t>(pieces));
    parallel_for_chunks(pieces, s.threads, [&](int64_t b, int64_t e) {
      for (int64_t p = b; p < e; ++p)
        for (int64_t i = p * kPiece; i < std::min(n, (p + 1) * kPiece); ++i) step(i, next[size_t(p)]);
    });
    std::vector<int32_t> joined;
    for (const std::vector<int32_t>& v : next) joined.insert(joined.end(), v.begin(), v.end());
    work.swap(joined);
  };
  auto seed = [&](int32_t f, std::vector<int32_t>& next) {
    if (green[f]) next.push_back(f);
    else for (int k = 0; k < 3; ++k) mark(3 * f + k, next);
  };
  for (int32_t f : selected) sel[f] = 1;
  if (!threads) {
    // One thread: one list, worked from its end (no rounds).
    for (int32_t f : selected) seed(f, work);
    while (!work.empty()) {
      const int32_t f = work.back();
      work.pop_back();
      close(f, work);
    }
  } else {
    round(int64_t(selected.size()), [&](int64_t i, std::vector<int32_t>& next) { seed(selected[size_t(i)], next); });
    while (!work.empty()) {
      const std::vector<int32_t> faces = std::move(work);
      round(int64_t(faces.size()), [&](int64_t i, std::vector<int32_t>& next) { close(faces[size_t(i)], next); });
    }
  }
  // The inner edge of a merged pair disappears with it; the faces made are
  // counted a chunk at a time, and summed in chunk order.
  const int64_t chunks = (int64_t(nf) + kChunk - 1) / kChunk;
  std::vector<int64_t>& made = plan.made_before;
  made.assign(size_t(chunks) + 1, 0);
  auto split_at = [split](int64_t c) { return split[c] != 0; };
  parallel_for_chunks(chunks, s.threads, [&](int64_t b, int64_t e) {
    for (int64_t k = b; k < e; ++k) {
      int64_t tris = 0;
      for (int64_t f = k * kChunk; f < std::min<int64_t>(nf, (k + 1) * kChunk); ++f) {
        if (green[f] == 1 && merged[f]) split[3 * f + 0] = split[3 * (f + 1) + 1] = 0;
        tris += made_of(green, merged, split_at, f);
      }
      made[size_t(k) + 1] = tris;
    }
  });
  for (int64_t k = 0; k < chunks; ++k) made[size_t(k) + 1] += made[size_t(k)];
  plan.triangles = made.back();
}

// The faces an adaptive level makes, in parent order.
struct EmittedFaces {
  Array<int32_t> cv, cw;
  std::vector<int32_t> fg;
  std::vector<uint8_t> green;
  // Per emitted face, the parent it copies unchanged, or -1 (State::Carried).
  std::vector<int32_t> from;
  // Stall detection (when on): the born value of every emitted face — the
  // parent's bend for red children, inherited for kept faces and greens.
  std::vector<float> born;
};

// Writes the faces made of a run of parents into EmittedFaces from face |n|
// on (the positions the closure counted: Plan::made_before).
struct Emitter {
  const Mesh& m;
  bool wedges, groups;
  EmittedFaces& out;
  int64_t n;  // the next face written
  int64_t green_splits = 0, red_splits = 0;
  struct Born {
    bool on = false;
    float red = INFINITY, kept = INFINITY;  // for the parent being emitted
    bool in_red = false;
  } born;

  // Faces [f, e) of the old level, none of them split or green, copied
  // unchanged: what face() makes of each with kept_from = f and born =
  // |kept_born| (per face; null: INFINITY), in bulk (late levels keep
  // nearly every face).
  void copy(int32_t f, int32_t e, const float* kept_born) {
    std::iota(out.from.begin() + n, out.from.begin() + n + (e - f), f);
    if (born.on) {
      if (kept_born) std::copy(kept_born + f, kept_born + e, out.born.begin() + n);
      else std::fill(out.born.begin() + n, out.born.begin() + n + (e - f), INFINITY);
    }
    std::copy(m.corner_vertex.begin() + 3 * size_t(f), m.corner_vertex.begin() + 3 * size_t(e), out.cv.begin() + 3 * n);
    if (wedges)
      std::copy(m.corner_wedge.begin() + 3 * size_t(f), m.corner_wedge.begin() + 3 * size_t(e), out.cw.begin() + 3 * n);
    if (groups) std::copy(m.face_group.begin() + f, m.face_group.begin() + e, out.fg.begin() + n);
    std::fill(out.green.begin() + n, out.green.begin() + n + (e - f), uint8_t(0));
    n += e - f;
  }
  void face(const int32_t v[3], const int32_t w[3], int32_t g, uint8_t gflag, int32_t kept_from = -1) {
    out.from[n] = kept_from;
    if (born.on) out.born[n] = born.in_red ? born.red : born.kept;
    for (int k = 0; k < 3; ++k) {
      out.cv[3 * n + k] = v[k];
      if (wedges) out.cw[3 * n + k] = w[k];
    }
    if (groups) out.fg[n] = g;
    out.green[n] = gflag;
    ++n;
  }
  // A face whose edges opposite local corner k split at mid[k] (-1: not):
  // none -> kept; one -> green bisection; three -> red 1 -> 4.
  // |parent|: the face split (for a kept one's record), or -1.
  void split(const int32_t v[3], const int32_t w[3], const int32_t mid[3], const int32_t mw[3], int32_t g,
             int32_t parent = -1) {
    const int sc = (mid[0] >= 0) + (mid[1] >= 0) + (mid[2] >= 0);
    if (sc == 0) { face(v, w, g, 0, parent); return; }
    if (sc == 1) {
      const int k = mid[0] >= 0 ? 0 : (mid[1] >= 0 ? 1 : 2);
      const int k1 = (k + 1) % 3, k2 = (k + 2) % 3;
      // Parent (a, b, c) = (v[k1], v[k2], v[k]), m on (a, b):
      // first child (a, m, c), second (m, b, c).
      const int32_t v1[3] = {v[k1], mid[k], v[k]}, w1[3] = {w[k1], mw[k], w[k]};
      const int32_t v2[3] = {mid[k], v[k2], v[k]}, w2[3] = {mw[k], w[k2], w[k]};
      face(v1, w1, g, 1);
      face(v2, w2, g, 2);
      ++green_splits;
      return;
    }
    ++red_splits;
    born.in_red = true;
    for (int j = 0; j < 3; ++j) {
      const int j1 = (j + 1) % 3, j2 = (j + 2) % 3;
      int32_t cvj[3], cwj[3];
      cvj[j] = v[j]; cwj[j] = w[j];
      cvj[j1] = mid[j2]; cwj[j1] = mw[j2];
      cvj[j2] = mid[j1]; cwj[j2] = mw[j1];
      face(cvj, cwj, g, 0);
    }
    face(mid, mw, g, 0);
    born.in_red = false;
  }
};

// fmax: the largest θ of each face of this level (for stall detection; may be
// empty when it is off).
void adaptive_level(State& s, Mesh& m, const Plan& plan, const std::vector<float>& fmax, LevelStats& ls) {
  const int32_t nf = m.num_faces(), nv = m.num_vertices();
  const int64_t nc = 3 * int64_t(nf);
  const bool wedges = m.has_wedges();
  const Array<int32_t>& opp = s.ct.opposites();

  // Topology: number the split edges and their wedges in corner order, a
  // chunk of corners at a time (counted, then numbered from the chunk's
  // first numbers). (No wedge numbers where the mesh has no wedges: every
  // vertex is its own.)
  Array<int32_t> evert(nc), ewedge(wedges ? nc : 0);
  std::vector<int32_t> edges;
  std::vector<WedgePair> wedge_src;  // (a, b) per new wedge
  auto wedge_at = [&](int64_t c) { return wedges ? ewedge[c] : -1; };
  struct Numbers {
    int64_t vertices = 0, wedges = 0;
    Numbers operator+(const Numbers& o) const { return {vertices + o.vertices, wedges + o.wedges}; }
  };
  const uint8_t* split = plan.split.data();
  const int32_t* op = opp.data();
  const int32_t* cw_old = wedges ? m.corner_wedge.data() : nullptr;
  // The first corner of a split edge; does it carry the same two wedges on both sides?
  auto numbered = [split, op](int64_t c) { return split[c] && (op[c] < 0 || c < op[c]); };
  auto shared = [cw_old](int64_t c, int64_t o) {
    return cw_old[next_corner(c)] == cw_old[prev_corner(o)] && cw_old[prev_corner(c)] == cw_old[next_corner(o)];
  };
  const int32_t w0 = m.wedge_count();
  const Numbers added = parallel_count_fill(
      nc, s.threads, kChunk,
      [&](int64_t b, int64_t e) {
        // (Every corner -1 first: an edge's second corner may lie in a later chunk.)
        std::fill(evert.begin() + b, evert.begin() + e, -1);
        if (wedges) std::fill(ewedge.begin() + b, ewedge.begin() + e, -1);
        Numbers k;
        for (int64_t c = b; c < e; ++c) {
          if (!numbered(c)) continue;
          ++k.vertices;
          if (wedges) k.wedges += op[c] < 0 || shared(c, op[c]) ? 1 : 2;
        }
        return k;
      },
      [&](const Numbers& total) {
        edges.resize(size_t(total.vertices));
        wedge_src.resize(size_t(total.wedges));
      },
      [&](int64_t b, int64_t e, Numbers at) {
        for (int64_t c = b; c < e; ++c) {
          if (!numbered(c)) continue;
          const int32_t o = op[c], v = nv + int32_t(at.vertices);
          evert[c] = v;
          if (o >= 0) evert[o] = v;
          edges[size_t(at.vertices++)] = int32_t(c);
          if (!wedges) continue;
          ewedge[c] = w0 + int32_t(at.wedges);
          wedge_src[size_t(at.wedges++)] = WedgePair(cw_old[next_corner(c)], cw_old[prev_corner(c)]);
          if (o < 0) continue;
          if (shared(c, o)) {
            ewedge[o] = ewedge[c];
          } else {
            ewedge[o] = w0 + int32_t(at.wedges);
            wedge_src[size_t(at.wedges++)] = WedgePair(cw_old[next_corner(o)], cw_old[prev_corner(o)]);
          }
        }
      });
  const int32_t next_v = nv + int32_t(added.vertices), next_w = w0 + int32_t(added.wedges);
  // Data pass.
  grow_vertices(m, next_v);
  // (A stencil costs tens of ns: a level's last few thousand edges still
  // make pieces for two threads.)
  parallel_for(int64_t(edges.size()), s.threads, [&](int64_t b, int64_t e) {
    std::vector<StencilTerm> terms;
    apply_stencils(m, s.bctx, edges.data() + b, e - b, nv + int32_t(b), terms);
  }, 256);
  // The level's rings go: its connectivity changes below (State::level_rings).
  if (s.bctx.rings == &s.level_rings) s.bctx.rings = nullptr;
  RingTable().swap(s.level_rings);
  if (wedges) {
    const int32_t first = m.num_wedges();
    grow_wedges(m, next_w);
    for (int32_t c = 0; c < nc; ++c)
      if (ewedge[c] >= 0) m.wedge_vertex[ewedge[c]] = evert[c];
    parallel_for(int64_t(wedge_src.size()), s.threads, [&](int64_t b, int64_t e) {
      blend_wedges(m, first + int32_t(b), wedge_src.data() + b, e - b);
    });
  }

  // Topology: emit the new faces in parent order, a chunk of parents at a
  // time, each from where the closure counted the chunks before it end.
  const bool groups = !m.face_group.empty();
  EmittedFaces out;
  // What the next level may reuse (State::Carried).
  State::Carried& carried = s.carried;
  carried.touched.assign(size_t(next_v), 0);
  std::fill(carried.touched.begin() + nv, carried.touched.end(), uint8_t(1));
  // (Old vertices are touched by any of their faces' chunks: the same byte
  // whichever thread stores it.)
  uint8_t* touched = carried.touched.data();
  auto touch = [&](int32_t f) {
    for (int k = 0; k < 3; ++k)
      __atomic_store_n(&touched[m.corner_vertex[3 * size_t(f) + k]], uint8_t(1), __ATOMIC_RELAXED);
  };
  const bool born_on = s.stall > 0 && !fmax.empty();
  auto bend = [&](int32_t f) { return std::isnan(fmax[f]) ? INFINITY : fmax[f]; };
  const int32_t none[3] = {-1, -1, -1};
  const float* kept_born = s.born.empty() ? nullptr : s.born.data();
  const uint8_t* green = s.green.data();
  const uint8_t* merged = plan.merged.data();
  const int32_t* ev = evert.data();
  std::atomic<int64_t> green_splits{0}, red_splits{0}, greens_merged{0};
  std::atomic<bool> miscounted{false};
  const size_t total = size_t(plan.triangles);
  out.cv.resize(3 * total);
  if (wedges) out.cw.resize(3 * total);
  if (groups) out.fg.resize(total);
  out.green.resize(total);
  out.from.resize(total);
  if (born_on) out.born.resize(total);
  auto fill = [&](int64_t b, int64_t e_chunk, int64_t at, int64_t end) {
    Emitter em{m, wedges, groups, out, at, 0, 0, {}};
    em.born.on = born_on;
    int64_t merges = 0;
    for (int32_t f = int32_t(b); f < int32_t(e_chunk); ++f) {
      // A run of faces neither green nor split: copied as they are.
      int32_t e = f;
      // (Split edges have vertex numbers >= 0, the others -1: all three are
      // -1 when their bitwise and is negative.)
      while (e < e_chunk && green[e] == 0 && (ev[3 * size_t(e)] & ev[3 * size_t(e) + 1] & ev[3 * size_t(e) + 2]) < 0)
        ++e;
      if (e > f) {
        em.copy(f, e, kept_born);
        f = e - 1;
        continue;
      }
      const uint8_t gflag = green[f];
      if (gflag == 2) continue;
      const int32_t g = m.group_of(f);
      if (em.born.on) {
        em.born.kept = kept_born ? kept_born[f] : INFINITY;
        em.born.red = bend(f);
        // A merged pair's parent is split: all its faces are its children.
        if (gflag == 1 && merged[f]) em.born.kept = em.born.red = std::max(bend(f), bend(f + 1));
      }
      if (gflag == 1) {
        const int32_t f2 = f + 1;
        if (!merged[f]) {
          for (int32_t h : {f, f2}) {
            int32_t v[3], w[3];
            for (int k = 0; k < 3; ++k) { v[k] = m.corner_vertex[3 * h + k]; w[k] = m.wedge_of(3 * h + k); }
            em.face(v, w, m.group_of(h), h == f ? 1 : 2, h);
          }
          continue;
        }
        touch(f);
        touch(f2);
        // Merge back: parent (a, b, c) with the old midpoint m on (a, b).
        ++merges;
        ++em.red_splits;
        const int32_t a = m.corner_vertex[3 * f], bb = m.corner_vertex[3 * f2 + 1], c = m.corner_vertex[3 * f + 2];
        const int32_t wa = m.wedge_of(3 * f), wb = m.wedge_of(3 * f2 + 1), wc = m.wedge_of(3 * f + 2);
        const int32_t m2 = m.corner_vertex[3 * f + 1], w2 = m.wedge_of(3 * f + 1);
        const int32_t m0 = evert[3 * f2 + 0], w0 = wedge_at(3 * f2 + 0);
        const int32_t m1 = evert[3 * f + 1], w1 = wedge_at(3 * f + 1);
        // Children of the regular split; the halves (a, m) and (m, b) may split.
        const int32_t F0v[3] = {a, m2, m1}, F0w[3] = {wa, w2, w1};
        const int32_t F0m[3] = {-1, -1, evert[3 * f + 2]}, F0mw[3] = {-1, -1, wedge_at(3 * f + 2)};
        const int32_t F1v[3] = {m2, bb, m0}, F1w[3] = {w2, wb, w0};
        const int32_t F1m[3] = {-1, -1, evert[3 * f2 + 2]}, F1mw[3] = {-1, -1, wedge_at(3 * f2 + 2)};
        const int32_t F2v[3] = {m1, m0, c}, F2w[3] = {w1, w0, wc};
        const int32_t F3v[3] = {m0, m1, m2}, F3w[3] = {w0, w1, w2};
        em.split(F0v, F0w, F0m, F0mw, g);
        em.split(F1v, F1w, F1m, F1mw, g);
        em.split(F2v, F2w, none, none, g);
        em.split(F3v, F3w, none, none, g);
        continue;
      }
      int32_t v[3], w[3], mid[3], mw[3];
      for (int k = 0; k < 3; ++k) {
        v[k] = m.corner_vertex[3 * f + k];
        w[k] = m.wedge_of(3 * f + k);
        mid[k] = evert[3 * f + k];
        mw[k] = wedges ? ewedge[3 * f + k] : mid[k];
      }
      if (mid[0] >= 0 || mid[1] >= 0 || mid[2] >= 0) touch(f);
      em.split(v, w, mid, mw, g, f);
    }
    if (em.n != end) miscounted.store(true, std::memory_order_relaxed);
    green_splits += em.green_splits;
    red_splits += em.red_splits;
    greens_merged += merges;
  };
  parallel_for_chunks(int64_t(plan.made_before.size()) - 1, s.threads, [&](int64_t b, int64_t e) {
    for (int64_t k = b; k < e; ++k)
      fill(k * kChunk, std::min<int64_t>(nf, (k + 1) * kChunk), plan.made_before[size_t(k)],
           plan.made_before[size_t(k) + 1]);
  });
  if (miscounted.load()) throw std::logic_error("adaptive level: the faces made disagree with their count");
  ls.green_splits += green_splits.load();
  ls.red_splits += red_splits.load();
  ls.greens_merged += greens_merged.load();
  note_peak(s, m, vbytes(evert) + vbytes(ewedge) + vbytes(out.cv) + vbytes(out.cw) + vbytes(out.fg) +
                      vbytes(out.green) + vbytes(plan.split) + vbytes(plan.merged) + vbytes(out.from));
  m.corner_vertex.swap(out.cv);
  if (wedges) m.corner_wedge.swap(out.cw);
  if (groups) m.face_group.swap(out.fg);
  s.green.swap(out.green);
  s.born.swap(out.born);
  carried.kept_from.swap(out.from);
  carried.theta.swap(s.theta);
  s.theta_current = false;
  carried.valid = s.carry && !s.input_split;
  // The old table is build(old, false)'s unless the input's split vertices.
  const bool renumber = s.incremental_table && !s.input_split;
  s.input_split = false;
  if (s.floor_sin2 > 0 && next_v > nv) ls.vertices_guarded = guard_slivers(s, m, out.cv, edges, nv, carried.kept_from);
  ls.vertices_added = next_v - nv;
  // Only the corners round changed faces are matched again; the rest of the
  // table is renumbered (the same table as a full build, which a test checks).
  if (!(renumber && s.ct.update(m, carried.kept_from, carried.touched, s.threads)))
    s.ct.build(m, false, s.threads, false, s.bctx.wide);
}

// ---------------------------------------------------------------------------
// Attributes that are recomputed rather than interpolated.

// Wedges made unit length a block at a time: their vectors gathered into
// arrays of x, y and z, the arithmetic in vector registers (unit_vectors,
// orthonormal_vectors), the results written back one wedge at a time.
constexpr int kUnitBlock = 256;

// o = n / |n| in single precision for |count| vectors n given as arrays of
// their x, y and z (double), |n| in |len|.
ITEAS_WIDE_CLONES void unit_vectors(const double* __restrict x, const double* __restrict y,
                                    const double* __restrict z, int count, float* __restrict ox,
                                    float* __restrict oy, float* __restrict oz, double* __restrict len) {
  for (int i = 0; i < count; ++i) {
    const double l = std::sqrt(x[i] * x[i] + y[i] * y[i] + z[i] * z[i]);
    len[i] = l;
    ox[i] = float(x[i] / l);
    oy[i] = float(y[i] / l);
    oz[i] = float(z[i] / l);
  }
}

// The same for tangents t, first made orthogonal to the unit normals n when
// there are any (|nx| not null): t - (t . n) n.
ITEAS_WIDE_CLONES void orthonormal_vectors(const double* __restrict x, const double* __restrict y,
                                           const double* __restrict z, const double* __restrict nx,
                                           const double* __restrict ny, const double* __restrict nz, int count,
                                           float* __restrict ox, float* __restrict oy, float* __restrict oz,
                                           double* __restrict len) {
  if (!nx) {
    unit_vectors(x, y, z, count, ox, oy, oz, len);
    return;
  }
  for (int i = 0; i < count; ++i) {
    const double d = x[i] * nx[i] + y[i] * ny[i] + z[i] * nz[i];
    const double a = x[i] - d * nx[i], b = y[i] - d * ny[i], c = z[i] - d * nz[i];
    const double l = std::sqrt(a * a + b * b + c * c);
    len[i] = l;
    ox[i] = float(a / l);
    oy[i] = float(b / l);
    oz[i] = float(c / l);
  }
}

}  // namespace

Array<int32_t> smoothing_groups(const Mesh& m, int normal_channel, int threads) {
  const Channel& nch = m.channels[size_t(normal_channel)];
  // Smoothing groups: wedges of one vertex with bit-identical (interpolated)
  // normals share a normal, so UV seams stay smooth and hard edges stay hard.
  // A group is named by its first wedge (below: how they are found). (A
  // hash map of (vertex, normal) keys took 60 % of dragon_vrip_res3's
  // uniform level 2, in its allocations.)
  const int32_t nw = m.num_wedges();
  const int32_t nv = m.num_vertices();
  const int32_t* wv = m.wedge_vertex.data();
  const float* wn = nch.data.data();
  // A wedge's bucket: its vertex, or nv for a vertex out of range (grouped
  // among themselves by vertex and normal all the same).
  auto bucket = [wv, nv](int32_t w) { return uint32_t(wv[w]) < uint32_t(nv) ? wv[w] : nv; };
  auto same = [wv, wn](int32_t x, int32_t y) {
    return wv[x] == wv[y] && std::memcmp(wn + 3 * size_t(x), wn + 3 * size_t(y), 3 * sizeof(float)) == 0;
  };
  // A wedge alone at its vertex (nearly every wedge) is its own group. The
  // others are listed by vertex (in wedge order within a vertex) and
  // compared with their vertex's wedges before them; a vertex with many
  // wedges sorts them by normal instead. (Before, every wedge was sorted by
  // vertex and every vertex's run looked at: Avocado level 4, 88,291
  // wedges of which 1,376 share their vertex, 0.20 -> 0.10 ms.)
  // count[b]: bucket b's wedges; then, for a bucket of several, ~ the place
  // in |order| of its next wedge.
  std::vector<int32_t> count(size_t(nv) + 1, 0);
  Array<int32_t> group(static_cast<size_t>(nw));  // every entry written below
  for (int32_t w = 0; w < nw; ++w) ++count[size_t(bucket(w))];
  std::vector<int32_t> start;  // the runs of the buckets of several wedges, in bucket order
  int32_t listed = 0;
  for (int32_t b = 0; b <= nv; ++b) {
    if (count[size_t(b)] < 2) continue;
    start.push_back(listed);
    listed += count[size_t(b)];
    count[size_t(b)] = ~start.back();
  }
  start.push_back(listed);
  Array<int32_t> order(static_cast<size_t>(listed));
  for (int32_t w = 0; w < nw; ++w) {
    int32_t& at = count[size_t(bucket(w))];
    if (at >= 0) {
      group[size_t(w)] = w;
      continue;
    }
    order[size_t(~at)] = w;
    --at;  // ~(at + 1)
  }
  constexpr int32_t kCompareAll = 16;  // wedges of one vertex compared pairwise up to this many
  parallel_for(int64_t(start.size()) - 1, threads, [&](int64_t r0, int64_t r1) {
    for (int64_t r = r0; r < r1; ++r) {
      int32_t* run = order.data() + start[r];
      const int32_t k = start[r + 1] - start[r];
      if (k <= kCompareAll) {
        for (int32_t i = 0; i < k; ++i) {
          const int32_t w = run[i];
          int32_t g = w;
          for (int32_t j = 0; j < i; ++j)
            if (same(run[j], w)) { g = group[size_t(run[j])]; break; }
          group[size_t(w)] = g;
        }
        continue;
      }
      // By vertex, normal bits, then wedge: equal keys are adjacent, the
      // first of each the group's first wedge.
      auto key = [wv, wn](int32_t w) {
        std::array<uint32_t, 4> q;
        q[0] = uint32_t(wv[w]);
        std::memcpy(q.data() + 1, wn + 3 * size_t(w), 3 * sizeof(float));
        return q;
      };
      std::sort(run, run + k, [&key](int32_t x, int32_t y) {
        const auto kx = key(x), ky = key(y);
        return kx != ky ? kx < ky : x < y;
      });
      for (int32_t i = 0; i < k; ++i)
        group[size_t(run[i])] = (i > 0 && same(run[i - 1], run[i])) ? group[size_t(run[i - 1])] : run[i];
    }
  }, 256);
  return group;
}

Array<double> smoothing_group_sums(const Mesh& m, const Array<int32_t>& group, int threads) {
  // The sums in face order, on one thread (a group's faces may lie
  // anywhere); zeroed on all.
  const int32_t nw = m.num_wedges();
  Array<double> acc(3 * size_t(nw));
  parallel_for(int64_t(acc.size()), threads, [&](int64_t b, int64_t e) {
    std::fill(acc.data() + b, acc.data() + e, 0.0);
  }, 16384);
  const int32_t nf = m.num_faces();
  const float* p = m.positions.data();
  const int32_t* cv = m.corner_vertex.data();
  const int32_t* cwd = m.corner_wedge.data();
  double* sum = acc.data();
  // Twice the area times the unit normal of face f (area-weighted sums).
  auto face_normal = [p, cv](int32_t f, double* n) {
    const float* a = p + 3 * size_t(cv[3 * f]);
    const float* b = p + 3 * size_t(cv[3 * f + 1]);
    const float* c = p + 3 * size_t(cv[3 * f + 2]);
    const double u[3] = {double(b[0]) - a[0], double(b[1]) - a[1], double(b[2]) - a[2]};
    const double v[3] = {double(c[0]) - a[0], double(c[1]) - a[1], double(c[2]) - a[2]};
    n[0] = u[1] * v[2] - u[2] * v[1];
    n[1] = u[2] * v[0] - u[0] * v[2];
    n[2] = u[0] * v[1] - u[1] * v[0];
  };
  auto add = [sum](int32_t g, const double* n) {
    double* t = sum + 3 * size_t(g);
    for (int i = 0; i < 3; ++i) t[i] += n[i];
  };
  // Four faces at a time: where they are the four children of a split face
  // (uniform_level's layout: child j keeps the parent's corner j, p_j, and
  // has the midpoints m_{j+2} and m_{j+1}; the centre child is (m0, m1, m2)),
  // each midpoint's group takes its three children's normals in registers
  // and is stored once. Every group still takes its faces' normals in face
  // order, so the sums have the same bits, with half the loads and stores
  // and no chain of additions through memory (Avocado level 4, 174,592
  // faces, one thread: 0.76-0.78 -> 0.62-0.64 ms). Any other four faces
  // (green pairs, faces kept, other layouts) are added one corner at a time.
  int32_t f = 0;
  for (; f + 4 <= nf; f += 4) {
    int32_t g[12];
    for (int i = 0; i < 12; ++i) g[i] = group[size_t(cwd[3 * size_t(f) + i])];
    double n[4][3];
    for (int j = 0; j < 4; ++j) face_normal(f + j, n[j]);
    const int32_t p0 = g[0], p1 = g[4], p2 = g[8], m2 = g[1], m1 = g[2], m0 = g[5];
    // A vertex in two of the six places (the children's faces alike, but
    // not one face's children): p1's normal would be added before m1's
    // first, and p2's before m2's first two, out of face order. Any other
    // pair keeps the order (p0's normal comes first anyway, and p_j's
    // before p_k's), or makes the faces its adds would move degenerate:
    // their normals are zero, and change no sum.
    bool split = (g[3] == m2) & (g[11] == m2) & (g[6] == m1) & (g[10] == m1) & (g[7] == m0) & (g[9] == m0);
    split &= (p1 != m1) & (p2 != m2);
    if (!split) {
      for (int i = 0; i < 12; ++i) add(g[i], n[i / 3]);
      continue;
    }
    add(p0, n[0]);
    add(p1, n[1]);
    add(p2, n[2]);
    // m2: children 0, 1 and 3; m1: 0, 2 and 3; m0: 1, 2 and 3.
    double* t = sum + 3 * size_t(m2);
    for (int i = 0; i < 3; ++i) t[i] = ((t[i] + n[0][i]) + n[1][i]) + n[3][i];
    t = sum + 3 * size_t(m1);
    for (int i = 0; i < 3; ++i) t[i] = ((t[i] + n[0][i]) + n[2][i]) + n[3][i];
    t = sum + 3 * size_t(m0);
    for (int i = 0; i < 3; ++i) t[i] = ((t[i] + n[1][i]) + n[2][i]) + n[3][i];
  }
  for (; f < nf; ++f) {
    double n[3];
    face_normal(f, n);
    for (int k = 0; k < 3; ++k) add(group[size_t(cwd[3 * size_t(f) + k])], n);
  }
  return acc;
}

void recompute_normals(Mesh& m, int threads) {
  int ni = -1;
  for (size_t i = 0; i < m.channels.size(); ++i)
    if (m.channels[i].kind == ChannelKind::kNormal && m.channels[i].components == 3) { ni = int(i); break; }
  if (ni < 0 || !m.has_wedges()) return;
  Channel& nch = m.channels[size_t(ni)];
  const int32_t nw = m.num_wedges();
  const Array<int32_t> group = smoothing_groups(m, ni, threads);
  const Array<double> acc = smoothing_group_sums(m, group, threads);
  // Each wedge's group's sum made unit length (a block at a time, the same
  // bits as one at a time); a group without area keeps its interpolated
  // normal, made unit length.
  const double* sums = acc.data();
  const int32_t* gr = group.data();
  float* const normals = nch.data.data();
  parallel_for(nw, threads, [&](int64_t b, int64_t e) {
    alignas(64) double x[kUnitBlock], y[kUnitBlock], z[kUnitBlock], len[kUnitBlock];
    alignas(64) float ox[kUnitBlock], oy[kUnitBlock], oz[kUnitBlock];
    for (int64_t w0 = b; w0 < e; w0 += kUnitBlock) {
      const int n = int(std::min<int64_t>(kUnitBlock, e - w0));
      for (int i = 0; i < n; ++i) {
        const double* s = sums + 3 * size_t(gr[w0 + i]);
        x[i] = s[0];
        y[i] = s[1];
        z[i] = s[2];
      }
      unit_vectors(x, y, z, n, ox, oy, oz, len);
      for (int i = 0; i < n; ++i) {
        float* out = normals + 3 * size_t(w0 + i);
        if (len[i] > 0) {
          out[0] = ox[i];
          out[1] = oy[i];
          out[2] = oz[i];
        } else {
          const double l2 = std::sqrt(double(out[0]) * out[0] + double(out[1]) * out[1] + double(out[2]) * out[2]);
          if (l2 > 0) for (int k = 0; k < 3; ++k) out[k] = float(out[k] / l2);
        }
      }
    }
  }, 8192);
}

// Tangents made orthogonal to the (recomputed) normal and unit length, on
// all threads (each wedge on its own); w, the handedness, made -1 or 1.
void orthogonalise_tangents(Mesh& m, int threads) {
  const int ni = m.find_channel("NORMAL");
  const bool normal = ni >= 0 && m.channels[ni].components == 3;
  const int32_t nw = m.num_wedges();
  for (Channel& ch : m.channels) {
    if (ch.kind != ChannelKind::kTangent || ch.components < 3) continue;
    // Locals: the stores may alias anything the captures reach.
    const int nc = ch.components;
    float* const td = ch.data.data();
    const float* const nd = normal ? m.channels[ni].data.data() : nullptr;
    // A block at a time (orthonormal_vectors: the same bits as one at a time).
    parallel_for(nw, threads, [nc, td, nd](int64_t b, int64_t e) {
      alignas(64) double x[kUnitBlock], y[kUnitBlock], z[kUnitBlock], len[kUnitBlock];
      alignas(64) double nx[kUnitBlock], ny[kUnitBlock], nz[kUnitBlock];
      alignas(64) float ox[kUnitBlock], oy[kUnitBlock], oz[kUnitBlock];
      for (int64_t w0 = b; w0 < e; w0 += kUnitBlock) {
        const int n = int(std::min<int64_t>(kUnitBlock, e - w0));
        for (int i = 0; i < n; ++i) {
          const float* t = td + size_t(w0 + i) * nc;
          x[i] = t[0];
          y[i] = t[1];
          z[i] = t[2];
        }
        if (nd)
          for (int i = 0; i < n; ++i) {
            const float* q = nd + 3 * size_t(w0 + i);
            nx[i] = q[0];
            ny[i] = q[1];
            nz[i] = q[2];
          }
        orthonormal_vectors(x, y, z, nd ? nx : nullptr, ny, nz, n, ox, oy, oz, len);
        for (int i = 0; i < n; ++i) {
          float* t = td + size_t(w0 + i) * nc;
          if (len[i] > 0) {
            t[0] = ox[i];
            t[1] = oy[i];
            t[2] = oz[i];
          }
          if (nc == 4) t[3] = t[3] < 0 ? -1.0f : 1.0f;
        }
      }
    }, 8192);
  }
}

namespace {

// Largest theta of each face over its non-sharp edges; NaN when none.
// On all threads, with selects instead of branches (which edges count
// follows no pattern).
void face_max_theta(const State& s, const Mesh& m, std::vector<float>& out) {
  const int32_t nf = m.num_faces();
  out.resize(size_t(nf));
  parallel_for(nf, s.threads, [&](int64_t b, int64_t e) {
    const float* theta = s.theta.data();
    const uint8_t* sharp = s.sharp.data();
    float* o = out.data();
    // An edge's θ is >= 0 or NaN: -1 stands for an edge that does not count.
    const float nan = std::numeric_limits<float>::quiet_NaN();
    for (int64_t f = b; f < e; ++f) {
      float t[3];
      for (int k = 0; k < 3; ++k) {
        const float x = theta[3 * f + k];
        t[k] = x == x && !sharp[3 * f + k] ? x : -1.0f;
      }
      const float a = t[0] > t[1] ? t[0] : t[1];
      const float best = a > t[2] ? a : t[2];
      o[f] = best < 0.0f ? nan : best;
    }
  }, 4096);
}

// How far splitting the edge at corner c would move the surface: the
// distance from its Butterfly point to its midpoint along the edge's normal
// (the sum of its faces' unit normals). A tangential shift, as beside a
// boundary of a flat patch, leaves the surface where it is. Without a usable
// normal (zero-area faces, a full fold) the whole distance counts.
// |p|: the edge's Butterfly point; |f1|, |f2|: the unit normals of the faces
// of c and of its opposite (face_normals: NaN for a zero-area face), f2 null
// at a boundary.
float edge_deviation(const Mesh& m, int32_t c, const float* p, const double* f1, const double* f2) {
  const float* a = &m.positions[3 * size_t(m.corner_vertex[next_corner(c)])];
  const float* b = &m.positions[3 * size_t(m.corner_vertex[prev_corner(c)])];
  double d[3], n[3] = {0, 0, 0};
  for (int j = 0; j < 3; ++j) d[j] = double(p[j]) - 0.5 * (double(a[j]) + double(b[j]));
  const double whole = std::sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]);
  for (const double* f : {f1, f2}) {
    if (!f) continue;
    if (std::isnan(f[0])) return float(whole);
    for (int j = 0; j < 3; ++j) n[j] += f[j];
  }
  const double nl = std::sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2]);
  if (!(nl > 1e-6)) return float(whole);
  return float(std::fabs(d[0] * n[0] + d[1] * n[1] + d[2] * n[2]) / nl);
}

// The adaptive selection of a level (SPEC §2.3 and the extensions of
// RefineOptions), in face order. A face's deviation is the largest of its
// edges'. Every verdict depends on the face alone, so the selection is the
// same for any thread count.
void select_faces(State& s, const Mesh& m, const RefineOptions& o, double T, const std::vector<float>& fmax,
                  std::vector<int32_t>& selected, LevelStats& ls) {
  enum : uint8_t { kLeft, kSelected, kStalled, kWithinTolerance, kOverFlatLimit, kJudgeTolerance, kJudgeFlat };
  const int32_t nf = m.num_faces();
  const int64_t nc = 3 * int64_t(nf);
  const bool stall = s.stall > 0 && !s.born.empty();
  std::vector<uint8_t> verdict(nf);
  std::atomic<bool> deviations{false};
  // A face's verdict from its largest θ, without branches (whether a face
  // bends more than T follows no pattern):
  //  * NaN: no bend to judge (no interior edge with a normal on both sides);
  //  * not beyond T: judged against the flat limit when there is one;
  //  * beyond T but still bending as much as when its parent was split:
  //    stalled (Butterfly is not smoothing it: a fold, a cusp or the
  //    ripples around one);
  //  * else selected, or judged against the tolerance when there is one.
  auto judge = [&](auto stalls, int64_t b, int64_t e) {
    // Locals: the byte stores may alias anything in memory, and what the
    // loop read through its captures was reloaded after each of them.
    const float* bend = fmax.data();
    const float* born = stalls ? s.born.data() : nullptr;
    uint8_t* out = verdict.data();
    const int up = o.select == Select::kAbove;
    const double limit = T, ratio = s.stall;
    const int yes = s.tolerance > 0 ? kJudgeTolerance : kSelected;  // beyond T
    const int no = s.flat_limit > 0 ? kJudgeFlat : kLeft;            // not beyond T
    uint8_t any = 0;
    // In integer arithmetic on the comparisons: GCC made branches of the
    // same selects written with ?: (kLeft is 0).
    for (int64_t f = b; f < e; ++f) {
      const float t = bend[f];
      const int beyond = (up & int(t > limit)) | ((1 - up) & int(t < limit));  // 0 for NaN
      const int stalled = stalls ? int(double(t) >= ratio * double(born[f])) : 0;
      const int bent_v = yes + (kStalled - yes) * stalled;
      const int unbent_v = no * int(t == t);  // NaN: kLeft
      const uint8_t v = uint8_t(unbent_v + (bent_v - unbent_v) * beyond);
      out[f] = v;
      any |= uint8_t(v >= kJudgeTolerance);
    }
    if (any) deviations.store(true, std::memory_order_relaxed);
  };
  parallel_for(nf, s.threads, [&](int64_t b, int64_t e) {
    if (stall) judge(std::true_type(), b, e);
    else judge(std::false_type(), b, e);
  }, 512);
  if (deviations.load()) {
    // Each edge once (from its first corner), for the faces that need it.
    const int32_t* opp = s.ct.opposites().data();
    // -1: not computed (a deviation is never negative).
    std::vector<float> dev(nc, -1.0f);
    State::Carried& carried = s.carried;
    const bool reuse = carried.valid && !carried.deviation.empty();
    const int32_t* cv = m.corner_vertex.data();
    // Per face, which of its corners' edges this level measures (bit k:
    // corner 3f + k): the edge's first corner (the smaller one, or a
    // boundary's), with no deviation carried, beside a face that needs one.
    // Listed here, where the carried deviations are copied, so that the pass
    // below skips the faces with nothing to measure (after the first levels
    // nearly all) instead of testing every corner, and no thread reads what
    // another writes. Carried corners are counted (measured).
    std::vector<uint8_t> todo(nf);
    note_peak(s, m, vbytes(dev) + vbytes(verdict) + vbytes(todo));
    std::atomic<int64_t> measured{0};
    {
      // (The angles' rule, CarriedAngles, a face at a time.)
      const CarriedAngles edges = reuse ? carried.edges() : CarriedAngles();
      const float* old = reuse ? carried.deviation.data() : nullptr;
      parallel_for(nf, s.threads, [&](int64_t b, int64_t e) {
        // Copies: the byte stores of the list may alias anything, and what
        // the loop read through its captures was reloaded after each of them
        // (bunny.off at the defaults, one thread: 2-3 % of the run).
        float* const out = dev.data();
        const uint8_t* const vd = verdict.data();
        uint8_t* const list = todo.data();
        const int32_t* const op = opp;
        const int32_t* const corners = cv;
        const float* const before = old;
        const CarriedAngles rule = edges;  // (no kept_from when nothing is carried)
        int64_t n = 0;
        for (int64_t f = b; f < e; ++f) {
          unsigned kept = 0;
          const int64_t from = rule.kept_from ? rule.carried_corners(corners, f, kept) : -1;
          const unsigned here = unsigned(vd[f] >= kJudgeTolerance);
          unsigned bits = 0;
          for (int k = 0; k < 3; ++k) {
            const int32_t c = int32_t(3 * f + k);
            if (kept >> k & 1) {  // (none for a face not kept)
              const float d = before[3 * from + k];
              out[c] = d;
              if (d >= 0.0f) { ++n; continue; }
            }
            // Without a branch: which uncarried corners are their edge's
            // first and need a deviation follows no pattern. (At a boundary
            // the other face is c's own.)
            const int32_t oc = op[c];
            const unsigned first = unsigned(oc < 0) | unsigned(oc > c);
            const unsigned need = here | unsigned(vd[(oc < 0 ? c : oc) / 3] >= kJudgeTolerance);
            bits |= (first & need) << k;
          }
          list[f] = uint8_t(bits);
        }
        measured.fetch_add(n, std::memory_order_relaxed);
      }, 512);
    }
    // Where most edges are measured afresh (the first levels), the rings of
    // the extraordinary vertices first, each walked once and its rule's
    // points summed for every edge round it (build_level_rings), instead of
    // walking a vertex's fan once for each of its edges. On later levels,
    // where a few regions changed, the walks for those edges cost less than
    // rings for every vertex.
    if (s.level_rings_on && 2 * measured.load() <= nc) {
      build_level_rings(m, s.ct, s.bctx.vclass, &s.green, s.level_rings, s.threads, s.bctx.wide);
      s.bctx.rings = &s.level_rings;
      note_peak(s, m, vbytes(dev) + vbytes(verdict) + vbytes(todo));
    }
    parallel_for(nf, s.threads, [&](int64_t b, int64_t e) {
      // A block of edges at a time: their Butterfly points in one call
      // (as the data pass makes them), their faces' normals in another
      // (vectorised), then their deviations. Each edge is measured by the
      // thread of the face listing it, which writes both its corners (no
      // other thread reads them in this pass).
      constexpr int kBlock = 256;
      int32_t list[kBlock], faces[2 * kBlock];
      float points[3 * kBlock];
      double nx[2 * kBlock], ny[2 * kBlock], nz[2 * kBlock];
      int n = 0;
      auto flush = [&] {
        if (n == 0) return;
        butterfly_points(s.bctx, list, n, m.positions.data(), points);
        for (int i = 0; i < n; ++i) {
          const int32_t c = list[i], oc = opp[c];
          faces[2 * i] = c / 3;
          faces[2 * i + 1] = oc >= 0 ? oc / 3 : c / 3;  // (at a boundary, not read)
        }
        face_normals(m, faces, 2 * n, nx, ny, nz);
        float* const dv = dev.data();
        for (int i = 0; i < n; ++i) {
          const int32_t c = list[i], oc = opp[c];
          const double f1[3] = {nx[2 * i], ny[2 * i], nz[2 * i]};
          const double f2[3] = {nx[2 * i + 1], ny[2 * i + 1], nz[2 * i + 1]};
          const float d = edge_deviation(m, c, &points[3 * i], f1, oc >= 0 ? f2 : nullptr);
          dv[c] = d;
          if (oc >= 0) dv[oc] = d;
        }
        n = 0;
      };
      const uint8_t* const listed = todo.data();
      for (int32_t f = int32_t(b); f < int32_t(e); ++f) {
        const unsigned bits = listed[f];
        if (bits == 0) continue;  // after the first levels nearly every face
        // Room for a face's three stores without a branch (the spare ones
        // are written over by the next entries).
        if (n > kBlock - 3) flush();
        for (int k = 0; k < 3; ++k) {
          list[n] = 3 * f + k;
          n += int(bits >> k & 1);
        }
      }
      flush();
    }, 512);
    parallel_for(nf, s.threads, [&](int64_t b, int64_t e) {
      const float* d3 = dev.data();
      uint8_t* out = verdict.data();
      const double tolerance = s.tolerance, flat_limit = s.flat_limit;  // locals, as in judge
      for (int64_t f = b; f < e; ++f) {
        const uint8_t v = out[f];
        const double d = std::max({d3[3 * f], d3[3 * f + 1], d3[3 * f + 2]});
        // Integer arithmetic, as in judge (kLeft is 0).
        const int tol = v == kJudgeTolerance, flat = v == kJudgeFlat;
        const int within = int(d <= tolerance), over = int(d > flat_limit);
        const int judged = tol * (kSelected + (kWithinTolerance - kSelected) * within) + flat * kOverFlatLimit * over;
        out[f] = uint8_t(v + ((tol | flat) * (judged - v)));
      }
    }, 512);
    if (s.deviations_seen && *s.deviations_seen) (*s.deviations_seen)(dev.data(), nc);
    carried.deviation.swap(dev);
  } else {
    std::vector<float>().swap(s.carried.deviation);
  }
  s.carried.valid = false;  // until adaptive_level says how the next level derives from this one
  std::vector<int32_t>().swap(s.carried.kept_from);
  std::vector<uint8_t>().swap(s.carried.touched);
  // Counted and listed without branches (the verdicts follow no pattern).
  int64_t stalled = 0, within = 0, over = 0, n = 0;
  selected.resize(size_t(nf));
  int32_t* list = selected.data();
  const uint8_t* v = verdict.data();
  for (int32_t f = 0; f < nf; ++f) {
    stalled += v[f] == kStalled;
    within += v[f] == kWithinTolerance;
    over += v[f] == kOverFlatLimit;
    list[n] = f;
    n += (v[f] == kSelected) | (v[f] == kOverFlatLimit);
  }
  selected.resize(size_t(n));
  ls.faces_stalled += stalled;
  ls.faces_within_tolerance += within;
  ls.faces_over_flat_limit += over;
}

// Uniform levels add a vertex per edge, and the count of edges follows from
// the faces and the boundary: E = (3F + B) / 2, then F -> 4F, B -> 2B. The
// vertex arrays get their final size at once, for the levels the budget lets
// run: each level's growth had copied the positions so far to a new array
// (bunny-npm level 3: 23 µs, serial, before the last level; long enough for
// the idle worker to fall asleep) and held both copies at its peak.
void reserve_uniform_vertices(Mesh& m, const RefineOptions& o, int64_t boundary_edges) {
  int64_t v = m.num_vertices(), f = m.num_faces(), b = boundary_edges;
  for (int level = 1; level <= o.levels && 4 * f <= o.max_triangles; ++level) {
    v += uniform_edges(f, b);
    f *= 4;
    b *= 2;
  }
  if (v <= m.num_vertices() || v > (int64_t(1) << 31)) return;
  m.positions.reserve(3 * size_t(v));
  for (VertexChannel& vc : m.vertex_channels) vc.data.reserve(3 * size_t(v));
}

}  // namespace

int64_t mesh_bytes(const Mesh& m) {
  int64_t b = vbytes(m.positions) + vbytes(m.corner_vertex) + vbytes(m.corner_wedge) + vbytes(m.face_group) +
              vbytes(m.wedge_vertex);
  for (const Channel& c : m.channels) b += vbytes(c.data);
  for (const VertexChannel& c : m.vertex_channels) b += vbytes(c.data);
  return b;
}

// When a uniform job puts its faces in spatial order (see refine_mesh): the
// least scatter of the input's face order, and the fewest faces for a job
// of one level.
constexpr double kScatteredOrder = 0.005;
constexpr int64_t kSortOneLevelFaces = 49152;

RefineResult refine_mesh(Mesh& m, const RefineOptions& options, const RefineHooks& hooks, RefineStats* st) {
  // The budget never past what 32-bit corner indices can number (as
  // parse_options caps it too).
  RefineOptions o = options;
  o.max_triangles = std::min(o.max_triangles, kMaxTriangles);
  RefineStats& stats = *st;
  stats = RefineStats();
  auto now = [&] { return hooks.now_ms ? hooks.now_ms() : 0.0; };
  auto cancelled = [&] { return hooks.cancel && hooks.cancel->load(std::memory_order_relaxed); };
  auto progress = [&](int level, const char* phase, double fr) { if (hooks.progress) hooks.progress(level, phase, fr); };

  State s;
  // One thread for the whole call while the CPUs are far apart, if even its
  // last level starts from few faces (threads_for; a level gives at most 4
  // faces per face). Not per level: the levels before a large one, split
  // between the threads, leave each thread's part in its own cache, and the
  // large level ran 6 % slower after small ones on one thread. The results
  // never depend on it.
  int64_t last_level_faces = m.num_faces();
  for (int l = 1; l < o.levels && last_level_faces < kSmallStepFaces; ++l) last_level_faces *= 4;
  s.threads = hooks.choose_threads ? threads_for(last_level_faces, resolve_threads(o.threads))
                                   : resolve_threads(o.threads);
  const PagePopulateThreads populate_threads(s.threads);
  // Wedges without channels carry nothing: drop them (every vertex its own wedge).
  if (m.channels.empty()) { Array<int32_t>().swap(m.corner_wedge); std::vector<int32_t>().swap(m.wedge_vertex); }
  if (std::all_of(m.face_group.begin(), m.face_group.end(), [](int32_t g) { return g == 0; }))
    std::vector<int32_t>().swap(m.face_group);

  // Uniform levels split every face's work by index: a thread's share of
  // each loop is a range of faces, and their children at the next level.
  // Faces in a scanner's or an exporter's order put neighbours far apart in
  // it, and each thread then reads vertices, opposites and points the other
  // has just written (a line on the other core costs a round trip). In a
  // spatial order each share is a region of the surface. Only for jobs whose
  // last level starts from kSmallStepFaces faces or more, so that small jobs
  // do not pay for the sort; never by the thread count, so the output is the
  // same on any number of threads; and only when a level will run (the
  // budget allows the first), so an unrefined output keeps the input's order.
  // Only for faces in a scattered order (face_order_scatter): an order that
  // already walks the surface (an exporter's, a refined mesh's) beats the
  // Morton order, and the sort made such jobs slower on one thread and on
  // two (uniform, no statistics: BrainStem level 2 43.7 -> 48.4 ms on one
  // thread, bun_zipper decoded from Draco level 1 2.6 -> 3.6 ms; scatter
  // 0.0001-0.0017 there against 0.012-0.061 for the scans it helps). A single
  // level pays for the sort only on large meshes: kitten (20,000 faces)
  // level 1 took 0.69 ms unsorted against 0.90 ms sorted on one thread and
  // 0.71 against 0.80 ms on two, fertility refined once (36,000 faces)
  // 1.61 against 1.87 ms, while bun_zipper (69,451) took 5.5 unsorted
  // against 4.0 ms sorted (performance log).
  if (hooks.spatial_order && o.mode == Mode::kUniform && o.levels >= 1 && last_level_faces >= kSmallStepFaces &&
      (o.levels >= 2 || m.num_faces() >= kSortOneLevelFaces) && int64_t(m.num_faces()) * 4 <= o.max_triangles &&
      face_order_scatter(m) >= kScatteredOrder)
    order_faces_spatially(m, s.threads);

  const double t0 = now();
  stats.triangles_in = m.num_faces();
  stats.vertices_in = m.wedge_count();
  // The uniform path reads its first rings from the fans the table records.
  s.bctx.wide = hooks.wide;
  // On several threads, the input's triangle quality (statistics) is taken
  // on the other one while the table sorts the corners by vertex, a serial
  // step (it reads the positions and corners alone, which a split of
  // non-manifold vertices, later, leaves the same for every face).
  const bool statistics = hooks.statistics || o.mode != Mode::kUniform;
  const bool quality_beside = statistics && s.threads > 1;
  stats.topology = s.ct.build(
      m, true, s.threads, o.mode == Mode::kUniform && !hooks.force_adaptive_path, s.bctx.wide,
      quality_beside ? std::function<void()>([&] { stats.quality_before = triangle_quality(m, 1); }) : nullptr);
  s.ring_limit = m.num_vertices();
  s.input_split = stats.topology.split_vertices > 0;
  s.carry = hooks.carry;
  s.incremental_table = hooks.incremental_table;
  s.level_rings_on = hooks.level_rings;
  s.deviations_seen = &hooks.deviations;
  stats.ms_topology = now() - t0;
  const double crease = o.crease_angle;
  const bool adaptive = o.mode != Mode::kUniform;
  if (!adaptive && !hooks.force_adaptive_path) reserve_uniform_vertices(m, o, stats.topology.boundary_edges);

  // Threshold and the "before" picture, on the input.
  // (Uniform refinement reports the mean θ as its T; the benchmark switch
  // skips all of it.)
  double T_input = 0;
  // On two threads a uniform job without creases, whose first level is
  // small, takes the input's angles beside that level
  // (first_level_beside_input), or after the loop when no first level runs
  // (cancelled, or no room for it). A large first level gains from both
  // threads itself (bun_zipper, 69,451 faces, level 1 with statistics:
  // 8.4-8.5 ms with both on each, 8.6-9.2 ms side by side).
  // Only where the points' array has room for the level's new points
  // (reserve_uniform_vertices: one per edge), so that it never moves.
  const bool uniform_path = !adaptive && !hooks.force_adaptive_path;
  const size_t points_kept =
      3 * size_t(m.num_vertices() + uniform_edges(m.num_faces(), stats.topology.boundary_edges));
  bool angles_beside = statistics && uniform_path && crease <= 0 && s.threads > 1 && m.num_faces() > 0 &&
                       m.num_faces() < kSmallStepFaces && m.positions.capacity() >= points_kept;
  if (statistics && !angles_beside) {
    current_angles(s, m);  // nothing carried into the input
    // The input's summary once: with the mean for T (uniform jobs, and the
    // default threshold) the edges above it are then counted alone.
    const bool mean = o.mode == Mode::kUniform || o.threshold.kind == ThresholdSpec::Kind::kMean;
    const InputAngles in = input_angles(m, s.ct, s.theta, crease, s.threads, mean ? nullptr : &o.threshold);
    stats.before = in.before;
    T_input = in.threshold;
  }
  if (statistics && !quality_beside) stats.quality_before = triangle_quality(m, s.threads);
  stats.threshold = T_input;
  if (adaptive || hooks.force_adaptive_path) s.green.assign(m.num_faces(), 0);
  // The summary of the mesh as it is: from the angles when current, else
  // from the faces' normals, through the corner table or, after a last
  // uniform level that made none, the parent's (State::split_from).
  auto summary = [&](double T, QualitySummary* quality) {
    if (!s.split_from.empty()) return summarize_split_angles(m, s.split_from, T, crease, s.threads, quality);
    return summarize_angles(m, s.ct, s.theta_current ? &s.theta : nullptr, T, crease, s.threads, quality);
  };
  if (adaptive) {
    s.stall = effective_stall_ratio(o);
    const double diagonal = bounding_box(m).diagonal();
    s.tolerance = effective_tolerance(o) * diagonal;
    s.flat_limit = effective_flat_limit(o) * diagonal;
    // (0.1 % above half: the reported minimum comes from a polynomial atan2
    // accurate to 1e-5 rad, which must not read a guarded triangle as under.)
    const double floor_rad = 0.5005 * stats.quality_before.min_angle * (M_PI / 180.0);
    s.floor_sin2 = std::sin(floor_rad) * std::sin(floor_rad);
  }
  note_peak(s, m, 0);

  const double t1 = now();
  int levels_done = 0;
  stats.stopped_by = "max_levels";
  std::vector<float> fmax;
  std::vector<int32_t> selected;
  AngleSummary last_after;
  // A uniform level makes four faces of each: is there room for another?
  auto no_room = [&] { return int64_t(m.num_faces()) * 4 > o.max_triangles; };
  QualitySummary fused_quality;
  bool quality_done = false;  // fused_quality describes the mesh as it is
  for (int level = 1; level <= o.levels; ++level) {
    if (cancelled()) { stats.stopped_by = "cancelled"; break; }
    const double lt0 = now();
    progress(level, "analyse", 0.0);
    LevelStats ls;
    ls.level = level;
    analyse(s, m, o, !uniform_path || crease > 0);
    if (!adaptive) {
      ls.threshold = T_input;
      if (no_room()) { stats.stopped_by = "budget"; stats.budget_clamped = true; break; }
      if (cancelled()) { stats.stopped_by = "cancelled"; break; }
      progress(level, "refine", 0.0);
      if (uniform_path && angles_beside) {
        const InputAngles in =
            first_level_beside_input(s, m, ls, level < o.levels, level < o.levels, statistics, points_kept);
        stats.before = in.before;
        T_input = stats.threshold = ls.threshold = in.threshold;
        angles_beside = false;
      } else if (uniform_path) {
        uniform_level(s, m, ls, crease <= 0, level < o.levels, level < o.levels, statistics);
      } else {
        selected.resize(m.num_faces());
        std::iota(selected.begin(), selected.end(), 0);
        Plan plan;
        close_selection(s, m, selected, plan);
        ls.faces_selected = m.num_faces();
        adaptive_level(s, m, plan, fmax, ls);
      }
    } else {
      const double T = o.threshold_scope == Scope::kLevel && o.mode == Mode::kIteas
                           ? compute_threshold(o.threshold, m, s.ct, s.theta, crease, s.threads)
                           : T_input;
      ls.threshold = T;
      if (level == 1) stats.threshold = T;
      face_max_theta(s, m, fmax);
      select_faces(s, m, o, T, fmax, selected, ls);
      if (selected.empty()) { stats.stopped_by = ls.faces_stalled > 0 ? "stalled" : "converged"; break; }
      Plan plan;
      close_selection(s, m, selected, plan);
      bool clamped = false;
      if (plan.triangles > o.max_triangles) {
        // Budget: the most bent faces first; the largest prefix that fits.
        clamped = true;
        std::stable_sort(selected.begin(), selected.end(), [&](int32_t a, int32_t b) { return fmax[a] > fmax[b]; });
        size_t lo = 0, hi = selected.size();
        std::vector<int32_t> prefix;
        while (lo < hi) {
          const size_t mid = (lo + hi + 1) / 2;
          prefix.assign(selected.begin(), selected.begin() + mid);
          close_selection(s, m, prefix, plan);
          if (plan.triangles <= o.max_triangles) lo = mid;
          else hi = mid - 1;
        }
        if (lo == 0) { stats.stopped_by = "budget"; stats.budget_clamped = true; break; }
        selected.resize(lo);
        std::sort(selected.begin(), selected.end());
        close_selection(s, m, selected, plan);
      }
      if (cancelled()) { stats.stopped_by = "cancelled"; break; }
      progress(level, "refine", 0.0);
      ls.faces_selected = int64_t(selected.size());
      adaptive_level(s, m, plan, fmax, ls);
      if (clamped) { stats.budget_clamped = true; stats.stopped_by = "budget"; }
    }
    ++levels_done;
    // After an adaptive level the angles are the next level's anyway (nearly
    // all carried): taken now, the statistics count the θ the selection sees.
    // A uniform level makes every edge new and the next one needs no angles
    // without creases: one single-precision pass instead.
    if (statistics && !uniform_path) {
      current_angles(s, m);
      note_peak(s, m, 0);
    }
    // A uniform level's summary computes each face's normal from its points
    // (adaptive levels read the angles they carry): on the last one the
    // triangle quality after refinement comes from the same gathered points
    // (the mesh's positions do not change after it). A uniform level is the
    // last when the levels asked for are done or the budget leaves no room
    // for another; a level after it (none runs) would clear the flag.
    const bool fuse = statistics && !s.theta_current && (level == o.levels || no_room());
    const AngleSummary after = statistics ? summary(ls.threshold, fuse ? &fused_quality : nullptr) : AngleSummary();
    quality_done = fuse;
    last_after = after;
    ls.triangles_after = m.num_faces();
    ls.mean_theta_after = after.mean;
    ls.max_theta_after = after.max;
    ls.ms = now() - lt0;
    stats.levels.push_back(ls);
    progress(level, "refine", 1.0);
    if (stats.stopped_by == "budget") break;
  }
  if (stats.stopped_by == "max_levels" && o.mode == Mode::kFixed && levels_done < o.levels) stats.stopped_by = "converged";
  if (angles_beside) {  // no first level ran (cancelled, or no room): the input is unchanged
    current_angles(s, m);
    const InputAngles in = input_angles(m, s.ct, s.theta, crease, s.threads);
    stats.before = in.before;
    T_input = stats.threshold = in.threshold;
  }

  if (levels_done > 0) {
    recompute_normals(m, s.threads);
    orthogonalise_tangents(m, s.threads);
  }
  stats.ms_refine = now() - t1;
  // The last level's summary already describes the output when T is the same.
  if (!stats.levels.empty() && stats.levels.back().threshold == stats.threshold && last_after.edges > 0)
    stats.after = last_after;
  else if (statistics)
    stats.after = summary(stats.threshold, nullptr);
  if (statistics) stats.quality_after = quality_done ? fused_quality : triangle_quality(m, s.threads);
  stats.triangles_out = m.num_faces();
  stats.vertices_out = m.wedge_count();
  stats.uniform_triangles = stats.triangles_in;
  for (int i = 0; i < levels_done; ++i) stats.uniform_triangles *= 4;
  stats.reduction_percent = stats.uniform_triangles > 0
                                ? 100.0 * (1.0 - double(stats.triangles_out) / double(stats.uniform_triangles))
                                : 0.0;
  stats.peak_bytes = s.peak;
  return stats.stopped_by == "cancelled" ? RefineResult::kCancelled : RefineResult::kOk;
}

}  // namespace iteas
