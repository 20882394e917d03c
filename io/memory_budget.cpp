#include "io/memory_budget.h"

#include <malloc.h>
#include <unistd.h>

#include <algorithm>
#include <cctype>
#include <cerrno>
#include <cstddef>
#include <cstdio>
#include <atomic>
#include <cstdlib>
#include <limits>
#include <mutex>
#include <unordered_map>

namespace iteas {
namespace {

std::atomic<int64_t> g_current{0}, g_peak{0};
std::atomic<int64_t> g_limit{std::numeric_limits<int64_t>::max()};  // the process's cap
thread_local int64_t t_net = 0;  // bytes this thread allocated minus what it freed
thread_local int64_t t_cap = std::numeric_limits<int64_t>::max();  // t_net may not pass this
thread_local bool t_exceeded = false;

// Over-aligned blocks are counted at their requested size, rounded up to a
// page, when glibc reports more: a large one (the 2 MB-aligned arrays of
// refinement) comes from a mapping with up to |align| bytes of slack before
// and after it, address space that is never touched, which
// malloc_usable_size counts as usable. What each was charged is kept here
// (there are few) so that freeing subtracts exactly that.
std::mutex& aligned_mutex() {
  static std::mutex* m = new std::mutex();
  return *m;
}
std::unordered_map<void*, int64_t>& aligned_charges() {
  static auto* m = new std::unordered_map<void*, int64_t>();  // never destroyed: frees may come late
  return *m;
}

void* allocate(std::size_t n, std::size_t align = 0) {
  // Refuse before asking the system: a bomb's 8 GB request never reaches malloc.
  if (n > std::size_t(std::numeric_limits<int64_t>::max() / 2) || t_net + int64_t(n) > t_cap ||
      g_current.load(std::memory_order_relaxed) + int64_t(n) > g_limit.load(std::memory_order_relaxed)) {
    t_exceeded = true;
    throw MemoryLimitExceeded();
  }
  void* p = nullptr;
  int64_t size = 0;
  if (align > alignof(std::max_align_t)) {
    if (posix_memalign(&p, align, n ? n : 1) != 0) p = nullptr;
    if (!p) throw std::bad_alloc();
    constexpr int64_t kPage = 4096;
    size = std::min(int64_t(malloc_usable_size(p)), (int64_t(n) + kPage - 1) / kPage * kPage);
    try {
      std::lock_guard<std::mutex> lock(aligned_mutex());
      aligned_charges()[p] = size;
    } catch (...) {
      std::free(p);
      throw;
    }
  } else {
    p = std::malloc(n ? n : 1);
    if (!p) throw std::bad_alloc();
    size = int64_t(malloc_usable_size(p));  // a little over n; counted as held
  }
  t_net += size;
  const int64_t now = g_current.fetch_add(size, std::memory_order_relaxed) + size;
  int64_t peak = g_peak.load(std::memory_order_relaxed);
  while (now > peak && !g_peak.compare_exchange_weak(peak, now, std::memory_order_relaxed)) {}
  return p;
}

void release(void* p) noexcept {
  if (!p) return;
  const int64_t size = int64_t(malloc_usable_size(p));
  t_net -= size;
  g_current.fetch_sub(size, std::memory_order_relaxed);
  std::free(p);
}

void release_aligned(void* p) noexcept {
  if (!p) return;
  int64_t size = -1;
  {
    std::lock_guard<std::mutex> lock(aligned_mutex());
    auto it = aligned_charges().find(p);
    if (it != aligned_charges().end()) {
      size = it->second;
      aligned_charges().erase(it);
    }
  }
  if (size < 0) size = int64_t(malloc_usable_size(p));  // an alignment malloc met: counted as such
  t_net -= size;
  g_current.fetch_sub(size, std::memory_order_relaxed);
  std::free(p);
}

}  // namespace

void keep_freed_memory() {
  mallopt(M_MMAP_THRESHOLD, 32 << 20);
  mallopt(M_TRIM_THRESHOLD, 128 << 20);
}

void set_process_heap_limit(int64_t bytes) {
  g_limit.store(bytes > 0 ? bytes : std::numeric_limits<int64_t>::max(), std::memory_order_relaxed);
}

int64_t process_heap_limit() {
  const int64_t limit = g_limit.load(std::memory_order_relaxed);
  return limit == std::numeric_limits<int64_t>::max() ? 0 : limit;
}

int64_t default_memory_limit() {
  int64_t total = int64_t(sysconf(_SC_PHYS_PAGES)) * int64_t(sysconf(_SC_PAGESIZE));
  // The container's limit: cgroup v2, or v1 on older hosts (whose "no
  // limit" is a number near 2^63, above the machine's memory).
  for (const char* file : {"/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory/memory.limit_in_bytes"})
    if (FILE* f = std::fopen(file, "r")) {
      long long v = 0;
      if (std::fscanf(f, "%lld", &v) == 1 && v > 0 && v < total) total = v;  // "max" reads as no number
      std::fclose(f);
    }
  return total / 4 * 3;
}

bool parse_byte_size(const std::string& text, int64_t* bytes) {
  if (text.empty() || !std::isdigit(static_cast<unsigned char>(text[0]))) return false;
  char* end = nullptr;
  errno = 0;
  const long long x = std::strtoll(text.c_str(), &end, 10);
  const std::string unit = end;
  const int shift = unit.empty() ? 0 : unit == "K" ? 10 : unit == "M" ? 20 : unit == "G" ? 30 : -1;
  if (errno != 0 || shift < 0 || x > (1LL << 50) >> shift) return false;
  *bytes = int64_t(x) << shift;
  return true;
}

int64_t current_heap_bytes() { return g_current.load(std::memory_order_relaxed); }
int64_t peak_heap_bytes() { return g_peak.load(std::memory_order_relaxed); }
void reset_peak_heap_bytes() { g_peak.store(g_current.load(std::memory_order_relaxed), std::memory_order_relaxed); }

MemoryBudget::MemoryBudget(int64_t limit)
    : start_(t_net), saved_cap_(t_cap), saved_exceeded_(t_exceeded) {
  // t_net may be negative (this thread freed what others allocated): no
  // overflow either way.
  const int64_t max = std::numeric_limits<int64_t>::max();
  const int64_t cap = t_net > 0 && limit > max - t_net ? max : t_net + limit;
  t_cap = cap < t_cap ? cap : t_cap;
  t_exceeded = false;
}

MemoryBudget::~MemoryBudget() {
  t_cap = saved_cap_;
  t_exceeded = saved_exceeded_ || t_exceeded;
}

int64_t MemoryBudget::used() const { return t_net - start_; }
bool MemoryBudget::exceeded() const { return t_exceeded; }

}  // namespace iteas

// The replacements: every form, so that no allocation pairs our delete with
// another allocator's new (sanitizer runtimes bring their own operator new).
void* operator new(std::size_t n) { return iteas::allocate(n); }
void* operator new[](std::size_t n) { return iteas::allocate(n); }
void* operator new(std::size_t n, const std::nothrow_t&) noexcept {
  try { return iteas::allocate(n); } catch (...) { return nullptr; }
}
void* operator new[](std::size_t n, const std::nothrow_t&) noexcept {
  try { return iteas::allocate(n); } catch (...) { return nullptr; }
}
void* operator new(std::size_t n, std::align_val_t a) { return iteas::allocate(n, std::size_t(a)); }
void* operator new[](std::size_t n, std::align_val_t a) { return iteas::allocate(n, std::size_t(a)); }
void* operator new(std::size_t n, std::align_val_t a, const std::nothrow_t&) noexcept {
  try { return iteas::allocate(n, std::size_t(a)); } catch (...) { return nullptr; }
}
void* operator new[](std::size_t n, std::align_val_t a, const std::nothrow_t&) noexcept {
  try { return iteas::allocate(n, std::size_t(a)); } catch (...) { return nullptr; }
}
void operator delete(void* p) noexcept { iteas::release(p); }
void operator delete[](void* p) noexcept { iteas::release(p); }
void operator delete(void* p, std::size_t) noexcept { iteas::release(p); }
void operator delete[](void* p, std::size_t) noexcept { iteas::release(p); }
void operator delete(void* p, const std::nothrow_t&) noexcept { iteas::release(p); }
void operator delete[](void* p, const std::nothrow_t&) noexcept { iteas::release(p); }
void operator delete(void* p, std::align_val_t) noexcept { iteas::release_aligned(p); }
void operator delete[](void* p, std::align_val_t) noexcept { iteas::release_aligned(p); }
void operator delete(void* p, std::size_t, std::align_val_t) noexcept { iteas::release_aligned(p); }
void operator delete[](void* p, std::size_t, std::align_val_t) noexcept { iteas::release_aligned(p); }
void operator delete(void* p, std::align_val_t, const std::nothrow_t&) noexcept { iteas::release_aligned(p); }
void operator delete[](void* p, std::align_val_t, const std::nothrow_t&) noexcept { iteas::release_aligned(p); }
