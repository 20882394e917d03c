#include "server/job_store.h"

#include <unistd.h>

#include <algorithm>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <random>
#include <sstream>
#include <thread>

namespace iteas {
namespace fs = std::filesystem;

namespace {

bool write_atomically(const std::string& target, const char* data, size_t size) {
  static thread_local std::mt19937_64 rng{std::random_device{}()};
  const std::string tmp = target + ".tmp" + std::to_string(rng());
  {
    std::ofstream f(tmp, std::ios::binary | std::ios::trunc);
    if (!f) return false;
    f.write(data, std::streamsize(size));
    if (!f.flush()) { std::error_code ec; fs::remove(tmp, ec); return false; }
  }
  std::error_code ec;
  fs::rename(tmp, target, ec);
  if (ec) fs::remove(tmp, ec);
  return !ec;
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

void JobStore::put(const std::string& id, const StoredJob& job, const std::vector<uint8_t>* result) const {
  if (!enabled()) return;
  if (delay_ms_ > 0) std::this_thread::sleep_for(std::chrono::milliseconds(delay_ms_));
  // The result first: a status that says "done" always finds its bytes.
  if (result) write_atomically(path(id, ".result"), reinterpret_cast<const char*>(result->data()), result->size());
  const std::string text =
      nlohmann::json{{"status", job.status}, {"http_status", job.http_status}, {"content_type", job.content_type}}.dump();
  write_atomically(path(id, ".json"), text.data(), text.size());
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
