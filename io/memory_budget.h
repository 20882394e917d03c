// Process-wide heap accounting and per-thread memory budgets.
//
// The global operator new/delete are replaced (as ClickHouse's MemoryTracker
// does): every allocation is counted for the process and for the allocating
// thread. A MemoryBudget scope caps the net bytes its thread may allocate while
// it lives; past the cap, operator new throws MemoryLimitExceeded (a
// std::bad_alloc) instead of asking the system, so a decoder fed a
// decompression bomb or a job that outgrows its estimate fails cleanly
// before the machine runs out of memory.
#pragma once

#include <cstdint>
#include <new>
#include <string>

namespace iteas {

struct MemoryLimitExceeded : std::bad_alloc {
  const char* what() const noexcept override { return "memory budget exceeded"; }
};

// Bytes the process holds through operator new now, and the most since the
// last reset_peak_heap_bytes().
int64_t current_heap_bytes();
int64_t peak_heap_bytes();
void reset_peak_heap_bytes();

// Lets glibc keep what the process frees for reuse: large blocks (up to
// 32 MiB) come from the heap instead of fresh mappings, and up to 128 MiB of
// free heap stays mapped. A refinement frees and allocates a level's arrays
// over and over; returned to the system at once, every page came back with a
// first-touch fault (about 10 us each on a virtual machine). Called once at
// start by the binary; the server gives the memory back after each job
// (malloc_trim).
void keep_freed_memory();

// A cap on all the process holds through operator new, on every thread
// (<= 0: none, the default): past it, operator new throws
// MemoryLimitExceeded instead of asking the system. The CLI sets it
// (--memory-limit, by default default_memory_limit()), so that a job too
// large for the machine stops with a message instead of being killed by the
// kernel's out-of-memory killer.
void set_process_heap_limit(int64_t bytes);
int64_t process_heap_limit();  // 0: none

// Three quarters of the machine's memory, or of its container's limit (cgroup
// v2 memory.max, or v1 memory.limit_in_bytes) when that is lower: what a
// process of ours may plan on.
int64_t default_memory_limit();

// A size in bytes as the flags give it: digits, optionally followed by K, M or
// G (binary multiples), at most 2^50 bytes. False for anything else.
bool parse_byte_size(const std::string& text, int64_t* bytes);

// While alive, this thread may hold at most |limit| more bytes than when the
// scope began. Scopes nest (the tighter cap wins). Not copyable.
class MemoryBudget {
 public:
  explicit MemoryBudget(int64_t limit);
  ~MemoryBudget();
  MemoryBudget(const MemoryBudget&) = delete;
  MemoryBudget& operator=(const MemoryBudget&) = delete;
  int64_t used() const;      // net bytes allocated by this thread in the scope
  bool exceeded() const;     // an allocation was refused in the scope

 private:
  int64_t start_, saved_cap_;
  bool saved_exceeded_;
};

}  // namespace iteas
