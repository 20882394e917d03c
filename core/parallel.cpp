#include "core/parallel.h"

#include <algorithm>
#include <atomic>
#include <chrono>
#include <condition_variable>
#include <exception>
#include <memory>
#include <mutex>
#include <system_error>
#include <thread>
#include <vector>

namespace iteas {

int hardware_threads() {
  unsigned n = std::thread::hardware_concurrency();
  return n == 0 ? 1 : static_cast<int>(n);
}

namespace {

using Body = std::function<void(int64_t, int64_t)>;

// Set while this thread runs pieces of a loop (the workers always are).
thread_local bool tl_in_loop = false;
struct InLoop {
  bool was = tl_in_loop;
  InLoop() { tl_in_loop = true; }
  ~InLoop() { tl_in_loop = was; }
};

inline void cpu_relax() {
#if defined(__x86_64__) || defined(__i386__)
  __builtin_ia32_pause();
#endif
}

// Waits until |state| holds |value|: spinning first (the other thread is
// usually about to store it), then yielding the CPU.
void wait_for(const std::atomic<int>& state, int value) {
  for (int spins = 0; state.load(std::memory_order_acquire) != value; ++spins) {
    if (spins < 4096) cpu_relax();
    else std::this_thread::yield();
  }
}

// Persistent workers for parallel_for. Starting a thread costs about 33 µs
// here, as much as a whole parallel loop of a small level; a level runs about
// a dozen loops with short serial steps between them. Each worker has its own
// slot: the caller points it at the loop and bumps its generation; the worker
// spins briefly after each loop (the next one usually follows within
// microseconds), then sleeps on a condition variable. Each thread runs its own
// share of the loop's pieces, then claims what is left of the others' shares,
// so a thread that is slowed (an uneven piece, a busy core) does not hold the
// other up; which thread runs a piece never changes what the piece writes.
class Pool {
 public:
  // Runs the pieces of [0, n) on the caller and |workers| workers. Returns
  // false (nothing run) when the pool is busy (a nested or concurrent
  // parallel_for) or cannot start the workers; the caller then falls back.
  bool run(int64_t n, int workers, int64_t pieces, const Body& body, std::exception_ptr& error) {
    std::unique_lock<std::mutex> in_use(use_, std::try_to_lock);
    if (!in_use.owns_lock()) return false;
    if (!grow(workers)) return false;
    loop_.body = &body;
    loop_.n = n;
    loop_.pieces = pieces;
    loop_.deal(workers + 1);
    loop_.failed.store(false, std::memory_order_relaxed);
    for (int w = 0; w < workers; ++w) {
      Slot& s = *slots_[w];
      s.error = nullptr;
      s.state.store(kAssigned, std::memory_order_release);
      s.go.store(s.go.load(std::memory_order_relaxed) + 1, std::memory_order_seq_cst);
      if (s.sleeping.load(std::memory_order_seq_cst)) {
        std::lock_guard<std::mutex> lock(s.mutex);
        s.wake.notify_one();
      }
    }
    {
      InLoop in_loop;
      error = loop_.drain(0);
    }
    for (int w = 0; w < workers; ++w) {
      Slot& s = *slots_[w];
      // Every piece is claimed and the caller's are done. A worker that has
      // not joined yet (still waking from its sleep) is told not to: waiting
      // for it would only add its wake-up time to the loop.
      int expected = kAssigned;
      if (s.state.compare_exchange_strong(expected, kIdle, std::memory_order_acq_rel)) continue;
      wait_for(s.state, kIdle);
      if (!error) error = s.error;
    }
    if (workers > 0) measure_round_trip();
    return true;
  }

  // For work the caller may run alone: true when the first worker is awake
  // (it spins for about 60 µs after each loop and yields the CPU for about
  // 940 µs more before it sleeps, or spins for 2 ms once roused),
  // and then the round trip below is measured again if stale. Otherwise the
  // worker is started, or woken to spin for 2 ms, so that a call soon after
  // this one finds it awake (a job that did not wait for it leaves it asleep
  // otherwise, and so would every tiny job after it); false also while the
  // pool is busy.
  bool rouse() {
    std::unique_lock<std::mutex> in_use(use_, std::try_to_lock);
    if (!in_use.owns_lock()) return false;
    if (slots_.empty()) {
      grow(1);
      return false;
    }
    Slot& s = *slots_[0];
    if (s.sleeping.load(std::memory_order_seq_cst)) {
      linger(s);
      return false;
    }
    measure_round_trip();
    return true;
  }

  // Nanoseconds a cache line takes from the caller's CPU to the first
  // worker's and back, as last measured (-1: not yet).
  static std::atomic<int64_t>& round_trip() {
    static std::atomic<int64_t> ns{-1};
    return ns;
  }

 private:
  // The loop's pieces are dealt in contiguous shares, one per thread (the
  // caller's first): each thread claims its own share's pieces in order, then
  // helps with the others'. Consecutive loops over the same index space (or
  // over a level's children, 4 faces per parent) then mostly give a thread
  // the data it wrote itself in the loop before, still in its own cache;
  // claiming every piece from one shared counter handed each thread a
  // different part every loop, whose lines then came from the other core.
  struct Loop {
    static constexpr int kMaxShares = 64;
    struct alignas(64) Share {
      std::atomic<int64_t> next{0};
      int64_t end = 0;
    };
    const Body* body = nullptr;
    int64_t n = 0, pieces = 1;
    int shares = 1;
    Share share[kMaxShares];
    std::atomic<bool> failed{false};
    void deal(int threads) {
      shares = std::min(threads, kMaxShares);
      for (int t = 0; t < shares; ++t) {
        share[t].next.store(pieces * t / shares, std::memory_order_relaxed);
        share[t].end = pieces * (t + 1) / shares;
      }
    }
    // Claims and runs pieces until none are left (or one has thrown):
    // participant |self|'s share first (0 is the caller, worker w is w + 1).
    std::exception_ptr drain(int self) {
      for (int k = 0; k < shares; ++k) {
        Share& sh = share[(self + k) % shares];
        for (;;) {
          if (failed.load(std::memory_order_relaxed)) return nullptr;
          const int64_t p = sh.next.fetch_add(1, std::memory_order_relaxed);
          if (p >= sh.end) break;
          // Piece p is [n p / pieces, n (p + 1) / pieces): lengths differ by one at most.
          try {
            (*body)(n * p / pieces, n * (p + 1) / pieces);
          } catch (...) {
            failed.store(true, std::memory_order_relaxed);
            return std::current_exception();
          }
        }
      }
      return nullptr;
    }
  };
  // A worker's part in the current loop: assigned by the caller, then either
  // joined by the worker (running, back to idle when it has drained) or
  // withdrawn by the caller before the worker got to it (back to idle).
  static constexpr int kIdle = 0, kAssigned = 1, kRunning = 2;
  struct Slot {
    std::atomic<uint64_t> go{0};
    std::atomic<int> state{kIdle};
    std::atomic<uint32_t> ping{0};  // odd: the caller asks; the worker answers +1
    std::atomic<bool> linger{false};  // woken to be measured: spin 2 ms
    std::atomic<bool> sleeping{false};
    Loop* loop = nullptr;
    int index = 1;  // participant number in a loop (the caller is 0)
    std::exception_ptr error;
    std::mutex mutex;
    std::condition_variable wake;
  };

  // At most every 100 ms, the first worker answers a flag 8 times while it
  // spins; the round trip kept is the median of the last 7. The caller holds
  // use_. A sleeping worker is not waited for (a wake-up took 0.15-0.75 ms
  // while the CPUs were far apart; rouse() wakes it, and a later call
  // measures). Nothing is recorded when there is no worker yet, or when the
  // answers take over 50 µs in all (then tried again in 10 ms).
  void measure_round_trip() {
    using Clock = std::chrono::steady_clock;
    if (slots_.empty()) return;
    Slot& s = *slots_[0];
    const Clock::time_point start = Clock::now();
    if (start < next_measurement_) return;
    if (s.sleeping.load(std::memory_order_seq_cst)) return;
    next_measurement_ = start + std::chrono::milliseconds(10);
    constexpr int kTrips = 8;
    int64_t trip[kTrips];
    for (int k = 0; k < kTrips; ++k) {
      ping_ += 2;
      const Clock::time_point t0 = Clock::now();
      s.ping.store(ping_, std::memory_order_release);
      while (s.ping.load(std::memory_order_acquire) != ping_ + 1) {
        cpu_relax();
        if (Clock::now() - start > std::chrono::microseconds(50)) return;
      }
      trip[k] = std::chrono::duration_cast<std::chrono::nanoseconds>(Clock::now() - t0).count();
    }
    std::nth_element(trip + 1, trip + 1 + kTrips / 2 - 1, trip + kTrips);
    round_trip().store(trip[kTrips / 2], std::memory_order_relaxed);
    next_measurement_ = start + std::chrono::milliseconds(100);
  }

  // Wakes a sleeping worker to spin for 2 ms (the caller holds use_: the
  // bumped generation then withdraws no loop).
  static void linger(Slot& s) {
    s.linger.store(true, std::memory_order_relaxed);
    s.go.store(s.go.load(std::memory_order_relaxed) + 1, std::memory_order_seq_cst);
    std::lock_guard<std::mutex> lock(s.mutex);
    s.wake.notify_one();
  }

  bool grow(int workers) {
    while (int(slots_.size()) < workers) {
      slots_.push_back(std::make_unique<Slot>());
      Slot* s = slots_.back().get();
      s->loop = &loop_;
      s->index = int(slots_.size());
      // A thread that cannot start (the system refuses one, or a memory
      // budget its state): no slot without a worker is left behind.
      try {
        std::thread(&Pool::work, s).detach();
      } catch (...) {
        slots_.pop_back();
        return false;
      }
    }
    return true;
  }

  static void work(Slot* s) {
    tl_in_loop = true;
    uint64_t seen = 0;
    for (;;) {
      // Spin about 60 µs for the next loop, then spin yielding the CPU
      // (sched_yield each turn) for about 940 µs more, then sleep. A worker
      // that has run out of pieces waits for the caller to finish the loop's
      // last ones (up to a piece's length) and then for the serial step
      // after it; with 20 µs it was often asleep when the next loop came
      // (bunny-npm level 3, the last level's children after its data pass:
      // asleep in 84 % of the runs, waking took 22-38 µs), and level 3 on two
      // threads took 1.38 against 1.30 ms (150 µs: no better). The default
      // mode's levels have serial steps of 0.06-1 ms between their loops, and
      // a worker asleep there made a new process's job on two threads slower
      // than on one about half the time (AMD Zen 5 class, nested virtual
      // machine; refine phase of the CLI at the defaults, two threads, 25
      // runs each, median and 90th percentile: bunny 26.2 / 28.3 -> 16.5 /
      // 19.3 ms, Max Planck 24.2 / 32.2 -> 20.7 / 23.7 ms, fertility 17.4 /
      // 19.0 -> 12.3 / 15.6 ms; one thread 24.3, 30.1 and 15.5 ms).
      // Yielding, not plain spinning, after the first 60 µs: other work on
      // the machine gets the CPU. A plain 1 ms spin measured as fast alone
      // but made two CLI processes at once (two threads each, two CPUs) 25 %
      // slower (ten pairs, bunny and Max Planck: 0.64 -> 0.80 s), the
      // yielding one 0.65-0.66 -> 0.60 s. A ping (the round trip measured)
      // puts a yielding worker back to spinning: answered between two
      // yields, system calls, it read as CPUs far apart, and small jobs then
      // ran on one thread. (On an earlier machine longer plain spins measured
      // slower: there a spinning thread took from the caller's serial steps.)
      auto until = std::chrono::steady_clock::now() + (s->linger.load(std::memory_order_relaxed) && s->linger.exchange(false, std::memory_order_relaxed)
                                                            ? std::chrono::microseconds(2000)
                                                            : std::chrono::microseconds(60));
      const auto yield_until = until + std::chrono::microseconds(940);
      int spins = 0;
      bool yielding = false;
      while (s->go.load(std::memory_order_acquire) == seen) {
        uint32_t p = s->ping.load(std::memory_order_acquire);
        if (p & 1u) {
          s->ping.compare_exchange_strong(p, p + 1, std::memory_order_acq_rel);
          // Measured: answer the next pings at once (a yield between two of
          // them, a system call, read as CPUs far apart), spinning again
          // for 60 µs.
          if (yielding) {
            yielding = false;
            until = std::chrono::steady_clock::now() + std::chrono::microseconds(60);
          }
        }
        if (yielding) std::this_thread::yield();
        else cpu_relax();
        if ((++spins & (yielding ? 15 : 255)) != 0) continue;
        const auto t = std::chrono::steady_clock::now();
        if (!yielding) {
          yielding = t > until;
          continue;
        }
        if (t <= yield_until) continue;
        yielding = false;
        std::unique_lock<std::mutex> lock(s->mutex);
        s->sleeping.store(true, std::memory_order_seq_cst);
        s->wake.wait(lock, [&] { return s->go.load(std::memory_order_seq_cst) != seen; });
        s->sleeping.store(false, std::memory_order_relaxed);
      }
      seen = s->go.load(std::memory_order_acquire);
      // Join the loop unless the caller has withdrawn it (then the loop's
      // data may already belong to the next loop, which bumps go again).
      int expected = kAssigned;
      if (!s->state.compare_exchange_strong(expected, kRunning, std::memory_order_acq_rel)) continue;
      s->error = s->loop->drain(s->index);
      s->state.store(kIdle, std::memory_order_release);
    }
  }

  std::mutex use_;
  std::chrono::steady_clock::time_point next_measurement_;  // none before
  uint32_t ping_ = 1;  // the last odd value asked (answered: ping_ + 1)
  Loop loop_;
  std::vector<std::unique_ptr<Slot>> slots_;
};

// Never destroyed: detached workers may still be parked on it at exit.
Pool& pool() {
  static Pool* p = new Pool();
  return *p;
}

}  // namespace

bool inside_parallel_for() { return tl_in_loop; }

int64_t cross_cpu_round_trip_ns() { return Pool::round_trip().load(std::memory_order_relaxed); }

int threads_for_round_trip(int64_t faces, int threads, int64_t round_trip_ns, bool worker_awake) {
  if (threads > 1 && faces < kSmallStepFaces && round_trip_ns > kFarRoundTripNs) return 1;
  if (threads > 1 && faces < kTinyStepFaces && !worker_awake) return 1;
  return threads;
}

int threads_for(int64_t faces, int threads) {
  if (threads <= 1 || faces >= kSmallStepFaces) return threads;
  // Small steps on one thread leave the pool idle: rouse() wakes the worker
  // for the calls after this one, or measures again when stale.
  const bool awake = pool().rouse();
  return threads_for_round_trip(faces, threads, cross_cpu_round_trip_ns(), awake);
}

void parallel_for(int64_t n, int threads, const Body& body, int64_t grain) {
  if (n <= 0) return;
  threads = resolve_threads(threads);
  grain = std::max<int64_t>(1, grain);
  threads = static_cast<int>(std::min<int64_t>(threads, (n + grain - 1) / grain));
  if (threads <= 1) {
    body(0, n);
    return;
  }
  // Exceptions (a memory budget, bad_alloc) are caught on every thread; all
  // threads finish before the first one is rethrown. Pieces: up to eight per
  // thread, never under the grain, of equal lengths and as many for each
  // thread. (Pieces of the grain with a shorter last one left one thread's
  // share short: a range of 1.8 grains on two threads went 1 : 0.8, and the
  // longer share set the time. Eight, not four: a level's data pass costs
  // more at its first corners than at its last, and a thread that has
  // finished its share takes the other's pieces one at a time.)
  int64_t pieces = std::min<int64_t>(8 * int64_t(threads), std::max<int64_t>(threads, n / grain));
  pieces -= pieces % threads;
  std::exception_ptr error;
  if (pool().run(n, threads - 1, pieces, body, error)) {
    if (error) std::rethrow_exception(error);
    return;
  }
  // Pool busy (nested or concurrent loops): threads of our own, one block
  // each. If one cannot be started, its block runs here.
  const int64_t block = (n + threads - 1) / threads;
  std::vector<std::exception_ptr> errors(threads);
  std::vector<std::thread> own;
  own.reserve(threads - 1);
  auto run = [&body, &errors](int t, int64_t b, int64_t e) {
    InLoop in_loop;
    try {
      body(b, e);
    } catch (...) {
      errors[t] = std::current_exception();
    }
  };
  for (int t = 1; t < threads; ++t) {
    const int64_t b = t * block, e = std::min(n, b + block);
    if (b >= e) continue;
    // A thread that cannot start (the system refuses one, or a memory budget
    // its state) runs its block here: an exception from here would destroy
    // the threads already started while they still run.
    try {
      own.emplace_back(run, t, b, e);
    } catch (...) {
      run(t, b, e);
    }
  }
  run(0, 0, std::min(n, block));
  for (std::thread& th : own) th.join();
  for (const std::exception_ptr& e : errors)
    if (e) std::rethrow_exception(e);
}

bool BesideWork::begin() {
  int idle = 0;
  return state_.compare_exchange_strong(idle, 1, std::memory_order_acq_rel);
}

void BesideWork::offer() {
  if (!begin()) return;
  try {
    work_();
  } catch (...) {
    error_ = std::current_exception();
  }
  state_.store(2, std::memory_order_release);
}

void BesideWork::finish() {
  if (begin()) {
    // Done (or failed) here: nothing to wait for afterwards.
    struct Done {
      std::atomic<int>& state;
      ~Done() { state.store(2, std::memory_order_release); }
    } done{state_};
    work_();
    return;
  }
  wait_for(state_, 2);
  if (error_) std::rethrow_exception(std::exchange(error_, nullptr));
}

}  // namespace iteas
