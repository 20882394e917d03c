#include "core/mesh.h"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstdlib>
#include <type_traits>

#if defined(__linux__)
#include <sys/mman.h>
#include <unistd.h>

#include <mutex>
#endif

#include "core/parallel.h"

#if defined(__linux__)
extern "C" char end;  // the end of the program's data (end(3))
#endif

namespace iteas {

#if defined(__linux__)
namespace {

// Stretches of the main heap (between the end of the program's data and the
// program break) that prepare_pages has found or made resident. A process that refines one
// mesh after another gets the same blocks back from its allocator run after
// run, and asking the kernel again each time (mincore, a system call of about
// 1 µs on this kind of virtual machine) was a tenth of a small level. Pages
// of the main heap leave only when the break comes down (trimming) or when
// the process says so (forget_resident_memory, after malloc_trim): the ranges
// are dropped whenever the break is not where it was when they were recorded.
// Blocks elsewhere (mapped ones, other threads' arenas) are asked about
// every time, as before. A wrong answer costs only speed (pages then fault
// one by one, or a resident block is walked), never correctness.
class ResidentRanges {
 public:
  bool covers(uintptr_t b, uintptr_t e) {
    std::lock_guard<std::mutex> lock(mu_);
    if (!current()) return false;
    for (int i = 0; i < n_; ++i)
      if (lo_[i] <= b && e <= hi_[i]) return true;
    return false;
  }
  void add(uintptr_t b, uintptr_t e) {
    std::lock_guard<std::mutex> lock(mu_);
    current();
    // Merge with every range it overlaps or touches, keep the rest.
    int k = 0;
    for (int i = 0; i < n_; ++i) {
      if (hi_[i] < b || e < lo_[i]) {
        lo_[k] = lo_[i];
        hi_[k] = hi_[i];
        ++k;
        continue;
      }
      b = std::min(b, lo_[i]);
      e = std::max(e, hi_[i]);
    }
    n_ = k;
    if (n_ == kMax) n_ = 0;  // full: start over
    lo_[n_] = b;
    hi_[n_] = e;
    ++n_;
  }
  void forget() {
    std::lock_guard<std::mutex> lock(mu_);
    n_ = 0;
  }
  // Is [b, e) in the main heap (brk memory) as it is now?
  bool in_heap(uintptr_t b, uintptr_t e) const { return b >= base_ && e <= brk_now(); }

 private:
  static uintptr_t brk_now() { return reinterpret_cast<uintptr_t>(sbrk(0)); }  // glibc: no system call
  // False (and the ranges dropped) when the break has moved since they were recorded.
  bool current() {
    const uintptr_t now = brk_now();
    if (now == brk_) return true;
    brk_ = now;
    n_ = 0;
    return false;
  }
  static constexpr int kMax = 32;
  std::mutex mu_;
  // The heap starts above the program's data (its end is the linker's |end|).
  const uintptr_t base_ = reinterpret_cast<uintptr_t>(&end);
  uintptr_t brk_ = 0;
  int n_ = 0;
  uintptr_t lo_[kMax] = {}, hi_[kMax] = {};
};

ResidentRanges& resident() {
  static ResidentRanges* r = new ResidentRanges();  // never destroyed: used by allocations at exit
  return *r;
}

// Threads that fault in a large array's pages (PagePopulateThreads).
thread_local int tl_populate_threads = 1;

// MADV_POPULATE_WRITE over [b, e) (page aligned), in populate_parts() parts
// of whole 2 MB stretches, one per thread.
void populate(uintptr_t b, uintptr_t e) {
#if defined(MADV_POPULATE_WRITE)
  const int parts = inside_parallel_for() ? 1 : populate_parts(e - b, tl_populate_threads);
  if (parts <= 1) {
    madvise(reinterpret_cast<void*>(b), e - b, MADV_POPULATE_WRITE);
    return;
  }
  auto cut = [&](int64_t p) {
    if (p == parts) return e;
    return std::max(b, (b + (e - b) / uintptr_t(parts) * uintptr_t(p)) & ~(uintptr_t(kHugePageBytes) - 1));
  };
  parallel_for_chunks(parts, parts, [&](int64_t p0, int64_t p1) {
    for (int64_t p = p0; p < p1; ++p) {
      const uintptr_t lo = cut(p), hi = cut(p + 1);
      if (hi > lo) madvise(reinterpret_cast<void*>(lo), hi - lo, MADV_POPULATE_WRITE);
    }
  });
#else
  (void)b;
  (void)e;
#endif
}

#if defined(MADV_POPULATE_WRITE)
// Faults in the absent pages of [b, e) (page aligned): mincore over the
// whole range, a batch at a time, then populate() for each run of absent
// pages. A resident gap of up to kGapPages pages inside a run is walked with
// it (about 140 ns a small page) rather than costing another call (about
// 1 us). A batch the kernel does not answer for counts as absent.
void populate_absent(uintptr_t b, uintptr_t e) {
  constexpr uintptr_t kPage = 4096, kBatchPages = 1024, kGapPages = 8;
  unsigned char v[kBatchPages];
  uintptr_t run_b = 0, run_e = 0;  // the run being gathered (none: run_e == 0)
  for (uintptr_t at = b; at < e; at += kBatchPages * kPage) {
    const uintptr_t to = std::min(e, at + kBatchPages * kPage);
    const size_t n = (to - at) / kPage;
    if (mincore(reinterpret_cast<void*>(at), to - at, v) != 0) std::fill(v, v + n, 0);
    for (size_t i = 0; i < n; ++i) {
      if (v[i] & 1) continue;
      const uintptr_t page = at + i * kPage;
      if (run_e != 0 && page - run_e <= kGapPages * kPage) {
        run_e = page + kPage;
        continue;
      }
      if (run_e != 0) populate(run_b, run_e);
      run_b = page;
      run_e = page + kPage;
    }
  }
  if (run_e != 0) populate(run_b, run_e);
}
#endif

}  // namespace
#endif

PagePopulateThreads::PagePopulateThreads(int threads) {
#if defined(__linux__)
  previous_ = tl_populate_threads;
  tl_populate_threads = resolve_threads(threads);
#else
  (void)threads;
  previous_ = 1;
#endif
}

PagePopulateThreads::~PagePopulateThreads() {
#if defined(__linux__)
  tl_populate_threads = previous_;
#endif
}

int populate_parts(size_t bytes, int threads) {
  if (threads <= 1 || bytes < kPopulatePartsFrom) return 1;
  return int(std::min<size_t>(size_t(threads), bytes / kHugePageBytes));
}

void forget_resident_memory() {
#if defined(__linux__)
  resident().forget();
#endif
}

void prepare_pages(void* p, size_t bytes) {
#if defined(__linux__)
  constexpr uintptr_t kPage = 4096, kHuge = kHugePageBytes;
  if (bytes < kPrefaultBytes) return;
  const uintptr_t lo = reinterpret_cast<uintptr_t>(p), hi = lo + bytes;
#if defined(MADV_HUGEPAGE)
  // The whole 2 MB stretches of the block (which starts on a 2 MB boundary
  // when it is that large); advice only, errors ignored.
  if (bytes >= kHuge) {
    const uintptr_t b = (lo + kHuge - 1) & ~(kHuge - 1), e = hi & ~(kHuge - 1);
    if (e > b) madvise(reinterpret_cast<void*>(b), e - b, MADV_HUGEPAGE);
  }
#endif
#if defined(MADV_POPULATE_WRITE)
  // Every page of the block will be written: fault them all in with one call
  // instead of one trap per page (Linux 5.14+; older kernels say EINVAL and
  // the pages fault on first write as before).
  // Pages already resident (memory the allocator kept) are left alone:
  // walking them costs more than it saves (9 MB of small pages: 325 us to
  // walk, 2 us to ask about). So every page is asked about, and only the runs
  // of absent ones are faulted in. Asking about the last 64 pages alone took
  // a block for resident when it was carved from a free heap chunk whose end
  // had been written and the rest never, and 1,550 to 1,960 of a 9 MB
  // array's 2,304 pages then faulted one by one (tests/corner_table_test.cpp).
  const uintptr_t b = (lo + kPage - 1) & ~(kPage - 1), e = hi & ~(kPage - 1);
  if (e <= b) return;
  // Blocks of the main heap already known resident are not asked about.
  ResidentRanges& known = resident();
  const bool heap = known.in_heap(b, e);
  if (heap && known.covers(b, e)) return;
  populate_absent(b, e);
  if (heap) known.add(b, e);
#endif
#else
  (void)p;
  (void)bytes;
#endif
}

int32_t Mesh::add_wedge(int32_t vertex) {
  wedge_vertex.push_back(vertex);
  for (Channel& ch : channels) ch.data.resize(ch.data.size() + ch.components, 0.0f);
  return num_wedges() - 1;
}

int Mesh::find_channel(const std::string& name) const {
  for (size_t i = 0; i < channels.size(); ++i)
    if (channels[i].name == name) return static_cast<int>(i);
  return -1;
}

double Aabb::diagonal() const {
  double s = 0;
  for (int k = 0; k < 3; ++k) s += double(hi[k] - lo[k]) * double(hi[k] - lo[k]);
  return std::sqrt(s);
}

Aabb bounding_box(const Mesh& mesh) {
  Aabb box;
  const int32_t n = mesh.num_vertices();
  if (n == 0) return box;
  for (int k = 0; k < 3; ++k) box.lo[k] = box.hi[k] = mesh.positions[k];
  for (int32_t v = 1; v < n; ++v)
    for (int k = 0; k < 3; ++k) {
      box.lo[k] = std::min(box.lo[k], mesh.positions[3 * v + k]);
      box.hi[k] = std::max(box.hi[k], mesh.positions[3 * v + k]);
    }
  return box;
}

int64_t drop_degenerate_faces(Mesh& mesh) {
  const int32_t nf = mesh.num_faces();
  int32_t out = 0;
  for (int32_t f = 0; f < nf; ++f) {
    const int32_t* v = &mesh.corner_vertex[3 * f];
    if (v[0] == v[1] || v[1] == v[2] || v[2] == v[0]) continue;
    for (int k = 0; k < 3; ++k) {
      mesh.corner_vertex[3 * out + k] = mesh.corner_vertex[3 * f + k];
      if (mesh.has_wedges()) mesh.corner_wedge[3 * out + k] = mesh.corner_wedge[3 * f + k];
    }
    if (!mesh.face_group.empty()) mesh.face_group[out] = mesh.face_group[f];
    ++out;
  }
  mesh.corner_vertex.resize(3 * size_t(out));
  if (mesh.has_wedges()) mesh.corner_wedge.resize(3 * size_t(out));
  if (!mesh.face_group.empty()) mesh.face_group.resize(out);
  return nf - out;
}

namespace {
// Bit i of x (x < 32) moved to bit 3i: the Morton code of a cell is
// kSpread[x] | kSpread[y] << 1 | kSpread[z] << 2.
struct Spread {
  uint32_t bits[32];
  constexpr Spread() : bits() {
    for (uint32_t x = 0; x < 32; ++x)
      for (int i = 0; i < 5; ++i) bits[x] |= ((x >> i) & 1u) << (3 * i);
  }
};
constexpr Spread kSpread;
}  // namespace

void order_faces_spatially(Mesh& mesh, int threads) {
  const int32_t nf = mesh.num_faces(), nv = mesh.num_vertices();
  if (nf < 2 || nv == 0) return;
  // A grid of 2^bits cells a side with about as many cells as faces, at
  // most 32 a side (one counting pass over 32,768 cells): a surface crosses
  // a small part of them, and the faces of a cell stay in their order.
  int bits = 2;
  while (bits < 5 && (int64_t(1) << (3 * bits)) < nf) ++bits;
  const size_t cells = size_t(1) << (3 * bits);
  const Aabb box = bounding_box(mesh);
  const float top = float((1 << bits) - 1);
  float lo[3], scale[3];
  for (int k = 0; k < 3; ++k) {
    lo[k] = box.lo[k];
    const float extent = box.hi[k] - box.lo[k];
    scale[k] = extent > 0.0f ? float(1 << bits) / extent : 0.0f;  // a flat box: one layer of cells
  }
  // The work is cut into parts, one a thread, of at least 8,192 faces: part
  // p counts and places the p-th range of the vertices and of the faces, and
  // the places come from counts summed cell by cell, then part by part, so
  // that every vertex and face lands where one part would put it.
  const int parts = std::max(1, std::min<int>(resolve_threads(threads), nf / 8192));
  const auto first = [](int64_t n, int64_t p, int parts) { return n * p / parts; };
  // Each vertex's cell; a face goes to its first vertex's (faces are small
  // beside a cell, and a vertex is cheaper than a centroid).
  Array<uint32_t> cell(static_cast<size_t>(nv));
  {
    const float* pos = mesh.positions.data();
    uint32_t* out = cell.data();
    parallel_for(nv, parts, [=](int64_t b, int64_t e) {
      for (int64_t v = b; v < e; ++v) {
        uint32_t code = 0;
        for (int k = 0; k < 3; ++k) {
          const float t = (pos[3 * size_t(v) + k] - lo[k]) * scale[k];
          // Comparisons that are false for NaN: such a vertex goes to cell 0.
          const uint32_t q = t > 0.0f ? (t < top ? uint32_t(t) : uint32_t(top)) : 0u;
          code |= kSpread.bits[q] << k;
        }
        out[v] = code;
      }
    });
  }
  // Per part and cell, the number of the part's vertices and faces there,
  // then where the next of them goes (cell by cell, part by part).
  Array<int32_t> vertex_at(size_t(parts) * cells), face_at(size_t(parts) * cells);
  const uint32_t* cl = cell.data();
  const int32_t* cv = mesh.corner_vertex.data();
  int32_t* va = vertex_at.data();
  int32_t* fa = face_at.data();
  parallel_for_chunks(parts, parts, [=](int64_t pb, int64_t pe) {
    for (int64_t p = pb; p < pe; ++p) {
      int32_t* vh = va + size_t(p) * cells;
      int32_t* fh = fa + size_t(p) * cells;
      std::fill(vh, vh + cells, 0);
      std::fill(fh, fh + cells, 0);
      for (int64_t v = first(nv, p, parts), e = first(nv, p + 1, parts); v < e; ++v) ++vh[cl[v]];
      for (int64_t f = first(nf, p, parts), e = first(nf, p + 1, parts); f < e; ++f) ++fh[cl[cv[3 * f]]];
    }
  });
  // The cells cut into as many ranges as parts: each range's totals (none
  // needed for the first), their sums in range order, then each range's
  // places from its sum.
  std::vector<int64_t> v_sum(size_t(parts) + 1, 0), f_sum(size_t(parts) + 1, 0);
  int64_t* vs = v_sum.data();
  int64_t* fs = f_sum.data();
  if (parts > 1) {
    parallel_for_chunks(parts, parts, [=](int64_t rb, int64_t re) {
      for (int64_t r = rb; r < re; ++r) {
        int64_t nvr = 0, nfr = 0;
        for (size_t p = 0; p < size_t(parts); ++p)
          for (size_t c = first(cells, r, parts), e = first(cells, r + 1, parts); c < e; ++c) {
            nvr += va[p * cells + c];
            nfr += fa[p * cells + c];
          }
        vs[r + 1] = nvr;
        fs[r + 1] = nfr;
      }
    });
    for (int r = 0; r < parts; ++r) {
      vs[r + 1] += vs[r];
      fs[r + 1] += fs[r];
    }
  }
  // (One part, the usual case, known at compile time: the loop over parts
  // then goes, and the pass runs as fast as a plain prefix sum.)
  auto place = [&](auto n_parts) {
    parallel_for_chunks(parts, parts, [=](int64_t rb, int64_t re) {
      for (int64_t r = rb; r < re; ++r) {
        int32_t v_run = int32_t(vs[r]), f_run = int32_t(fs[r]);
        for (size_t c = first(cells, r, parts), e = first(cells, r + 1, parts); c < e; ++c)
          for (size_t p = 0; p < size_t(n_parts); ++p) {
            const int32_t nvc = va[p * cells + c], nfc = fa[p * cells + c];
            va[p * cells + c] = v_run;
            fa[p * cells + c] = f_run;
            v_run += nvc;
            f_run += nfc;
          }
      }
    });
  };
  if (parts == 1) place(std::integral_constant<int, 1>());
  else place(parts);
  // Vertices numbered by cell (a cell's vertices in their order), then the
  // faces placed by their first vertex's cell with their corners renumbered.
  Array<int32_t> id(static_cast<size_t>(nv));
  Array<int32_t> corners(3 * size_t(nf)), wedges(mesh.has_wedges() ? 3 * size_t(nf) : 0);
  std::vector<int32_t> groups(mesh.face_group.size());
  {
    int32_t* to = id.data();
    parallel_for_chunks(parts, parts, [=](int64_t pb, int64_t pe) {
      for (int64_t p = pb; p < pe; ++p) {
        int32_t* vh = va + size_t(p) * cells;
        for (int64_t v = first(nv, p, parts), e = first(nv, p + 1, parts); v < e; ++v) to[v] = vh[cl[v]]++;
      }
    });
    const int32_t* cw = mesh.has_wedges() ? mesh.corner_wedge.data() : nullptr;
    const int32_t* fg = groups.empty() ? nullptr : mesh.face_group.data();
    int32_t* co = corners.data();
    int32_t* wo = wedges.data();
    int32_t* go = groups.data();
    parallel_for_chunks(parts, parts, [=](int64_t pb, int64_t pe) {
      for (int64_t p = pb; p < pe; ++p) {
        int32_t* fh = fa + size_t(p) * cells;
        for (int64_t f = first(nf, p, parts), e = first(nf, p + 1, parts); f < e; ++f) {
          const size_t from = 3 * size_t(f), i = size_t(fh[cl[cv[from]]]++);
          for (int k = 0; k < 3; ++k) co[3 * i + k] = to[cv[from + k]];
          if (cw)
            for (int k = 0; k < 3; ++k) wo[3 * i + k] = cw[from + k];
          if (fg) go[i] = fg[f];
        }
      }
    });
  }
  mesh.corner_vertex.swap(corners);
  mesh.corner_wedge.swap(wedges);
  mesh.face_group.swap(groups);
  // Three floats per vertex, moved to the vertex's new number.
  auto renumber = [&](auto& data) {
    std::remove_reference_t<decltype(data)> moved(data.size());
    const int32_t* to = id.data();
    const float* from = data.data();
    float* out = moved.data();
    parallel_for(nv, parts, [=](int64_t b, int64_t e) {
      for (int64_t v = b; v < e; ++v)
        for (int k = 0; k < 3; ++k) out[3 * size_t(to[v]) + k] = from[3 * size_t(v) + k];
    });
    data.swap(moved);
  };
  renumber(mesh.positions);
  for (VertexChannel& ch : mesh.vertex_channels) renumber(ch.data);
  for (int32_t& v : mesh.wedge_vertex) v = id[v];
}

double face_order_scatter(const Mesh& mesh) {
  const int32_t nf = mesh.num_faces(), nv = mesh.num_vertices();
  if (nf < 2 || nv == 0) return 0;
  const int32_t* cv = mesh.corner_vertex.data();
  constexpr int32_t kPairs = 16384;
  const int32_t step = std::max(1, (nf - 1) / kPairs);
  int64_t sum = 0, pairs = 0;
  for (int32_t f = 1; f < nf; f += step, ++pairs) {
    const int32_t* a = cv + 3 * size_t(f);
    int32_t nearest = INT32_MAX;
    for (int i = 0; i < 3; ++i)
      for (int j = -3; j < 0; ++j) nearest = std::min(nearest, std::abs(a[i] - a[j]));
    sum += nearest;
  }
  return double(sum) / double(pairs) / double(nv);
}

void Mesh::materialize() {
  if (!has_wedges()) {
    corner_wedge = corner_vertex;
    wedge_vertex.resize(num_vertices());
    for (int32_t v = 0; v < num_vertices(); ++v) wedge_vertex[v] = v;
  }
  if (face_group.empty()) face_group.assign(num_faces(), 0);
}

}  // namespace iteas
