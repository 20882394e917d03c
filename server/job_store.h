// A job and result store shared by replicas (SPEC §8, scale-out): a directory
// that every replica mounts (a ReadWriteMany volume in Kubernetes). The replica
// that runs a job writes its status when it is queued, starts and ends, and its
// result when done; any replica answers GET /v1/jobs/{id}[/result] and DELETE
// from here when the job is not its own. Files are written to a temporary name
// and renamed, so a reader sees a whole file or none.
#pragma once

#include <chrono>
#include <cstdint>
#include <optional>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

namespace iteas {

struct StoredJob {
  nlohmann::json status;     // the body of GET /v1/jobs/{id}
  int http_status = 200;     // for a failed job: the status of its error
  std::string content_type;  // of the result
  // Why the store has no result for a job that is done (the replica that ran
  // it could not write it: a full volume, say); empty when it has it.
  std::string result_error;
};

class JobStore {
 public:
  explicit JobStore(std::string dir);
  bool enabled() const { return !dir_.empty(); }
  bool usable(std::string* error) const;  // the directory exists and is writable

  // Writes the job's status, and its result when given (before the status).
  // Returns "" when all was written, else what failed and the system's
  // reason; a result that could not be written is recorded as such in the
  // status (StoredJob::result_error).
  std::string put(const std::string& id, const StoredJob& job, const std::vector<uint8_t>* result = nullptr) const;
  std::optional<StoredJob> get(const std::string& id) const;
  bool result(const std::string& id, std::string* bytes) const;
  bool remove(const std::string& id) const;
  // Forgets jobs whose status was last written or touched longer than |ttl|
  // ago (and temporaries as old).
  void expire(std::chrono::seconds ttl) const;
  // Marks the job's status as current: its replica still holds the job
  // (queued or running), so the sweep of any replica keeps it.
  void touch(const std::string& id) const;

 private:
  std::string path(const std::string& id, const char* ext) const;
  std::string dir_;
  // Tests: ITEAS_TEST_STORE_DELAY_MS makes every put() wait that long first,
  // as a slow shared volume would (0: no wait).
  int delay_ms_ = 0;
};

}  // namespace iteas
