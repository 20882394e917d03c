#include "server/job_store.h"

#include <fcntl.h>
#include <unistd.h>

#include <cerrno>

#include <algorithm>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <random>
#include <sstream>
#include <system_error>
#include <thread>

#include "io/pipeline.h"

namespace iteas {
namespace fs = std::filesystem;

namespace {

// Writes |size| bytes to |target| through a temporary name beside it; ""
// when whole, else what failed and the system's reason (a full volume, a file
// size limit, a volume gone read-only). A failed write leaves no temporary.
std::string write_atomically(const std::string& target, const char* data, size_t size) {
  static thread_local std::mt19937_64 rng{std::random_device{}()};
  const std::string tmp = target + ".tmp" + std::to_string(rng());
  auto failed = [&](const char* what, int e) {
    return std::string("cannot ") + what + " " + tmp + ": " + std::error_code(e, std::generic_category()).message();
  };
  const int fd = ::open(tmp.c_str(), O_WRONLY | O_CREAT | O_TRUNC | O_CLOEXEC, 0644);
  if (fd < 0) return failed("create", errno);
  std::string error;
  for (size_t done = 0; done < size && error.empty();) {
    const ssize_t n = ::write(fd, data + done, size - done);
    if (n > 0) done += size_t(n);
    else if (n < 0 && errno == EINTR) continue;
    else error = failed("write", n < 0 ? errno : EIO);
  }
  // A network volume may report the failure only here.
  if (::close(fd) != 0 && error.empty()) error = failed("write", errno);
  if (error.empty() && ::rename(tmp.c_str(), target.c_str()) != 0) error = failed("rename", errno);
  if (!error.empty()) ::unlink(tmp.c_str());
  return error;
}

bool read_all(const std::string& file, std::string* out) {
  std::ifstream f(file, std::ios::binary);
  if (!f) return false;
  std::ostringstream s;
  s << f.rdbuf();
  *out = s.str();
  return true;
}

}  // namespace

JobStore::JobStore(std::string dir) : dir_(std::move(dir)) {
  if (const char* d = std::getenv("ITEAS_TEST_STORE_DELAY_MS")) delay_ms_ = std::clamp(std::atoi(d), 0, 10000);
}

std::string JobStore::path(const std::string& id, const char* ext) const { return dir_ + "/" + id + ext; }

bool JobStore::usable(std::string* error) const {
  if (!enabled()) return true;
  std::error_code ec;
  if (!fs::is_directory(dir_, ec)) { *error = "job store " + dir_ + " is not a directory"; return false; }
  if (access(dir_.c_str(), W_OK) != 0) { *error = "job store " + dir_ + " is not writable"; return false; }
  return true;
}

std::string JobStore::put(const std::string& id, const StoredJob& job, const std::vector<uint8_t>* result) const {
  if (!enabled()) return "";
  if (delay_ms_ > 0) std::this_thread::sleep_for(std::chrono::milliseconds(delay_ms_));
  // The result first: a status that says "done" always finds its bytes, or
  // says why the store could not take them.
  std::string error;
  if (result) error = write_atomically(path(id, ".result"), reinterpret_cast<const char*>(result->data()), result->size());
  nlohmann::json record{{"status", job.status}, {"http_status", job.http_status}, {"content_type", job.content_type}};
  if (!error.empty()) record["result_error"] = error;
  const std::string text = json_text(record);
  const std::string status_error = write_atomically(path(id, ".json"), text.data(), text.size());
  if (error.empty()) return status_error;
  return status_error.empty() ? error : error + "; " + status_error;
}

std::optional<StoredJob> JobStore::get(const std::string& id) const {
  if (!enabled()) return std::nullopt;
  std::string text;
  if (!read_all(path(id, ".json"), &text)) return std::nullopt;
  const nlohmann::json j = nlohmann::json::parse(text, nullptr, false);
  if (j.is_discarded() || !j.is_object() || !j.contains("status")) return std::nullopt;
  StoredJob s;
  s.status = j["status"];
  s.http_status = j.value("http_status", 200);
  s.content_type = j.value("content_type", std::string("application/octet-stream"));
  s.result_error = j.value("result_error", std::string());
  return s;
}

bool JobStore::result(const std::string& id, std::string* bytes) const {
  return enabled() && read_all(path(id, ".result"), bytes);
}

bool JobStore::remove(const std::string& id) const {
  if (!enabled()) return false;
  std::error_code ec;
  const bool had = fs::remove(path(id, ".json"), ec);
  fs::remove(path(id, ".result"), ec);
  return had;
}

void JobStore::touch(const std::string& id) const {
  if (!enabled()) return;
  std::error_code ec;
  fs::last_write_time(path(id, ".json"), fs::file_time_type::clock::now(), ec);
}

void JobStore::expire(std::chrono::seconds ttl) const {
  if (!enabled()) return;
  std::error_code ec;
  const auto now = fs::file_time_type::clock::now();
  for (const auto& entry : fs::directory_iterator(dir_, ec)) {
    std::error_code e2;
    const auto when = entry.last_write_time(e2);
    if (e2 || now - when < ttl) continue;
    fs::remove(entry.path(), e2);  // status, result or a stale temporary
  }
}

}  // namespace iteas
