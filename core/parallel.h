// A deterministic parallel-for: the range is cut into contiguous pieces, dealt
// in contiguous shares to the calling thread and persistent workers, which
// claim their own share's pieces in order and then the rest. Results never
// depend on scheduling or on the thread count as long as each index writes
// only its own outputs (loops that reduce do so per fixed-size chunk and
// combine the chunks in order).
#pragma once

#include <cstdint>
#include <functional>

namespace iteas {

// Runs body(begin, end) over [0, n) on up to |threads| threads (<= 0: all cores),
// giving each thread at least |grain| indices (small ranges run inline). Loops
// over fixed-size chunks pass grain 1.
void parallel_for(int64_t n, int threads, const std::function<void(int64_t, int64_t)>& body, int64_t grain = 4096);

int hardware_threads();
// A thread count as the options give it: <= 0 means all cores.
inline int resolve_threads(int threads) { return threads <= 0 ? hardware_threads() : threads; }

// True while the calling thread runs pieces of a parallel_for of more than one
// thread (a loop started there finds the pool busy and starts threads of its own).
bool inside_parallel_for();

}  // namespace iteas

namespace iteas {
// For loops whose indices are already coarse chunks of work.
inline void parallel_for_chunks(int64_t n, int threads, const std::function<void(int64_t, int64_t)>& body) {
  parallel_for(n, threads, body, 1);
}
}  // namespace iteas
