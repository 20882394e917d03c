// A bounded work queue in front of a fixed pool of workers. Submitting to a
// full queue fails at once (the HTTP layer answers 429): there is no unbounded
// queue anywhere. Jobs expire after a TTL and held results have a byte cap.
#pragma once

#include <atomic>
#include <chrono>
#include <condition_variable>
#include <cstdint>
#include <deque>
#include <functional>
#include <map>
#include <memory>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include <nlohmann/json.hpp>

#include "io/pipeline.h"

namespace iteas {

enum class JobState { kQueued, kRunning, kDone, kFailed, kCancelled };
const char* job_state_name(JobState s);

struct Job {
  std::string id;
  bool listed = true;  // false for synchronous requests (not reachable by id)
  std::vector<uint8_t> input;
  JobRequest request;  // data/size point into |input|
  int64_t memory_estimate = 0;  // estimate_job_bytes(): reserved while it runs
  std::atomic<bool> cancel{false};
  std::chrono::steady_clock::time_point created, finished;

  // Guarded by |mu|.
  mutable std::mutex mu;
  std::condition_variable changed;
  JobState state = JobState::kQueued;
  int level = 0;
  std::string phase = "queued";
  double fraction = 0;
  nlohmann::json stats;
  std::vector<uint8_t> result;
  Status error;

  nlohmann::json status_json() const;  // takes |mu|
  nlohmann::json status_json_locked() const;  // |mu| held by the caller
  bool finished_state() const { return state == JobState::kDone || state == JobState::kFailed || state == JobState::kCancelled; }
};

struct QueueLimits {
  int workers = 2;
  size_t capacity = 16;                // queued (not yet running) jobs
  std::chrono::seconds ttl{600};       // finished jobs are forgotten after this
  size_t result_bytes_cap = 512u << 20;  // bytes of finished results held at once
  // Memory (0: unbounded): a quarter for held uploads, the rest for running
  // jobs, each reserving its estimate and confined to it by a MemoryBudget.
  int64_t memory_limit = 0;
  // Memory the jobs freed goes back to the system (malloc_trim) once no job
  // has run for this long; 0: after every job. Kept, the next job reuses the
  // pages instead of faulting them in afresh.
  std::chrono::milliseconds trim_delay{1000};
  // Freed memory held past this (the process's resident bytes beyond the
  // heap in use) goes back at once, busy or not: 0 is min(256 MiB, an
  // eighth of memory_limit), or 256 MiB without a memory limit.
  int64_t keep_freed_bytes = 0;
  // The most threads of the core a job gets (0: all cores). A job gets the
  // cores no running job holds, less one for each waiting job an idle
  // worker could start, and at least one: alone, every core; beside
  // others, one. The result is the same on any number of threads; the work
  // around the core's loops stays on the job's own thread
  // (JobRequest::outer_threads), under its budget.
  int lone_job_threads = 0;
};

enum class Admission { kAccepted, kQueueFull, kClosed, kTooBig, kUploadsFull };

class JobQueue {
 public:
  JobQueue(const QueueLimits& limits, std::function<double()> now_ms);
  ~JobQueue();

  // Queues the job, or says why not: full queue, closed, a memory estimate
  // over the working share (413), or held uploads over their share (429).
  Admission submit(const std::shared_ptr<Job>& job);
  int64_t working_share() const { return limits_.memory_limit - limits_.memory_limit / 4; }
  int64_t reserved_bytes() const;
  std::shared_ptr<Job> find(const std::string& id);
  // Cancels a queued or running job and forgets it; false if unknown.
  bool remove(const std::string& id);

  // Stops taking work; lets running and queued jobs finish for |grace|, then
  // cancels what is left and joins the workers.
  void drain(std::chrono::milliseconds grace);

  // Called with each listed job when it is queued (under the queue's lock,
  // before a worker can see it), starts and ends: the shared store's writer.
  // Always with the job's |mu| held, the new state set: a client that sees
  // the state from this replica finds it in the store from any other (a job
  // reported done here had answered 409 from another replica until the store
  // caught up). Must not take |mu| itself.
  void set_observer(std::function<void(Job&)> f) { observer_ = std::move(f); }

  size_t queued() const;
  size_t running() const { return running_.load(); }
  // Times freed memory went back to the system (malloc_trim).
  int64_t trims() const { return trims_.load(); }
  // Jobs started, by the threads of the core they got.
  std::map<int, int64_t> started_by_threads() const;
  std::map<std::string, int64_t> counts_by_state() const;
  // The jobs (listed: reachable by id) not finished yet, queued or running:
  // the shared store's entries this replica keeps alive.
  std::vector<std::string> unfinished_ids() const;

 private:
  void work();
  void expire_locked();
  // Freed memory back to the system.
  void trim();
  // Whether the freed memory the process holds is past keep_freed_bytes.
  bool holding_too_much() const;

  QueueLimits limits_;
  std::function<double()> now_ms_;
  mutable std::mutex mu_;
  std::condition_variable wake_;
  std::deque<std::shared_ptr<Job>> queue_;
  std::map<std::string, std::shared_ptr<Job>> jobs_;  // listed jobs by id
  std::vector<std::thread> workers_;
  std::atomic<size_t> running_{0};
  std::function<void(Job&)> observer_;
  int64_t reserved_ = 0;      // estimates of running jobs (under mu_)
  int64_t held_uploads_ = 0;  // input bytes of queued jobs (under mu_)
  bool closed_ = false;
  // Idle since |idle_since_| with freed memory not yet trimmed (under mu_).
  bool trim_due_ = false;
  std::chrono::steady_clock::time_point idle_since_;
  std::atomic<int64_t> trims_{0};
  std::map<int, int64_t> started_by_threads_;  // (under mu_)
  int64_t cores_in_use_ = 0;                   // threads of the running jobs (under mu_)
};

}  // namespace iteas
