// A deterministic parallel-for: the range is cut into contiguous pieces, dealt
// in contiguous shares to the calling thread and persistent workers, which
// claim their own share's pieces in order and then the rest. Results never
// depend on scheduling or on the thread count as long as each index writes
// only its own outputs (loops that reduce do so per fixed-size chunk and
// combine the chunks in order).
#pragma once

#include <algorithm>
#include <atomic>
#include <cstdint>
#include <exception>
#include <functional>
#include <type_traits>
#include <utility>
#include <vector>

namespace iteas {

// Runs body(begin, end) over [0, n) on up to |threads| threads (<= 0: all cores),
// giving each thread at least |grain| indices (small ranges run inline). Loops
// over fixed-size chunks pass grain 1.
void parallel_for(int64_t n, int threads, const std::function<void(int64_t, int64_t)>& body, int64_t grain = 4096);

int hardware_threads();
// A thread count as the options give it: <= 0 means all cores.
inline int resolve_threads(int threads) { return threads <= 0 ? hardware_threads() : threads; }

// The round trip of a cache line between the caller's CPU and the pool's
// first worker, in ns, as last measured (at most every 100 ms: after a
// parallel loop, or when threads_for asks; -1 before the first).
int64_t cross_cpu_round_trip_ns();

// The threads worth using for work whose largest step is over |faces| faces:
// |threads|, except one while the CPUs are far apart and the work is small,
// or while the worker sleeps and the work is tiny (see below).
// A virtual machine's two CPUs can sit close together on the host or far
// apart, for minutes at a time (measured here: a round trip of 120-190 ns or
// of 450-530 ns); far apart, every line one thread has written costs the
// other about three times as much, and two threads took longer than one
// below about 15,000 faces (bunny-npm uniform, back to back: level 1 0.29-0.36
// against 0.19 ms, level 2 0.81 against 0.59 ms; level 3, whose last level
// starts from 58,784 faces, as fast on two as on one). The result never
// depends on it (the loops are deterministic). Measures the round trip again
// when the last measurement is stale.
int threads_for(int64_t faces, int threads);
// Also one for a tiny job while the worker sleeps (or does not exist yet):
// waking it took 22-38 µs here after a short sleep and 0.6 ms or more once
// its virtual CPU had been idle for 2 ms, while a job whose last level
// starts from under 8,192 faces takes 0.2-0.4 ms on one thread (bunny-npm
// uniform level 1, whose loops the worker then joined late or never: 0.79-1.0x
// one thread's speed in the benchmark, where every run finds it asleep).
// The rule itself, for a given round trip (-1: unknown, taken as close).
constexpr int64_t kSmallStepFaces = 16384;
constexpr int64_t kTinyStepFaces = 8192;
constexpr int64_t kFarRoundTripNs = 300;
int threads_for_round_trip(int64_t faces, int threads, int64_t round_trip_ns, bool worker_awake = true);

// True while the calling thread runs pieces of a parallel_for of more than one
// thread (a loop started there finds the pool busy and starts threads of its own).
bool inside_parallel_for();

// Work that another thread may take while this one goes on with its own,
// for as long as what the work reads stays as it is: offer() (on the other
// thread, e.g. as a piece of a parallel_for_chunks) does it unless it has
// begun; finish() (on the owner's thread, before what it reads changes)
// does it there if no thread has begun it, else waits until it is done and
// rethrows what it threw there. Done once, whoever does it.
class BesideWork {
 public:
  explicit BesideWork(std::function<void()> work) : work_(std::move(work)) {}
  BesideWork(const BesideWork&) = delete;
  BesideWork& operator=(const BesideWork&) = delete;
  void offer();
  void finish();

 private:
  bool begin();
  std::function<void()> work_;
  std::atomic<int> state_{0};  // 0 idle, 1 begun, 2 done
  std::exception_ptr error_;
};

}  // namespace iteas

namespace iteas {
// For loops whose indices are already coarse chunks of work.
inline void parallel_for_chunks(int64_t n, int threads, const std::function<void(int64_t, int64_t)>& body) {
  parallel_for(n, threads, body, 1);
}

// A compaction in two parallel passes over fixed chunks of [0, n):
// count(begin, end) says how many entries a chunk will write; the counts
// are summed in chunk order; prepare(total) runs once, on the caller (to
// size the output); fill(begin, end, at) writes the chunk's entries from
// position |at|. Every entry lands where a serial pass in index order would
// put it, whatever the threads. fill may also take a fourth argument, the
// end of the chunk's entries. On one thread the whole range is one chunk.
// The count is an integer, or a struct of several (value-initialised to
// zero, summed with +). Returns the total.
template <typename Count, typename Prepare, typename Fill>
auto parallel_count_fill(int64_t n, int threads, int64_t chunk, const Count& count, const Prepare& prepare,
                         const Fill& fill) {
  using T = decltype(count(int64_t(0), int64_t(0)));
  if (resolve_threads(threads) <= 1) chunk = std::max<int64_t>(n, 1);  // one thread: one chunk
  const int64_t chunks = n <= 0 ? 0 : (n + chunk - 1) / chunk;
  std::vector<T> at(size_t(chunks) + 1, T());
  parallel_for_chunks(chunks, threads, [&](int64_t b, int64_t e) {
    for (int64_t k = b; k < e; ++k) at[size_t(k) + 1] = count(k * chunk, std::min(n, (k + 1) * chunk));
  });
  for (int64_t k = 0; k < chunks; ++k) at[size_t(k) + 1] = at[size_t(k)] + at[size_t(k) + 1];
  prepare(at[size_t(chunks)]);
  parallel_for_chunks(chunks, threads, [&](int64_t b, int64_t e) {
    for (int64_t k = b; k < e; ++k) {
      const int64_t begin = k * chunk, end = std::min(n, (k + 1) * chunk);
      if constexpr (std::is_invocable_v<const Fill&, int64_t, int64_t, T, T>)
        fill(begin, end, at[size_t(k)], at[size_t(k) + 1]);
      else
        fill(begin, end, at[size_t(k)]);
    }
  });
  return at[size_t(chunks)];
}
}  // namespace iteas
