#include "core/parallel.h"

#include <algorithm>
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
  std::vector<std::thread> pool;
  pool.reserve(threads - 1);
  const int64_t block = (n + threads - 1) / threads;
  for (int t = 1; t < threads; ++t) {
    const int64_t b = t * block, e = std::min(n, b + block);
    if (b < e) pool.emplace_back([&body, b, e] { body(b, e); });
  }
  body(0, std::min(n, block));
  for (std::thread& th : pool) th.join();
}

}  // namespace iteas
