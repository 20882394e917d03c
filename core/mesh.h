// The refinable mesh: one welded connectivity per glTF mesh, attributes kept per
// corner ("wedges") so seams, hard normals and primitive borders survive.
// Flat arrays only (meshoptimizer / Draco style), no pointer graphs.
#pragma once

#include <cstdint>
#include <memory>
#include <new>
#include <string>
#include <utility>
#include <vector>

namespace iteas {

// std::allocator except that resize() and sized construction leave new
// elements of trivial types uninitialised instead of zero-filling them. The
// refinement writes every entry of the arrays it grows, so the zero fill was a
// wasted single-threaded pass (and it took every page fault on one thread).
// Anything that needs zeros says so: assign(n, 0) or resize(n, 0).
// Arrays of two pages or more are made ready before they are written: their
// pages are faulted in with one system call (MADV_POPULATE_WRITE) rather than
// one trap per 4 KB page (here a trap costs 9.5 us, a populated page 0.4 us:
// even a 2-page array gains), and those of 2 MB or more are offered to
// transparent huge pages (where the system allows it on request). Refinement
// writes tens of MB of fresh memory per level, and page faults were most of
// its kernel time; level 1 of a small mesh, 0.4 ms with reused memory, paid
// 0.6 ms for its traps with fresh memory.
// Arrays of 2 MB or more start on a 2 MB boundary, so that every whole 2 MB
// stretch of them can be a huge page (not only the aligned middle of an
// arbitrary block): on this kind of virtual machine a huge page is populated
// 3x faster than the 512 small pages it replaces, unmapped 17x faster, and
// written 10x faster afterwards (one TLB entry instead of 512).
constexpr size_t kPrefaultBytes = 8 * 1024;
constexpr size_t kHugePageBytes = size_t(2) << 20;
void prepare_pages(void* p, size_t bytes);
// Tells prepare_pages that the allocator may have given freed pages back to
// the system (after malloc_trim): blocks it had found resident are asked
// about again.
void forget_resident_memory();
// For its lifetime, the calling thread's prepare_pages faults in the pages of
// a large array on up to |threads| threads (<= 0: all cores), a part each,
// as the kernel zeroes every new page and two threads zero twice as many; the
// refinement sets its own thread count. Not inside a parallel_for's pieces.
// Only arrays of two 2 MB stretches or more are split, in whole stretches
// (populate_parts). Split into small pages, both halves of an array share the
// kernel's locks for its page tables, and two threads faulted in arrays of
// 40-700 KB more slowly than one (bunny-npm on two threads, fresh memory:
// level 2 0.93-0.97 -> 0.89-0.90 ms, level 3 2.76-2.83 -> 2.48-2.56 ms with
// those in one call). Arrays of 4-12 MB (bunny-npm level 4) were faulted in
// faster in one call too, but bun_zipper's of 4-16 MB were not (level 3 on
// two threads 6 % slower that way): whole stretches stay split.
constexpr size_t kPopulatePartsFrom = 2 * kHugePageBytes;
// The parts a fresh range of |bytes| is faulted in as, on |threads| threads.
int populate_parts(size_t bytes, int threads);
class PagePopulateThreads {
 public:
  explicit PagePopulateThreads(int threads);
  ~PagePopulateThreads();
  PagePopulateThreads(const PagePopulateThreads&) = delete;
  PagePopulateThreads& operator=(const PagePopulateThreads&) = delete;

 private:
  int previous_;
};

template <typename T>
struct NoInitAllocator : std::allocator<T> {
  using value_type = T;
  NoInitAllocator() noexcept = default;
  template <typename U>
  NoInitAllocator(const NoInitAllocator<U>&) noexcept {}
  template <typename U>
  struct rebind { using other = NoInitAllocator<U>; };
  T* allocate(size_t n) {
    // (n * sizeof(T) does not overflow: containers ask for at most max_size().)
    const size_t bytes = n * sizeof(T);
    T* p = bytes >= kHugePageBytes ? static_cast<T*>(::operator new(bytes, std::align_val_t(kHugePageBytes)))
                                   : std::allocator<T>::allocate(n);
    prepare_pages(p, bytes);
    return p;
  }
  void deallocate(T* p, size_t n) noexcept {
    if (n * sizeof(T) >= kHugePageBytes) ::operator delete(p, std::align_val_t(kHugePageBytes));
    else std::allocator<T>::deallocate(p, n);
  }
  template <typename U>
  void construct(U* p) noexcept { ::new (static_cast<void*>(p)) U; }
  template <typename U, typename... Args>
  void construct(U* p, Args&&... args) { ::new (static_cast<void*>(p)) U(std::forward<Args>(args)...); }
};
template <typename T, typename U>
bool operator==(const NoInitAllocator<T>&, const NoInitAllocator<U>&) { return true; }
template <typename T, typename U>
bool operator!=(const NoInitAllocator<T>&, const NoInitAllocator<U>&) { return false; }
template <typename T>
using Array = std::vector<T, NoInitAllocator<T>>;

// How a per-wedge channel is carried through refinement (SPEC §2 "Attributes").
enum class ChannelKind : uint8_t {
  kLinear,   // TEXCOORD_n, COLOR_n, anything else: interpolated along the edge
  kNormal,   // recomputed from the refined geometry, hard edges kept
  kTangent,  // interpolated, re-orthogonalised against the normal, w kept
  kJoints,   // JOINTS_n: blended together with the paired WEIGHTS_n
  kWeights,  // WEIGHTS_n: top 4 influences kept, renormalised
};

struct Channel {
  std::string name;        // glTF semantic, e.g. "TEXCOORD_0"
  int components = 0;      // 1..4
  ChannelKind kind = ChannelKind::kLinear;
  int pair = -1;           // for kJoints/kWeights: index of the partner channel
  Array<float> data;       // components per wedge (grown without a zero fill: see Array)
};

// A per-vertex channel refined with the Butterfly stencil weights
// (morph-target position deltas).
struct VertexChannel {
  std::string name;
  std::vector<float> data;  // 3 per vertex
};

struct Mesh {
  Array<float> positions;             // 3 per vertex
  Array<int32_t> corner_vertex;       // 3 per face: corner -> vertex
  Array<int32_t> corner_wedge;        // 3 per face: corner -> wedge
  std::vector<int32_t> face_group;    // per face: primitive id
  std::vector<int32_t> wedge_vertex;  // per wedge: its vertex
  std::vector<Channel> channels;      // per-wedge data
  std::vector<VertexChannel> vertex_channels;  // per-vertex data (morph deltas)

  int32_t num_vertices() const { return static_cast<int32_t>(positions.size() / 3); }
  int32_t num_faces() const { return static_cast<int32_t>(corner_vertex.size() / 3); }
  int32_t num_wedges() const { return static_cast<int32_t>(wedge_vertex.size()); }

  // corner_wedge/wedge_vertex may be empty when the mesh has no per-wedge
  // channels: then every vertex is its own wedge. face_group may be empty:
  // then every face is in group 0. Refinement uses both to save memory.
  bool has_wedges() const { return !corner_wedge.empty(); }
  int32_t wedge_of(int32_t c) const { return corner_wedge.empty() ? corner_vertex[c] : corner_wedge[c]; }
  int32_t group_of(int32_t f) const { return face_group.empty() ? 0 : face_group[f]; }
  int32_t wedge_count() const { return has_wedges() ? num_wedges() : num_vertices(); }
  // Makes corner_wedge/face_group explicit again (identity / zeros).
  void materialize();

  // Adds a wedge for |vertex| with all channel values zero; returns its index.
  int32_t add_wedge(int32_t vertex);
  // Index of the channel with that name, or -1.
  int find_channel(const std::string& name) const;
};

// Geometry facts used by tests and statistics.
struct Aabb {
  float lo[3] = {0, 0, 0};
  float hi[3] = {0, 0, 0};
  double diagonal() const;
};
Aabb bounding_box(const Mesh& mesh);

// Drops faces with a repeated vertex (SPEC §2); returns how many were dropped.
int64_t drop_degenerate_faces(Mesh& mesh);

// Puts the faces (with their corners' wedges and their groups) in the order
// of a Z-order (Morton) curve through a grid over the bounding box, by the
// cell of each face's first vertex (faces of one cell keep their relative
// order), and numbers the vertices in the same order, by their own cells (a
// cell's vertices keep their relative order; positions and per-vertex
// channels move with them). Wedges keep their numbers. A thread's share of
// a loop over faces or vertices is then one region of the surface, whose
// vertices, edges and neighbours the other thread seldom touches (see
// refine_mesh). Runs on up to |threads| threads (<= 0: all cores); the
// result is the same on any number.
void order_faces_spatially(Mesh& mesh, int threads = 1);

// How scattered the faces' order is: over pairs of consecutive faces, the
// mean of the least distance between a vertex number of one and a vertex
// number of the other, over the vertex count. Faces that walk the surface
// share a vertex, or a near number, with the face before (an exporter's
// order, Draco's traversal, a refined mesh's children: at most 0.0017 on the
// corpus); a scan's faces jump (0.012-0.061 there; a random order about
// 0.07). Every ((faces - 1) / 16,384)-th pair is read (at least every
// one): 16,384 to 32,767 pairs from 16,385 faces on.
double face_order_scatter(const Mesh& mesh);

}  // namespace iteas
