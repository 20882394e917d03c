#include "core/parallel.h"

#include <algorithm>
#include <exception>
#include <system_error>
#include <thread>
#include <vector>

namespace iteas {

int hardware_threads() {
  unsigned n = std::thread::hardware_concurrency();
  return n == 0 ? 1 : static_cast<int>(n);
}

void parallel_for(int64_t n, int threads, const std::function<void(int64_t, int64_t)>& body, int64_t grain) {
  if (n <= 0) return;
  if (threads <= 0) threads = hardware_threads();
  grain = std::max<int64_t>(1, grain);
  threads = static_cast<int>(std::min<int64_t>(threads, (n + grain - 1) / grain));
  if (threads <= 1) {
    body(0, n);
    return;
  }
  // Exceptions (a memory budget, bad_alloc) are caught on every thread; all
  // threads are joined before the first one is rethrown. If a thread cannot be
  // started, its block runs here.
  const int64_t block = (n + threads - 1) / threads;
  std::vector<std::exception_ptr> errors(threads);
  std::vector<std::thread> pool;
  pool.reserve(threads - 1);
  auto run = [&body, &errors](int t, int64_t b, int64_t e) {
    try {
      body(b, e);
    } catch (...) {
      errors[t] = std::current_exception();
    }
  };
  for (int t = 1; t < threads; ++t) {
    const int64_t b = t * block, e = std::min(n, b + block);
    if (b >= e) continue;
    try {
      pool.emplace_back(run, t, b, e);
    } catch (const std::system_error&) {
      run(t, b, e);
    }
  }
  run(0, 0, std::min(n, block));
  for (std::thread& th : pool) th.join();
  for (const std::exception_ptr& error : errors)
    if (error) std::rethrow_exception(error);
}

}  // namespace iteas
