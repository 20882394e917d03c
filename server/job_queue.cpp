#include "server/job_queue.h"

#include <malloc.h>
#include <unistd.h>

#include <algorithm>
#include <cstdio>
#include <iterator>
#include <limits>

#include "core/mesh.h"
#include "core/parallel.h"
#include "io/memory_budget.h"

namespace iteas {

const char* job_state_name(JobState s) {
  switch (s) {
    case JobState::kQueued: return "queued";
    case JobState::kRunning: return "running";
    case JobState::kDone: return "done";
    case JobState::kFailed: return "failed";
    case JobState::kCancelled: return "cancelled";
  }
  return "failed";
}

nlohmann::json Job::status_json() const {
  std::lock_guard<std::mutex> lock(mu);
  return status_json_locked();
}

nlohmann::json Job::status_json_locked() const {
  nlohmann::json j = {{"id", id},
                      {"status", job_state_name(state)},
                      {"progress", {{"level", level}, {"phase", phase}, {"fraction", fraction}}}};
  if (state == JobState::kDone) j["statistics"] = stats;
  if (state == JobState::kFailed) j["error"] = {{"code", error.code}, {"message", error.message}};
  return j;
}

JobQueue::JobQueue(const QueueLimits& limits, std::function<double()> now_ms)
    : limits_(limits), now_ms_(std::move(now_ms)) {
  if (limits_.keep_freed_bytes <= 0)
    limits_.keep_freed_bytes = limits_.memory_limit > 0 ? std::min<int64_t>(256 << 20, limits_.memory_limit / 8) : 256 << 20;
  for (int i = 0; i < std::max(1, limits_.workers); ++i) workers_.emplace_back([this] { work(); });
}

JobQueue::~JobQueue() { drain(std::chrono::milliseconds(0)); }

Admission JobQueue::submit(const std::shared_ptr<Job>& job) {
  std::lock_guard<std::mutex> lock(mu_);
  expire_locked();
  if (closed_) return Admission::kClosed;
  if (limits_.memory_limit > 0 && job->memory_estimate > working_share()) return Admission::kTooBig;
  if (queue_.size() >= limits_.capacity) return Admission::kQueueFull;
  const int64_t input = int64_t(job->input.size());
  if (limits_.memory_limit > 0 && held_uploads_ + input > limits_.memory_limit / 4) return Admission::kUploadsFull;
  held_uploads_ += input;
  job->created = std::chrono::steady_clock::now();
  queue_.push_back(job);
  if (job->listed) {
    jobs_[job->id] = job;
    if (observer_) {
      std::lock_guard<std::mutex> jl(job->mu);
      observer_(*job);
    }
  }
  wake_.notify_all();
  return Admission::kAccepted;
}

int64_t JobQueue::reserved_bytes() const {
  std::lock_guard<std::mutex> lock(mu_);
  return reserved_;
}

std::shared_ptr<Job> JobQueue::find(const std::string& id) {
  std::lock_guard<std::mutex> lock(mu_);
  expire_locked();
  auto it = jobs_.find(id);
  return it == jobs_.end() ? nullptr : it->second;
}

bool JobQueue::remove(const std::string& id) {
  std::shared_ptr<Job> job;
  {
    std::lock_guard<std::mutex> lock(mu_);
    auto it = jobs_.find(id);
    if (it == jobs_.end()) return false;
    job = it->second;
    jobs_.erase(it);
    for (auto q = queue_.begin(); q != queue_.end(); ++q)
      if (*q == job) { held_uploads_ -= int64_t(job->input.size()); queue_.erase(q); break; }
    wake_.notify_all();
  }
  job->cancel = true;
  std::lock_guard<std::mutex> lock(job->mu);
  if (job->state == JobState::kQueued) {
    job->state = JobState::kCancelled;
    job->finished = std::chrono::steady_clock::now();
  }
  job->changed.notify_all();
  return true;
}

void JobQueue::drain(std::chrono::milliseconds grace) {
  {
    std::lock_guard<std::mutex> lock(mu_);
    if (workers_.empty()) return;
    closed_ = true;
    wake_.notify_all();
  }
  const auto deadline = std::chrono::steady_clock::now() + grace;
  while (std::chrono::steady_clock::now() < deadline) {
    {
      std::lock_guard<std::mutex> lock(mu_);
      if (queue_.empty() && running_ == 0) break;
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  }
  std::vector<std::shared_ptr<Job>> left;
  {
    std::lock_guard<std::mutex> lock(mu_);
    left.assign(queue_.begin(), queue_.end());
    queue_.clear();
    for (auto& [id, job] : jobs_) job->cancel = true;
  }
  for (auto& job : left) {
    job->cancel = true;
    {
      std::lock_guard<std::mutex> lock(job->mu);
      job->state = JobState::kCancelled;
      job->finished = std::chrono::steady_clock::now();
      if (job->listed && observer_) observer_(*job);
      job->changed.notify_all();
    }
  }
  for (std::thread& t : workers_) t.join();
  workers_.clear();
}

std::map<int, int64_t> JobQueue::started_by_threads() const {
  std::lock_guard<std::mutex> lock(mu_);
  return started_by_threads_;
}

size_t JobQueue::queued() const {
  std::lock_guard<std::mutex> lock(mu_);
  return queue_.size();
}

std::map<std::string, int64_t> JobQueue::counts_by_state() const {
  std::map<std::string, int64_t> out = {{"queued", 0}, {"running", 0}, {"done", 0}, {"failed", 0}, {"cancelled", 0}};
  std::lock_guard<std::mutex> lock(mu_);
  for (const auto& [id, job] : jobs_) {
    std::lock_guard<std::mutex> jl(job->mu);
    ++out[job_state_name(job->state)];
  }
  return out;
}

std::vector<std::string> JobQueue::unfinished_ids() const {
  std::vector<std::string> ids;
  std::lock_guard<std::mutex> lock(mu_);
  for (const auto& [id, job] : jobs_) {
    std::lock_guard<std::mutex> jl(job->mu);
    if (!job->finished_state()) ids.push_back(id);
  }
  return ids;
}

void JobQueue::expire_locked() {
  const auto now = std::chrono::steady_clock::now();
  // TTL first, then the oldest finished results until under the byte cap.
  std::vector<std::pair<std::chrono::steady_clock::time_point, std::string>> finished;
  size_t bytes = 0;
  for (auto it = jobs_.begin(); it != jobs_.end();) {
    bool expired = false;
    {
      Job& job = *it->second;
      std::lock_guard<std::mutex> jl(job.mu);
      if (job.finished_state()) {
        expired = now - job.finished > limits_.ttl;
        if (!expired) {
          finished.emplace_back(job.finished, it->first);
          bytes += job.result.size();
        }
      }
    }
    // Erased only once its lock is released: the map may hold the job's last
    // reference, and the lock's mutex is a member of the job.
    it = expired ? jobs_.erase(it) : std::next(it);
  }
  std::sort(finished.begin(), finished.end());
  for (const auto& [t, id] : finished) {
    if (bytes <= limits_.result_bytes_cap) break;
    auto it = jobs_.find(id);
    bytes -= it->second->result.size();
    jobs_.erase(it);
  }
}

void JobQueue::work() {
  while (true) {
    std::shared_ptr<Job> job;
    int threads = 1;
    {
      std::unique_lock<std::mutex> lock(mu_);
      // FIFO, and the head starts only when its estimate fits beside the
      // running jobs' (or nothing runs: it then has the whole working share).
      auto fits = [&] {
        return limits_.memory_limit <= 0 || running_ == 0 ||
               reserved_ + queue_.front()->memory_estimate <= working_share();
      };
      auto ready = [&] { return (closed_ && queue_.empty()) || (!queue_.empty() && fits()); };
      // Idle with memory to give back: a worker waits out the delay, and
      // trims if no job came (the one that finished last, usually).
      while (!ready()) {
        if (!trim_due_) {
          wake_.wait(lock);
          continue;
        }
        const auto due = idle_since_ + limits_.trim_delay;
        if (std::chrono::steady_clock::now() < due) {
          wake_.wait_until(lock, due);
          continue;
        }
        trim_due_ = false;
        lock.unlock();
        trim();
        lock.lock();
      }
      if (queue_.empty()) return;  // closed and nothing left
      job = queue_.front();
      queue_.pop_front();
      held_uploads_ -= int64_t(job->input.size());
      reserved_ += job->memory_estimate;
      // The cores no running job holds, less one for each waiting job an
      // idle worker could start now (at least one, at most
      // lone_job_threads): a job alone gets every core and one beside others
      // one, as do they; a lone worker's job gets every core even with jobs
      // waiting (they could not start before it ends anyway).
      const int64_t idle_workers = std::max<int64_t>(0, int64_t(std::max(1, limits_.workers)) - int64_t(running_) - 1);
      const int64_t startable = std::min<int64_t>(int64_t(queue_.size()), idle_workers);
      const int64_t free_cores = int64_t(hardware_threads()) - cores_in_use_ - startable;
      threads = int(std::clamp<int64_t>(free_cores, 1, resolve_threads(limits_.lone_job_threads)));
      cores_in_use_ += threads;
      ++started_by_threads_[threads];
      ++running_;
      trim_due_ = false;  // busy again: its pages are in use
    }
    {
      std::lock_guard<std::mutex> jl(job->mu);
      job->state = JobState::kRunning;
      job->phase = "decode";
      if (job->listed && observer_) observer_(*job);
      job->changed.notify_all();
    }
    JobHooks hooks;
    hooks.now_ms = now_ms_;
    hooks.cancel = &job->cancel;
    hooks.progress = [&job](int level, const char* phase, double fraction) {
      std::lock_guard<std::mutex> jl(job->mu);
      if (level > 0) job->level = level;
      job->phase = phase;
      job->fraction = fraction;
    };
    JobResult result;
    Status status;
    try {
      // Everything this job allocates on this thread counts against its estimate.
      MemoryBudget budget(limits_.memory_limit > 0 ? job->memory_estimate : std::numeric_limits<int64_t>::max());
      JobRequest request = job->request;
      request.options.refine.threads = threads;
      request.outer_threads = 1;
      status = job->cancel ? Status() : run_job(request, hooks, &result);
    } catch (const MemoryLimitExceeded&) {
      result = JobResult();
      status = Status::Error(ErrorKind::kTooLarge, "memory_budget",
                             "the job outgrew its memory estimate of " + std::to_string(job->memory_estimate >> 20) +
                                 " MiB (lower levels or max_triangles)");
    } catch (const std::bad_alloc&) {
      status = Status::Error(ErrorKind::kTooLarge, "out_of_memory", "the job needs more memory than the server has");
    } catch (const std::exception& e) {
      // A reader or library threw what it should have reported: the job fails,
      // the worker and the server live on (the fuzzers hunt these down).
      result = JobResult();
      status = Status::Error(ErrorKind::kBadInput, "unreadable", std::string("the input could not be processed: ") + e.what());
    }
    {
      std::lock_guard<std::mutex> jl(job->mu);
      if (job->cancel || result.cancelled) {
        job->state = JobState::kCancelled;
      } else if (!status.ok()) {
        job->state = JobState::kFailed;
        job->error = status;
      } else {
        job->state = JobState::kDone;
        job->stats = std::move(result.stats);
        job->result = std::move(result.bytes);
        job->phase = "done";
        job->fraction = 1;
      }
      job->input.clear();
      job->input.shrink_to_fit();
      job->finished = std::chrono::steady_clock::now();
      if (job->listed && observer_) observer_(*job);
      job->changed.notify_all();
    }
    const bool trim_now = limits_.trim_delay.count() <= 0 || holding_too_much();
    {
      std::lock_guard<std::mutex> lock(mu_);
      reserved_ -= job->memory_estimate;
      cores_in_use_ -= threads;
      --running_;
      // The last job of a busy spell: its memory goes back once the queue
      // has stayed idle for trim_delay (work() above). While jobs follow
      // one another they reuse the pages the ones before them freed (one
      // request after another at the defaults, medians: bunny.off's refine
      // 20.5-20.8 -> 19.3-19.9 ms, bun_zipper's 38.7 -> 36.2-37.1 ms and
      // its requests 78.0-81.5 -> 73.1-74.8 ms, when every job had trimmed
      // and faulted its pages in afresh).
      if (!trim_now && running_ == 0 && queue_.empty()) {
        trim_due_ = true;
        idle_since_ = std::chrono::steady_clock::now();
      }
      wake_.notify_all();
    }
    if (trim_now) trim();
  }
}

void JobQueue::trim() {
  malloc_trim(0);
  forget_resident_memory();
  ++trims_;
}

bool JobQueue::holding_too_much() const {
  // Resident pages beyond the heap in use: what the allocator keeps freed,
  // plus the program itself and its stacks (counted as held: a little
  // early, never late).
  long pages = 0, resident = 0;
  if (FILE* f = std::fopen("/proc/self/statm", "r")) {
    if (std::fscanf(f, "%ld %ld", &pages, &resident) != 2) resident = 0;
    std::fclose(f);
  }
  const int64_t rss = int64_t(resident) * int64_t(sysconf(_SC_PAGESIZE));
  return rss - current_heap_bytes() > limits_.keep_freed_bytes;
}

}  // namespace iteas
