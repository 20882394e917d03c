#include "core/butterfly.h"

#include <cmath>

#include "core/parallel.h"

namespace iteas {

void mark_sharp_edges(const CornerTable& ct, const std::vector<float>* theta, double crease_angle,
                      std::vector<uint8_t>& sharp, int threads) {
  const int32_t nc = ct.num_corners();
  sharp.resize(nc);
  parallel_for(nc, threads, [&](int64_t b, int64_t e) {
    for (int64_t c = b; c < e; ++c)
      sharp[c] = ct.opposite(int32_t(c)) < 0 || (crease_angle > 0 && theta && (*theta)[c] >= crease_angle);
  });
}

void classify_vertices(const Mesh& mesh, const CornerTable& ct, const std::vector<uint8_t>& sharp,
                       VertexClass& out, int threads) {
  const int32_t nv = mesh.num_vertices();
  out.valence.assign(nv, 0);
  out.complete.assign(nv, 0);
  parallel_for(nv, threads, [&](int64_t b, int64_t e) {
    for (int64_t v = b; v < e; ++v) {
      const int32_t first = ct.vertex_corner(int32_t(v));
      if (first < 0) continue;
      int32_t faces = 0, c = first;
      bool closed = false, has_sharp = false;
      while (true) {
        ++faces;
        if (sharp[prev_corner(c)]) has_sharp = true;  // outgoing edge v -> next
        const int32_t s = ct.swing_right(c);
        if (s < 0) break;
        if (s == first) { closed = true; break; }
        if (faces > ct.num_corners()) break;  // defensive: malformed fan
        c = s;
      }
      out.valence[v] = closed ? faces : faces + 1;
      // The extraordinary rules need a ring of 3 or more (a closed fan of two
      // faces, from a doubled triangle, would get weights that do not sum to 1).
      out.complete[v] = closed && !has_sharp && faces >= 3;
    }
  });
}

void discount_green_apices(const Mesh& mesh, const std::vector<uint8_t>& green, VertexClass& vclass) {
  for (size_t f = 0; f < green.size(); ++f)
    if (green[f] == 2) --vclass.valence[mesh.corner_vertex[3 * f + 2]];
}

namespace {

inline uint8_t green_of(const ButterflyContext& ctx, int32_t corner) {
  return ctx.green && !ctx.green->empty() ? (*ctx.green)[corner / 3] : 0;
}

// The vertex at corner x as the parent of a green pair sees it: the midpoint
// corner of each child stands for the parent's opposite vertex.
inline int32_t vtx(const ButterflyContext& ctx, int32_t x) {
  const uint8_t g = green_of(ctx, x);
  if (g == 1 && x % 3 == 1) return ctx.mesh->corner_vertex[x + 3];  // b of the second child
  if (g == 2 && x % 3 == 0) return ctx.mesh->corner_vertex[x - 3];  // a of the first child
  return ctx.mesh->corner_vertex[x];
}

// Is the edge opposite corner x one of the parent's own edges, (c, a) or (b, c)?
inline bool parent_edge(const ButterflyContext& ctx, int32_t x) {
  const uint8_t g = green_of(ctx, x);
  return (g == 1 && x % 3 == 1) || (g == 2 && x % 3 == 0);
}

inline void add(std::vector<StencilTerm>& out, int32_t v, double w) { out.push_back({v, w}); }

// s_j for valence K (Zorin et al. 1996): K = 3 and 4 special, K >= 5 by formula.
// Tabulated once for K < 64; larger valences compute on the fly.
constexpr int kMaxTabulated = 64;
struct WeightTable {
  double w[kMaxTabulated][kMaxTabulated];
  WeightTable() {
    for (int K = 3; K < kMaxTabulated; ++K)
      for (int j = 0; j < K; ++j) {
        if (K == 3) w[K][j] = j == 0 ? 5.0 / 12.0 : -1.0 / 12.0;
        else if (K == 4) w[K][j] = j == 0 ? 3.0 / 8.0 : (j == 2 ? -1.0 / 8.0 : 0.0);
        else w[K][j] = (0.25 + std::cos(2.0 * M_PI * j / K) + 0.5 * std::cos(4.0 * M_PI * j / K)) / K;
      }
  }
};
const double* extraordinary_weights(int K) {
  static const WeightTable table;  // immutable after construction
  return K >= 3 && K < kMaxTabulated ? table.w[K] : nullptr;
}

// Extraordinary rule at vertex v (corner x0 at v, whose next vertex is the
// other endpoint of the edge): 3/4 v + sum_j s_j e_j over the ring in order.
void extraordinary(const ButterflyContext& ctx, int32_t x0, int32_t valence, double scale,
                   std::vector<StencilTerm>& out) {
  const std::vector<int32_t>& cv = ctx.mesh->corner_vertex;
  const int K = valence;
  add(out, cv[x0], 0.75 * scale);
  const double* w = extraordinary_weights(K);
  int32_t x = x0;
  for (int j = 0; j < K; ++j) {
    // The bisecting edge (c, m) of a green pair with this vertex as apex is
    // not in the parent's ring: skip it (classify discounted it from K).
    while (green_of(ctx, x) == 2 && x % 3 == 2) x = ctx.ct->swing_right(x);
    const double s = w ? w[j] : (0.25 + std::cos(2.0 * M_PI * j / K) + 0.5 * std::cos(4.0 * M_PI * j / K)) / K;
    if (s != 0.0) add(out, cv[next_corner(x)], s * scale);
    x = ctx.ct->swing_right(x);
  }
}

// The point on the far side of the edge opposite corner |x| (across a sharp
// edge it is replaced by the parallelogram completion of x's own triangle).
void plain_wing(const ButterflyContext& ctx, int32_t x, double w, std::vector<StencilTerm>& out) {
  const int32_t o = ctx.ct->opposite(x);
  if (o >= 0 && !(*ctx.sharp)[x]) {
    add(out, vtx(ctx, o), w);
  } else {
    add(out, vtx(ctx, next_corner(x)), w);
    add(out, vtx(ctx, prev_corner(x)), w);
    add(out, vtx(ctx, x), -w);
  }
}

// A wing of an edge whose face is |x|'s face. When that edge is a parent edge
// of a green pair (|parent_view|), the wings are the parent's: across its
// other parent edge (reached through the sibling), and across (a, b), where
// the neighbour is already split, by parallelogram completion a + b - c.
void wing(const ButterflyContext& ctx, int32_t x, bool parent_view, double w, std::vector<StencilTerm>& out) {
  const uint8_t g = green_of(ctx, x);
  if (parent_view && g != 0) {
    const int32_t k = x % 3, f0 = (g == 1 ? x / 3 : x / 3 - 1) * 3;  // first corner of the first child
    const std::vector<int32_t>& cv = ctx.mesh->corner_vertex;
    const int32_t a = cv[f0], b = cv[f0 + 4], c = cv[f0 + 2];
    if ((g == 1 && k == 2) || (g == 2 && k == 2)) {  // across (a, m) or (m, b): across (a, b)
      add(out, a, w); add(out, b, w); add(out, c, -w);
      return;
    }
    if (g == 1 && k == 0) { plain_wing(ctx, f0 + 3, w, out); return; }  // across (b, c)
    if (g == 2 && k == 1) { plain_wing(ctx, f0 + 1, w, out); return; }  // across (c, a)
  }
  plain_wing(ctx, x, w, out);
}

// Along a boundary or crease curve: the curve neighbour of v other than
// |other|, or -1 when v has other than two sharp edges.
int32_t curve_neighbour(const ButterflyContext& ctx, int32_t v, int32_t other) {
  const std::vector<int32_t>& cv = ctx.mesh->corner_vertex;
  const std::vector<uint8_t>& sharp = *ctx.sharp;
  const int32_t first = ctx.ct->vertex_corner(v);
  int32_t found = -1, count = 0, c = first, guard = 0;
  while (c >= 0) {
    if (sharp[prev_corner(c)]) {  // outgoing edge v -> next(c)
      ++count;
      if (cv[next_corner(c)] != other) found = cv[next_corner(c)];
    }
    const int32_t s = ctx.ct->swing_right(c);
    if (s < 0) {  // open fan: its last incoming edge prev(c) -> v is a boundary
      ++count;
      if (cv[prev_corner(c)] != other) found = cv[prev_corner(c)];
      break;
    }
    if (s == first || ++guard > ctx.ct->num_corners()) break;
    c = s;
  }
  return count == 2 ? found : -1;
}

void four_point(const ButterflyContext& ctx, int32_t v1, int32_t v2, std::vector<StencilTerm>& out) {
  add(out, v1, 9.0 / 16.0);
  add(out, v2, 9.0 / 16.0);
  const int32_t p = curve_neighbour(ctx, v1, v2);
  if (p >= 0) add(out, p, -1.0 / 16.0);
  else { add(out, v1, -2.0 / 16.0); add(out, v2, 1.0 / 16.0); }
  const int32_t q = curve_neighbour(ctx, v2, v1);
  if (q >= 0) add(out, q, -1.0 / 16.0);
  else { add(out, v2, -2.0 / 16.0); add(out, v1, 1.0 / 16.0); }
}

}  // namespace

void butterfly_stencil(const ButterflyContext& ctx, int32_t c, std::vector<StencilTerm>& out) {
  out.clear();
  const std::vector<int32_t>& cv = ctx.mesh->corner_vertex;
  const CornerTable& ct = *ctx.ct;
  const int32_t v1 = cv[next_corner(c)], v2 = cv[prev_corner(c)];
  const int32_t d = ct.opposite(c);
  if (d < 0 || (*ctx.sharp)[c]) {
    four_point(ctx, v1, v2, out);
    return;
  }
  const bool c1 = ctx.vclass.complete[v1], c2 = ctx.vclass.complete[v2];
  const bool pf = parent_edge(ctx, c), pg = parent_edge(ctx, d);
  const int32_t k1 = ctx.vclass.valence[v1], k2 = ctx.vclass.valence[v2];
  // Corner at v1 whose next vertex is v2 is next(c); at v2 whose next is v1: next(d).
  if (c1 && c2) {
    if (k1 == 6 && k2 == 6) {
      const double w = ctx.tension;
      add(out, v1, 0.5 - w);
      add(out, v2, 0.5 - w);
      add(out, vtx(ctx, c), 0.125 + 2 * w);
      add(out, vtx(ctx, d), 0.125 + 2 * w);
      wing(ctx, prev_corner(c), pf, -1.0 / 16.0 - w, out);  // across (a1, v1)
      wing(ctx, next_corner(c), pf, -1.0 / 16.0 - w, out);  // across (v2, a1)
      wing(ctx, prev_corner(d), pg, -1.0 / 16.0 - w, out);
      wing(ctx, next_corner(d), pg, -1.0 / 16.0 - w, out);
      if (w > 0) {
        // 10-point: the ring neighbours of v1 and v2 straight across from the
        // edge (three steps round a valence-6 ring).
        int32_t x = next_corner(c), y = next_corner(d);
        for (int j = 0; j < 3; ++j) { x = ct.swing_right(x); y = ct.swing_right(y); }
        add(out, cv[next_corner(x)], w);
        add(out, cv[next_corner(y)], w);
      }
      return;
    }
    if (k1 != 6 && k2 != 6) {
      extraordinary(ctx, next_corner(c), k1, 0.5, out);
      extraordinary(ctx, next_corner(d), k2, 0.5, out);
    } else if (k1 != 6) {
      extraordinary(ctx, next_corner(c), k1, 1.0, out);
    } else {
      extraordinary(ctx, next_corner(d), k2, 1.0, out);
    }
    return;
  }
  if (c1) { extraordinary(ctx, next_corner(c), k1, 1.0, out); return; }
  if (c2) { extraordinary(ctx, next_corner(d), k2, 1.0, out); return; }
  add(out, v1, 0.5);
  add(out, v2, 0.5);
  add(out, vtx(ctx, c), 0.125);
  add(out, vtx(ctx, d), 0.125);
  wing(ctx, prev_corner(c), pf, -1.0 / 16.0, out);
  wing(ctx, next_corner(c), pf, -1.0 / 16.0, out);
  wing(ctx, prev_corner(d), pg, -1.0 / 16.0, out);
  wing(ctx, next_corner(d), pg, -1.0 / 16.0, out);
}

}  // namespace iteas
