// The HTTP layer. This is the only file that includes httplib.h. Every
// handler runs inside one wrapper that maps failures to the error envelope
// {"error": {"code", "message", "status"}} of SPEC §7.
#include "server/server.h"

#include <httplib.h>
#include <signal.h>
#include <strings.h>
#include <spdlog/sinks/stdout_sinks.h>
#include <spdlog/spdlog.h>

#include <algorithm>
#include <atomic>
#include <cctype>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <condition_variable>
#include <functional>
#include <map>
#include <mutex>
#include <optional>
#include <random>
#include <regex>
#include <set>
#include <thread>
#include <utility>
#include <vector>

#include <unistd.h>

#include "core/parallel.h"
#include "server/connection.h"
#include "server/job_queue.h"
#include "server/job_store.h"
#include "io/memory_budget.h"

namespace iteas {

extern const char* kOpenApiYaml;  // generated from proto/openapi.yaml

namespace {

using json = nlohmann::json;
using Clock = std::chrono::steady_clock;

double now_ms() {
  return std::chrono::duration<double, std::milli>(Clock::now().time_since_epoch()).count();
}

// --- metrics -----------------------------------------------------------------
class Metrics {
 public:
  static constexpr double kBuckets[] = {0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1, 2.5, 5, 10, 30, 60};
  // |seconds| < 0: the request's start is unknown (it failed before routing);
  // it is counted, and left out of the duration histogram.
  void observe(const std::string& route, int status, double seconds) {
    std::lock_guard<std::mutex> lock(mu_);
    ++requests_[{route, status}];
    if (seconds < 0) return;
    auto& h = hist_[route];
    if (h.empty()) h.assign(std::size(kBuckets) + 1, 0);
    size_t i = 0;
    while (i < std::size(kBuckets) && seconds > kBuckets[i]) ++i;
    ++h[i];
    sums_[route] += seconds;
  }
  void store_error() { ++store_errors_; }
  void triangles(int64_t in, int64_t out) {
    tri_in_ += in;
    tri_out_ += out;
  }
  std::string text(const JobQueue& q) {
    std::lock_guard<std::mutex> lock(mu_);
    std::string s;
    s += "# HELP iteas_requests_total HTTP requests by route and status.\n# TYPE iteas_requests_total counter\n";
    for (const auto& [k, v] : requests_)
      s += "iteas_requests_total{route=\"" + k.first + "\",status=\"" + std::to_string(k.second) + "\"} " + std::to_string(v) + "\n";
    s += "# HELP iteas_request_duration_seconds Request latency.\n# TYPE iteas_request_duration_seconds histogram\n";
    for (const auto& [route, h] : hist_) {
      int64_t cum = 0;
      for (size_t i = 0; i < h.size(); ++i) {
        cum += h[i];
        const std::string le = i < std::size(kBuckets) ? fmt(kBuckets[i]) : "+Inf";
        s += "iteas_request_duration_seconds_bucket{route=\"" + route + "\",le=\"" + le + "\"} " + std::to_string(cum) + "\n";
      }
      s += "iteas_request_duration_seconds_sum{route=\"" + route + "\"} " + fmt(sums_[route]) + "\n";
      s += "iteas_request_duration_seconds_count{route=\"" + route + "\"} " + std::to_string(cum) + "\n";
    }
    s += "# HELP iteas_queue_depth Jobs waiting for a worker.\n# TYPE iteas_queue_depth gauge\niteas_queue_depth " +
         std::to_string(q.queued()) + "\n";
    s += "# HELP iteas_jobs_running Jobs being refined.\n# TYPE iteas_jobs_running gauge\niteas_jobs_running " +
         std::to_string(q.running()) + "\n";
    s += "# HELP iteas_memory_reserved_bytes Memory estimates of running jobs.\n# TYPE iteas_memory_reserved_bytes gauge\n"
         "iteas_memory_reserved_bytes " + std::to_string(q.reserved_bytes()) + "\n";
    s += "# HELP iteas_heap_bytes Heap held through operator new.\n# TYPE iteas_heap_bytes gauge\niteas_heap_bytes " +
         std::to_string(current_heap_bytes()) + "\n";
    s += "# HELP iteas_jobs_started_total Jobs started, by the core's threads they got.\n# TYPE iteas_jobs_started_total counter\n";
    for (const auto& [threads, n] : q.started_by_threads())
      s += "iteas_jobs_started_total{threads=\"" + std::to_string(threads) + "\"} " + std::to_string(n) + "\n";
    s += "# HELP iteas_heap_trims_total Times freed memory went back to the system.\n# TYPE iteas_heap_trims_total counter\n"
         "iteas_heap_trims_total " + std::to_string(q.trims()) + "\n";
    s += "# HELP iteas_jobs Jobs held, by status.\n# TYPE iteas_jobs gauge\n";
    for (const auto& [state, n] : q.counts_by_state())
      s += "iteas_jobs{status=\"" + state + "\"} " + std::to_string(n) + "\n";
    s += "# HELP iteas_triangles_in_total Input triangles of finished jobs.\n# TYPE iteas_triangles_in_total counter\n"
         "iteas_triangles_in_total " + std::to_string(tri_in_.load()) + "\n";
    s += "# HELP iteas_triangles_out_total Output triangles of finished jobs.\n# TYPE iteas_triangles_out_total counter\n"
         "iteas_triangles_out_total " + std::to_string(tri_out_.load()) + "\n";
    s += "# HELP iteas_job_store_errors_total Job statuses or results the job store could not take.\n"
         "# TYPE iteas_job_store_errors_total counter\n"
         "iteas_job_store_errors_total " + std::to_string(store_errors_.load()) + "\n";
    return s;
  }

 private:
  static std::string fmt(double x) {
    char b[32];
    std::snprintf(b, sizeof b, "%g", x);
    return b;
  }
  std::mutex mu_;
  std::map<std::pair<std::string, int>, int64_t> requests_;
  std::map<std::string, std::vector<int64_t>> hist_;
  std::map<std::string, double> sums_;
  std::atomic<int64_t> tri_in_{0}, tri_out_{0}, store_errors_{0};
};

// --- helpers -------------------------------------------------------------------
struct HttpError {
  int status;
  std::string code, message;
};

void send_error(httplib::Response& res, int status, const std::string& code, const std::string& message) {
  res.status = status;
  res.set_content(json_text(json{{"error", {{"code", code}, {"message", message}, {"status", status}}}}), "application/json");
}

int status_for(const Status& s) {
  switch (s.kind) {
    case ErrorKind::kBadInput: return 400;
    case ErrorKind::kUnsupported: return 415;
    case ErrorKind::kUnusable: return 422;
    case ErrorKind::kTooLarge: return 413;
    default: return 400;
  }
}

const char* content_type_for(const std::string& format) {
  if (format == "glb") return "model/gltf-binary";
  if (format == "gltf") return "model/gltf+json";
  if (format == "obj") return "model/obj";
  if (format == "ply") return "application/ply";
  return "application/octet-stream";
}

std::string route_of(const std::string& path) {
  if (path.rfind("/v1/jobs/", 0) == 0) return path.size() > 16 && path.find("/result") != std::string::npos ? "/v1/jobs/{id}/result" : "/v1/jobs/{id}";
  static const char* known[] = {"/v1/refine", "/v1/jobs", "/healthz", "/readyz", "/metrics", "/v1/openapi.yaml"};
  for (const char* k : known) if (path == k) return k;
  return "other";
}

// The job routes' patterns, as registered (httplib matches them whole).
const char* const kJobRoute = R"(/v1/jobs/([0-9a-f]{1,64}))";
const char* const kJobResultRoute = R"(/v1/jobs/([0-9a-f]{1,64})/result)";

// The methods a route takes, for a 405's Allow header; empty where no route
// has the path.
std::string allowed_methods(const std::string& path) {
  static const std::regex job(kJobRoute), job_result(kJobResultRoute);
  if (path == "/v1/refine" || path == "/v1/jobs") return "POST";
  if (path == "/healthz" || path == "/readyz" || path == "/metrics" || path == "/v1/openapi.yaml") return "GET, HEAD";
  if (std::regex_match(path, job)) return "GET, HEAD, DELETE";
  if (std::regex_match(path, job_result)) return "GET, HEAD";
  return "";
}

// Can |s| go into the log as it is: 1-64 characters of [A-Za-z0-9._:-]?
// A client's X-Request-Id (UUIDs, trace ids) is kept only then, else it gets
// a new id: a quote in it forged fields of a JSON log line. So is a method
// (httplib may have set one it then refused).
bool loggable_token(const std::string& s) {
  if (s.empty() || s.size() > 64) return false;
  return std::all_of(s.begin(), s.end(), [](char c) {
    return std::isalnum(static_cast<unsigned char>(c)) || c == '.' || c == '_' || c == ':' || c == '-';
  });
}

// The path of a request target in absolute form ("http://host:port/a/b"
// -> "/a/b", "http://host" -> "/"); any other path as it is.
std::string origin_form(const std::string& path) {
  size_t scheme = 0;
  for (const char* s : {"http://", "https://"})
    if (path.size() >= std::strlen(s) && strncasecmp(path.c_str(), s, std::strlen(s)) == 0) scheme = std::strlen(s);
  if (scheme == 0) return path;
  const size_t slash = path.find('/', scheme);
  return slash == std::string::npos ? "/" : path.substr(slash);
}

// The routes that take an upload (read by read_upload, to --max-upload-bytes).
// Asked also before routing, where the path is still as it came.
bool is_upload(const httplib::Request& req) {
  const std::string path = origin_form(req.path);
  return req.method == "POST" && (path == "/v1/refine" || path == "/v1/jobs");
}

// A Range header the connection's stream deferred (kDeferredRange) gets its
// name back, and the request the ranges it asks for, when it is a GET and
// there is one such header that parses as bytes ranges. Any other is
// dropped, and so ignored (RFC 9110 §14.2: Range is defined for GET alone,
// a unit the server does not know must be ignored, and a malformed one may
// be); httplib answered the malformed ones 416 itself, honoured the others
// on any method and status, and answers a file of the web page 206 whenever
// the request has a Range header.
void take_deferred_range(httplib::Request& req) {
  std::vector<std::string> values;
  const auto [first, last] = req.headers.equal_range(kDeferredRange);
  for (auto it = first; it != last; ++it) values.push_back(it->second);
  req.headers.erase(first, last);
  req.ranges.clear();
  if (req.method != "GET" || values.size() != 1) return;
  httplib::Ranges ranges;
  if (!httplib::detail::parse_range_header(values.front(), ranges)) return;
  // httplib's parser takes "bytes=-" as a range (the whole); it is none.
  for (const auto& [from, to] : ranges)
    if (from < 0 && to < 0) return;
  req.ranges = std::move(ranges);
  req.headers.emplace("Range", values.front());
}

// More ranges than this in one request are not served one by one.
constexpr size_t kMaxRanges = 16;

// The ranges of a GET, fitted to its answer before httplib slices it (RFC
// 9110 §14.1.2): a last position past the end ends at the end (httplib
// wrote "bytes 2-99999/60" for a 60-byte answer), and a range that starts
// past it, or a suffix of no bytes, is dropped. When none is left, 416 with
// "Content-Range: bytes */length" (httplib answered an empty 416). Ranges
// that together ask for more than the answer, or more than kMaxRanges of
// them, get the whole answer (RFC 9110 §14.2 lets a server ignore them):
// httplib built every part in memory, so 2,700 copies of "0-" in an 8 KB
// header turned a 708 KB result into a 1.9 GB answer. An answer whose
// handler set its status is whole: httplib sliced a body but kept a 200.
void fit_ranges(httplib::Request& req, httplib::Response& res) {
  if (req.ranges.empty()) return;
  if (res.status != -1) {
    req.ranges.clear();
    return;
  }
  const auto size = static_cast<ssize_t>(res.body.size());
  httplib::Ranges fitted;
  ssize_t asked = 0;
  for (auto [from, to] : req.ranges) {
    if (from < 0) {  // a suffix: the last |to| bytes
      from = std::max<ssize_t>(0, size - to);
      to = to > 0 ? size - 1 : -1;
    } else {
      to = to < 0 ? size - 1 : std::min(to, size - 1);
    }
    if (from >= size || from > to) continue;
    fitted.emplace_back(from, to);
    asked += to - from + 1;
  }
  if (asked > size || fitted.size() > kMaxRanges) {
    req.ranges.clear();
    return;
  }
  req.ranges = std::move(fitted);
  if (!req.ranges.empty()) return;
  send_error(res, 416, "range_not_satisfiable",
             fmt::format("no range of the Range header is within the answer's {} bytes", size));
  res.set_header("Content-Range", fmt::format("bytes */{}", size));
}

// The Content-Length a request declares (0 without one).
uint64_t declared_length(const httplib::Request& req) {
  return std::strtoull(req.get_header_value("Content-Length").c_str(), nullptr, 10);
}

// Why httplib refused a request line that has the form "method target
// version": a method it does not know (a token of letters, digits and
// -._), or a version of the form HTTP/d.d other than 1.0 and 1.1.
enum class RequestLineFault { kOther, kUnknownMethod, kUnsupportedVersion };
RequestLineFault request_line_fault(const httplib::Request& req) {
  static const std::set<std::string> methods{"GET", "HEAD", "POST", "PUT", "DELETE", "CONNECT", "OPTIONS", "TRACE", "PATCH", "PRI"};
  const std::string& v = req.version;
  const bool version_form = v.size() == 8 && v.compare(0, 5, "HTTP/") == 0 && std::isdigit(static_cast<unsigned char>(v[5])) &&
                            v[6] == '.' && std::isdigit(static_cast<unsigned char>(v[7]));
  if (!version_form || req.target.empty() || !loggable_token(req.method)) return RequestLineFault::kOther;
  if (!methods.count(req.method)) return RequestLineFault::kUnknownMethod;
  if (v != "HTTP/1.1" && v != "HTTP/1.0") return RequestLineFault::kUnsupportedVersion;
  return RequestLineFault::kOther;
}

// What httplib 0.11 would take wrongly (RFC 9112 §5, §6): header lines it
// drops or decodes (connection_head_fault); a Content-Length that is not a
// number (it reads "abc" as 0 and "5x" as 5, so the body's bytes were parsed
// as the next request) or given twice with different values; a
// Transfer-Encoding other than "chunked" alone (it read "gzip, chunked" as no
// encoding, and the body until the connection closed). The status, code and
// message to answer, or status 0.
struct FramingError {
  int status = 0;
  std::string code, message;
};
FramingError framing_error(const httplib::Request& req) {
  if (std::string fault = connection_head_fault(); !fault.empty()) return {400, "bad_header", std::move(fault)};
  const std::string length = req.get_header_value("Content-Length");
  for (size_t i = 0, n = req.get_header_value_count("Content-Length"); i < n; ++i) {
    const std::string v = req.get_header_value("Content-Length", i);
    if (v.empty() || v.size() > 19 || v.find_first_not_of("0123456789") != std::string::npos || v != length)
      return {400, "bad_content_length", "Content-Length must be one decimal number of bytes"};
  }
  // httplib's values come without the spaces round them.
  const size_t encodings = req.get_header_value_count("Transfer-Encoding");
  if (encodings > 1 || (encodings == 1 && strcasecmp(req.get_header_value("Transfer-Encoding").c_str(), "chunked") != 0))
    return {501, "unsupported_transfer_encoding", "the Transfer-Encoding taken is chunked alone (a Content-Encoding may compress an upload)"};
  return {};
}

// |text| with each byte |pick| chooses written as |format| gives its code
// ("%%%02X", "\\x%02X").
std::string escaped(const std::string& text, bool (*pick)(unsigned char), const char* format) {
  std::string out;
  out.reserve(text.size());
  for (unsigned char c : text) {
    if (pick(c)) {
      char b[8];
      std::snprintf(b, sizeof b, format, c);
      out += b;
    } else {
      out += char(c);
    }
  }
  return out;
}

// The request's path as the text log writes it: httplib decodes it, so a
// %0A in the URL put a line of the client's own into the log; control
// characters, spaces, backslashes and '%' itself are percent-encoded again.
std::string loggable_path(const std::string& path) {
  if (path.empty()) return "-";  // a request line httplib could not parse
  return escaped(path, [](unsigned char c) { return c <= 0x20 || c == 0x7f || c == '%' || c == '\\'; }, "%%%02X");
}

// Free text for the text log, on one line: control characters and
// backslashes escaped (a message may quote what a client or the system said).
std::string one_line(const std::string& text) {
  return escaped(text, [](unsigned char c) { return c < 0x20 || c == 0x7f || c == '\\'; }, "\\x%02X");
}

std::string new_id() {
  static std::atomic<uint64_t> counter{0};
  thread_local std::mt19937_64 rng(std::random_device{}());
  char b[40];
  std::snprintf(b, sizeof b, "%016llx%04llx", static_cast<unsigned long long>(rng()),
                static_cast<unsigned long long>(counter++ & 0xffff));
  return b;
}

bool constant_time_equal(const std::string& a, const std::string& b) {
  if (a.size() != b.size()) return false;
  unsigned char d = 0;
  for (size_t i = 0; i < a.size(); ++i) d |= static_cast<unsigned char>(a[i] ^ b[i]);
  return d == 0;
}

thread_local Clock::time_point t_request_start;
thread_local std::string t_request_id;
thread_local int64_t t_bytes_in = -1;  // a body read by read_upload (-1: req.body)
// The pre-routing handler ran for this request. httplib 0.11 answers some
// requests before it (400: the request line or headers unreadable, or not
// sent within the read timeout; 414: the URI too long): those had no
// request id or start time of their own, and
// were logged with the last request's on the thread.
thread_local bool t_routed = false;

// Past the upload limit, or for an upload refused before it was read, up to
// this many more bytes are read and dropped, so that the client gets its
// answer on a connection it can keep using; past them it is closed.
constexpr size_t kDrainBytes = size_t(16) << 20;
// What a request may send as its body, off the wire, on a route that takes
// no upload (httplib reads it whole into memory).
constexpr size_t kOtherBodyBytes = size_t(1) << 20;
// Connections the kernel holds for the accept loop (Node and nginx take
// 511; capped by net.core.somaxconn).
constexpr int kListenBacklog = 1024;

// Debian's cpp-httplib 0.11 insists on CRLF after the closing boundary,
// which some clients (Node 18's fetch) leave out.
constexpr const char* kBadMultipart =
    "the multipart body could not be read (boundaries malformed, or the closing one not ended by CRLF); "
    "send the mesh as the raw request body instead";

// A POST's body through the handler's |reader|: |receive| gets the bytes
// (of every part of a multipart body, each announced to |part| first).
bool read_body(const httplib::Request& req, const httplib::ContentReader& reader,
               const httplib::MultipartContentHeader& part, const httplib::ContentReceiver& receive) {
  return req.is_multipart_form_data() ? reader(part, receive) : reader(receive);
}

// Some of the body stays unread after this answer, or what follows it on the
// connection cannot be trusted: the client is told, and the connection is
// closed after the answer. (httplib 0.11 kept reading it, and parsed the
// rest of an upload as requests.)
void close_after_answer(const httplib::Request& req, httplib::Response& res) {
  // httplib writes its own when the request asked or was the connection's
  // last: a second header would repeat it.
  if (!connection_last_request() && req.get_header_value("Connection") != "close" && !res.has_header("Connection"))
    res.set_header("Connection", "close");
  connection_close_after_answer();
}

// Runs |step| every |every| on a thread of its own, from its construction
// until its destruction.
class Periodic {
 public:
  Periodic(std::chrono::milliseconds every, std::function<void()> step)
      : thread_([this, every, step = std::move(step)] {
          std::unique_lock<std::mutex> lock(mu_);
          while (!stop_) {
            lock.unlock();
            step();
            lock.lock();
            cv_.wait_for(lock, every, [this] { return stop_; });
          }
        }) {}
  ~Periodic() {
    {
      std::lock_guard<std::mutex> lock(mu_);
      stop_ = true;
    }
    cv_.notify_all();
    thread_.join();
  }

 private:
  std::mutex mu_;
  std::condition_variable cv_;
  bool stop_ = false;
  std::thread thread_;  // last: it starts once the others exist
};

}  // namespace

// --- flags -----------------------------------------------------------------------
bool parse_server_flags(const std::vector<std::string>& args, ServerConfig* c, std::string* error) {
  struct Flag {
    const char* name;
    std::function<bool(const std::string&)> set;
  };
  auto integer = [](int64_t lo, int64_t hi, auto* target) {
    return [lo, hi, target](const std::string& v) {
      char* end = nullptr;
      const long long x = std::strtoll(v.c_str(), &end, 10);
      if (v.empty() || *end || x < lo || x > hi) return false;
      *target = static_cast<std::remove_pointer_t<decltype(target)>>(x);
      return true;
    };
  };
  const std::vector<Flag> flags = {
      {"host", [c](const std::string& v) { c->host = v; return !v.empty(); }},
      {"port", integer(0, 65535, &c->port)},
      {"workers", integer(0, 256, &c->workers)},
      {"queue", integer(1, 100000, &c->queue)},
      {"http-threads", integer(0, 4096, &c->http_threads)},
      {"max-upload-bytes", integer(1, int64_t(1) << 40, &c->max_upload_bytes)},
      {"max-output-triangles", integer(1, kMaxTriangles, &c->max_output_triangles)},
      {"request-timeout", integer(1, 86400, &c->request_timeout_s)},
      {"job-ttl", integer(1, 30 * 86400, &c->job_ttl_s)},
      {"result-bytes-cap", integer(0, int64_t(1) << 40, &c->result_bytes_cap)},
      {"memory-limit", [c](const std::string& v) { return parse_byte_size(v, &c->memory_limit); }},  // bytes, or K/M/G
      {"grace", integer(0, 3600, &c->grace_s)},
      {"read-timeout", integer(1, 3600, &c->read_timeout_s)},
      {"min-rate", integer(0, int64_t(1) << 40, &c->min_rate)},
      {"trim-delay", integer(0, 3600 * 1000, &c->trim_delay_ms)},
      {"lone-job-threads", integer(0, 256, &c->lone_job_threads)},
      {"web-root", [c](const std::string& v) { c->web_root = v; return true; }},
      {"job-dir", [c](const std::string& v) { c->job_dir = v; return true; }},
      {"api-key", [c](const std::string& v) { c->api_key = v; return true; }},
      {"log-format", [c](const std::string& v) { c->log_format = v; return v == "text" || v == "json"; }},
  };
  // Environment first (ITEAS_MAX_UPLOAD_BYTES, ...), then flags.
  for (const Flag& f : flags) {
    std::string env = "ITEAS_";
    for (const char* p = f.name; *p; ++p) env += *p == '-' ? '_' : char(std::toupper(static_cast<unsigned char>(*p)));
    if (const char* v = std::getenv(env.c_str()))
      if (!f.set(v)) { *error = "bad value for " + env; return false; }
  }
  for (size_t i = 0; i < args.size(); ++i) {
    std::string name = args[i], value;
    if (name.rfind("--", 0) != 0) { *error = "unexpected argument '" + name + "'"; return false; }
    name = name.substr(2);
    const size_t eq = name.find('=');
    if (eq != std::string::npos) { value = name.substr(eq + 1); name = name.substr(0, eq); }
    else if (i + 1 < args.size()) value = args[++i];
    else { *error = "--" + name + " needs a value"; return false; }
    bool found = false;
    for (const Flag& f : flags)
      if (name == f.name) {
        found = true;
        if (!f.set(value)) { *error = "bad value for --" + name; return false; }
      }
    if (!found) { *error = "unknown flag --" + name; return false; }
  }
  return true;
}

// --- the service ---------------------------------------------------------------------
int serve(const ServerConfig& cfg) {
  auto logger = spdlog::stdout_logger_mt("iteas");
  if (cfg.log_format == "json")
    logger->set_pattern(R"({"time":"%Y-%m-%dT%H:%M:%S.%e%z","level":"%l",%v})");
  else
    logger->set_pattern("%Y-%m-%d %H:%M:%S.%e %l %v");
  logger->flush_on(spdlog::level::info);
  const bool json_log = cfg.log_format == "json";
  // A line other than an access-log line: |fields| in the JSON log (an
  // object's members: these lines were free text, which broke it), |text| in
  // the text log, on one line.
  auto log_event = [&](spdlog::level::level_enum level, const json& fields, const std::string& text) {
    if (json_log) {
      const std::string object = json_text(fields);
      logger->log(level, "{}", object.substr(1, object.size() - 2));
    } else {
      logger->log(level, "{}", one_line(text));
    }
  };

  // Signals are taken by one thread with sigwait: block them everywhere first.
  sigset_t sigs;
  sigemptyset(&sigs);
  sigaddset(&sigs, SIGTERM);
  sigaddset(&sigs, SIGINT);
  pthread_sigmask(SIG_BLOCK, &sigs, nullptr);

  const int workers = cfg.workers > 0 ? cfg.workers : hardware_threads();
  QueueLimits limits;
  limits.workers = workers;
  limits.capacity = size_t(cfg.queue);
  limits.ttl = std::chrono::seconds(cfg.job_ttl_s);
  limits.result_bytes_cap = size_t(cfg.result_bytes_cap);
  limits.memory_limit = cfg.memory_limit > 0 ? cfg.memory_limit : default_memory_limit();
  limits.trim_delay = std::chrono::milliseconds(cfg.trim_delay_ms);
  limits.lone_job_threads = cfg.lone_job_threads;
  JobQueue queue(limits, now_ms);
  const JobStore store(cfg.job_dir);
  {
    std::string error;
    if (!store.usable(&error)) {
      log_event(spdlog::level::err, {{"event", "job_store_unusable"}, {"message", error}}, error);
      return 2;
    }
  }
  Metrics metrics;
  queue.set_observer([&](Job& job) {  // job.mu held (JobQueue::set_observer)
    StoredJob s;
    s.status = job.status_json_locked();
    s.content_type = content_type_for(job.request.output_format);
    if (job.state == JobState::kFailed) s.http_status = status_for(job.error);
    // A store that cannot take a write (a full volume, a file size limit)
    // costs the other replicas this job, never this one: it still answers
    // from memory, and the others say why they cannot (503).
    const std::string error = store.put(job.id, s, job.state == JobState::kDone ? &job.result : nullptr);
    if (!error.empty()) {
      metrics.store_error();
      log_event(spdlog::level::err, {{"event", "job_store_error"}, {"job", job.id}, {"message", error}},
                "job " + job.id + ": the job store could not take it: " + error);
    }
  });
  std::atomic<bool> draining{false};

  // The shared store's upkeep, on a thread of its own: every quarter of the
  // TTL (at most a minute), this replica touches the status of each job it
  // still holds, queued or running; every TTL (at most a minute) it sweeps
  // what is older than the TTL. The sweep ran on submissions before, by file
  // age alone: a job queued or running longer than the TTL lost its status,
  // and the other replicas answered 404 for it until it ended. A replica that
  // dies stops touching its jobs, and they go a TTL later.
  std::optional<Periodic> upkeep;
  if (store.enabled()) {
    const auto ttl = std::chrono::milliseconds(int64_t(cfg.job_ttl_s) * 1000);
    const auto sweep_every = std::min(ttl, std::chrono::milliseconds(60000));
    auto next_sweep = std::chrono::steady_clock::now();
    upkeep.emplace(std::clamp(ttl / 4, std::chrono::milliseconds(250), std::chrono::milliseconds(60000)), [&, sweep_every, next_sweep]() mutable {
      for (const std::string& id : queue.unfinished_ids()) store.touch(id);
      if (std::chrono::steady_clock::now() < next_sweep) return;
      store.expire(std::chrono::seconds(cfg.job_ttl_s));
      next_sweep = std::chrono::steady_clock::now() + sweep_every;
    });
  }

  // A keep-alive connection holds its thread: it is given back after a few
  // requests or two idle seconds, so more clients than threads still take
  // turns. A request's head must come within the read timeout, and its body
  // and response at --min-rate (see server/connection.h).
  ConnectionLimits connection_limits;
  connection_limits.read_timeout_s = cfg.read_timeout_s;
  connection_limits.keep_alive_timeout_s = std::min(2, cfg.read_timeout_s);
  connection_limits.keep_alive_max = 8;
  connection_limits.min_rate = cfg.min_rate;
  GuardedServer svr(connection_limits);
  // Connection threads are separate from the refinement workers, and enough
  // that keep-alive clients cannot starve the API.
  const int http_threads = cfg.http_threads > 0 ? cfg.http_threads : std::max(64, 8 * workers);
  svr.new_task_queue = [http_threads] { return new httplib::ThreadPool(size_t(http_threads)); };
  svr.set_payload_max_length(size_t(cfg.max_upload_bytes));
  // Off the wire, an upload may take its decoded limit, the bytes dropped
  // past it, and its framing (chunk headers).
  const size_t upload_wire_bytes = size_t(cfg.max_upload_bytes) + size_t(cfg.max_upload_bytes) / 64 + kDrainBytes + (64 << 10);
  const std::string too_slow = fmt::format("the body came slower than {} bytes a second", cfg.min_rate);

  // A client that asks before sending its body (curl does past 1 MB) is
  // told 413 at once when the length it declares is over what the route
  // takes; it got "100 Continue" before, sent the whole body, and was told
  // then. (Answered before routing: its own id, and the connection closed.)
  svr.set_expect_100_continue_handler([&](const httplib::Request& req, httplib::Response& res) {
    if (declared_length(req) <= (is_upload(req) ? uint64_t(cfg.max_upload_bytes) : uint64_t(kOtherBodyBytes))) return 100;
    res.status = 413;  // httplib 0.11 answers with res.status, not with what this returns
    return 413;
  });
  svr.set_pre_routing_handler([&](const httplib::Request& req, httplib::Response& res) {
    t_request_start = Clock::now();
    t_bytes_in = -1;
    t_routed = true;
    // A request target in absolute form ("GET http://host/healthz", as a
    // client speaking to a proxy sends it) names the same route (RFC 9112
    // §3.2.2: a server must accept it); httplib matched the whole URL: 404.
    const_cast<httplib::Request&>(req).path = origin_form(req.path);
    const bool upload = is_upload(req);
    connection_body_budget(upload ? upload_wire_bytes : kOtherBodyBytes);
    const std::string given = req.get_header_value("X-Request-Id");
    t_request_id = loggable_token(given) ? given : new_id();
    res.set_header("X-Request-Id", t_request_id);
    // A body whose length httplib would take wrongly is refused unread, and
    // the connection closed. Both a length and chunks: the chunks frame it,
    // and the connection is closed after the answer (a request smuggled past
    // a proxy that took the length instead ends with it).
    const FramingError framing = framing_error(req);
    if (framing.status) {
      send_error(res, framing.status, framing.code, framing.message);
      close_after_answer(req, res);
      return httplib::Server::HandlerResponse::Handled;
    }
    if (req.has_header("Transfer-Encoding") && req.has_header("Content-Length")) close_after_answer(req, res);
    // httplib 0.11 served a Range header on any method and status (a POST
    // with one got a slice of its refined mesh, 206). The Request is a
    // non-const local of httplib's, handed to us as const.
    take_deferred_range(const_cast<httplib::Request&>(req));
    // A request with neither a Content-Length nor a Transfer-Encoding has no
    // body (RFC 9112 §6.3), but httplib 0.11 reads one until the connection
    // closes for POST, PUT, PATCH and DELETE: `curl -X POST` of an upload
    // route without a body waited the read timeout (10 s) for a 408. It is
    // given the length it has.
    if (!req.has_header("Content-Length") && !req.has_header("Transfer-Encoding"))
      const_cast<httplib::Request&>(req).headers.emplace("Content-Length", "0");
    // A body on a route that takes no upload is read whole by httplib, and
    // decoded: 872 KB of gzip became 200 MB in memory. An encoded one is
    // refused unread, and the connection closed after the answer.
    const std::string encoding = req.get_header_value("Content-Encoding");
    const bool has_body = req.has_header("Transfer-Encoding") || declared_length(req) > 0;
    if (!upload && has_body && !encoding.empty() && encoding != "identity") {
      send_error(res, 415, "unsupported_encoding",
                 "a body with a Content-Encoding is taken by the uploads alone (POST /v1/refine, /v1/jobs)");
      close_after_answer(req, res);
      return httplib::Server::HandlerResponse::Handled;
    }
    // Nothing else is answered here: this runs before httplib reads the body,
    // and an early answer leaves it unread, which costs the connection.
    // Authentication is in wrap(), which reads and drops the body.
    return httplib::Server::HandlerResponse::Unhandled;
  });
  svr.set_logger([&](const httplib::Request& req, const httplib::Response& res) {
    const bool routed = std::exchange(t_routed, false);
    // Unrouted requests have no start time: their duration is not known.
    const double secs = routed ? std::chrono::duration<double>(Clock::now() - t_request_start).count() : -1;
    const int64_t bytes_in = t_bytes_in >= 0 ? t_bytes_in : int64_t(req.body.size());
    metrics.observe(route_of(req.path), res.status, secs);
    const std::string ms = secs < 0 ? std::string(json_log ? "null" : "-") : fmt::format("{:.3f}", secs * 1000);
    // Only a method httplib parsed; the remote address is set after the headers.
    const std::string method = loggable_token(req.method) ? req.method : "-";
    const std::string remote = req.remote_addr.empty() ? "-" : req.remote_addr;
    // A response the client did not all take is marked: its status says
    // what was meant, not what arrived.
    const bool cut = connection_response_cut();
    if (json_log)
      logger->info(R"("request_id":"{}","method":"{}","path":"{}","status":{},"bytes_in":{},"bytes_out":{},"ms":{},"remote":"{}"{})",
                   t_request_id, method, route_of(req.path), res.status, bytes_in, res.body.size(), ms, remote,
                   cut ? R"(,"cut_off":true)" : "");
    else
      logger->info("{} {} {} {} in={} out={} {}{} {}{}", t_request_id, method, loggable_path(req.path), res.status, bytes_in,
                   res.body.size(), ms, secs < 0 ? "" : "ms", remote, cut ? " cut-off" : "");
  });
  svr.set_exception_handler([&](const httplib::Request&, httplib::Response& res, std::exception_ptr ep) {
    std::string what = "unexpected error";
    try { if (ep) std::rethrow_exception(ep); } catch (const std::exception& e) { what = e.what(); } catch (...) {}
    log_event(spdlog::level::err, {{"event", "internal_error"}, {"request_id", t_request_id}, {"message", what}},
              t_request_id + " internal error: " + what);
    send_error(res, 500, "internal", "internal error");
  });
  svr.set_error_handler([&](const httplib::Request& req, httplib::Response& res) {
    // An error is answered whole: httplib 0.11 applied a Range header to
    // error envelopes too (a 404 came back as 6 bytes of JSON, 206-style).
    const_cast<httplib::Request&>(req).ranges.clear();
    if (!t_routed) {
      // Answered before routing: an id of its own, and the connection is
      // closed after it (what follows on it cannot be trusted to be framed).
      t_request_id = new_id();
      res.set_header("X-Request-Id", t_request_id);
      close_after_answer(req, res);
    }
    // A limit the connection's stream hit, unless a handler has answered
    // already (the upload routes say it themselves).
    switch (res.body.empty() ? connection_limit_hit() : LimitHit::kNone) {
      case LimitHit::kHeadTimeout:
        return send_error(res, 408, "request_timeout",
                          fmt::format("the request line and headers were not all sent within {} s", cfg.read_timeout_s));
      case LimitHit::kHeadTooLarge:
        if (res.status == 414) break;
        return send_error(res, 431, "headers_too_large",
                          fmt::format("the request line and headers are over {} KiB", kHeadBytes >> 10));
      case LimitHit::kBodyTooLarge:
        return send_error(res, 413, "payload_too_large",
                          fmt::format("{} {} takes no body over {} KiB", req.method, req.path, kOtherBodyBytes >> 10));
      case LimitHit::kTooSlow:
        return send_error(res, 408, "request_timeout", too_slow);
      case LimitHit::kNone:
        break;
    }
    if (!t_routed) {
      if (res.status == 414) return send_error(res, 414, "uri_too_long", "the request line is over 8,192 bytes");
      if (res.status == 400) {
        // httplib refuses a request line whose method or version it does not
        // know as malformed; RFC 9110 §15.6.2 and §15.6.6 name them.
        const RequestLineFault fault = request_line_fault(req);
        if (fault == RequestLineFault::kUnknownMethod)
          return send_error(res, 501, "unknown_method", "the method " + req.method + " is not one this server knows");
        if (fault == RequestLineFault::kUnsupportedVersion)
          return send_error(res, 505, "http_version_not_supported", "the server speaks HTTP/1.1 and HTTP/1.0, not " + req.version);
        return send_error(res, 400, "bad_request", "the request line or headers are malformed");
      }
    }
    if (!res.body.empty()) return;  // an envelope is already there
    const std::string allow = res.status == 404 ? allowed_methods(req.path) : "";
    if (!allow.empty()) {
      // A route with this path takes other methods (RFC 9110 §15.5.6).
      res.set_header("Allow", allow);
      send_error(res, 405, "method_not_allowed", req.path + " takes " + allow + ", not " + req.method);
    } else if (res.status == 404) {
      send_error(res, 404, "not_found", "no such route: " + req.method + " " + req.path);
    } else if (res.status == 413) {
      send_error(res, 413, "payload_too_large", "the body is over the server's upload limit");
    } else if (res.status == 400 && req.is_multipart_form_data()) {
      send_error(res, 400, "bad_multipart", kBadMultipart);
    } else {
      send_error(res, res.status, "bad_request", "the request could not be read");
    }
  });

  // Reads a POST's body through |reader|: the raw body, or a multipart
  // body's "mesh" part. At most --max-upload-bytes are kept, counted after
  // any Content-Encoding is undone: Debian's cpp-httplib 0.11 applies its
  // payload limit only to a declared Content-Length, and a chunked body, one
  // without a length, or a gzip one (a 2.1 MB upload of zeros took 1 GB)
  // were read whole before. Past the limit up to 16 MiB more are read and
  // dropped, so that a client sending a little too much gets its 413 on a
  // clean connection; the rest is not read, and the 413 says
  // "Connection: close".
  struct Upload {
    std::vector<uint8_t> bytes;
    std::string filename;
    bool has_mesh = false;  // multipart: a "mesh" part came
  };
  auto read_upload = [&](const httplib::Request& req, httplib::Response& res,
                         const httplib::ContentReader& reader) -> Upload {
    Upload up;
    const size_t limit = size_t(cfg.max_upload_bytes);
    const bool declared = req.has_header("Content-Length") && !req.has_header("Transfer-Encoding");
    const bool multipart = req.is_multipart_form_data();
    bool over = false, in_mesh = !multipart;
    size_t seen = 0;  // every part's bytes, for the limit
    auto keep = [&](const char* data, size_t n) {
      seen += n;
      if (seen > limit) {
        if (!over) up.bytes = {};
        over = true;
        return seen - limit <= kDrainBytes;
      }
      if (!in_mesh) return true;
      // Grown by doubling, but never past the limit: a gzip body of 500 MB
      // peaked the server at 596 MB against the default 256 MiB limit
      // (doubling past it), 307 MB capped.
      if (up.bytes.size() + n > up.bytes.capacity())
        up.bytes.reserve(std::min(limit, std::max({2 * up.bytes.capacity(), up.bytes.size() + n, size_t(64) << 10})));
      up.bytes.insert(up.bytes.end(), data, data + n);
      return true;
    };
    // A declared length is the body's size unless it is encoded.
    if (declared && !req.has_header("Content-Encoding") && !multipart) {
      const uint64_t length = declared_length(req);
      if (length <= limit) up.bytes.reserve(size_t(length));
    }
    const bool ok = read_body(req, reader, [&](const httplib::MultipartFormData& part) {
      in_mesh = part.name == "mesh" && !up.has_mesh;
      if (in_mesh) {
        up.has_mesh = true;
        up.filename = part.filename;
      }
      return true;
    }, keep);
    t_bytes_in = int64_t(seen);
    // A declared length over the limit: httplib reads the body, drops it and
    // sets 413.
    const bool skipped = !ok && !over && declared && res.status == 413;
    if (over || skipped) {
      if (!ok && !skipped) close_after_answer(req, res);  // some of it left unread
      throw HttpError{413, "payload_too_large", "the body is over the server's upload limit"};
    }
    if (!ok) {
      close_after_answer(req, res);
      const LimitHit hit = connection_limit_hit();
      if (hit == LimitHit::kTooSlow) throw HttpError{408, "request_timeout", too_slow};
      if (hit == LimitHit::kBodyTooLarge)  // framing past the wire allowance
        throw HttpError{413, "payload_too_large", "the body is over the server's upload limit"};
      if (multipart) throw HttpError{400, "bad_multipart", kBadMultipart};
      throw HttpError{400, "bad_body", "the request body could not be read (malformed chunked or compressed data)"};
    }
    return up;
  };
  // Builds a job from a request: options, body (raw or multipart "mesh").
  auto make_job = [&](const httplib::Request& req, Upload&& up, bool listed) -> std::shared_ptr<Job> {
    if (draining) throw HttpError{503, "draining", "the server is shutting down"};
    std::vector<std::pair<std::string, std::string>> pairs;
    for (const auto& [k, v] : req.params) {
      // Which of two values would be meant is unknown: the last one was used.
      if (!pairs.empty() && pairs.back().first == k)
        throw HttpError{400, "bad_option", "option '" + k + "' is given more than once"};
      pairs.emplace_back(k, v);
    }
    Options options;
    std::string error, bad;
    if (!parse_options(pairs, &options, &error, &bad)) throw HttpError{400, "bad_option", error};
    if (options.refine.max_triangles > cfg.max_output_triangles) options.refine.max_triangles = cfg.max_output_triangles;
    if (options.out.output.empty()) options.out.output = "glb";
    auto job = std::make_shared<Job>();
    job->id = new_id();
    job->listed = listed;
    std::string name;
    const std::string type = req.get_header_value("Content-Type");
    if (req.is_multipart_form_data()) {
      if (!up.has_mesh) throw HttpError{400, "missing_mesh", "multipart upload needs a 'mesh' file part"};
      job->input = std::move(up.bytes);
      name = up.filename;
    } else {
      const std::string base = type.substr(0, type.find(';'));
      static const char* accepted[] = {"model/gltf-binary", "model/gltf+json", "application/octet-stream", "application/json",
                                       "model/obj", "model/stl", "application/ply", ""};
      bool ok = false;
      for (const char* a : accepted) ok = ok || base == a;
      if (!ok) throw HttpError{415, "unsupported_media_type", "Content-Type '" + base + "' is not a mesh type"};
      job->input = std::move(up.bytes);
    }
    if (job->input.empty()) throw HttpError{400, "empty_body", "the request has no mesh"};
    job->request.data = job->input.data();
    job->request.size = job->input.size();
    job->request.name_hint = name;
    job->request.output_format = options.out.output;
    job->request.options = options;
    job->memory_estimate = estimate_job_bytes(job->request);
    if (sniff_format(job->request.data, job->request.size, name).empty())
      throw HttpError{415, "unsupported_format", "the body is not a recognised mesh format (glb, gltf, drc, obj, ply, off, stl)"};
    return job;
  };
  auto submit = [&](const std::shared_ptr<Job>& job, httplib::Response& res) {
    switch (queue.submit(job)) {
      case Admission::kAccepted: return;
      case Admission::kClosed: throw HttpError{503, "draining", "the server is shutting down"};
      case Admission::kTooBig:
        throw HttpError{413, "memory_estimate",
                        "this job may need " + std::to_string(job->memory_estimate >> 20) + " MiB, over the server's " +
                            std::to_string(queue.working_share() >> 20) + " MiB for work; lower levels or max_triangles"};
      case Admission::kQueueFull:
        res.set_header("Retry-After", "2");
        throw HttpError{429, "queue_full", "the work queue is full; retry later"};
      case Admission::kUploadsFull:
        res.set_header("Retry-After", "2");
        throw HttpError{429, "uploads_full", "the server holds too many queued uploads; retry later"};
    }
  };
  // One wrapper for every handler: HttpError and anything else to the envelope.
  // The API key is checked first: an upload without it is not read.
  auto guard = [&](const httplib::Request& req, httplib::Response& res, const std::function<void()>& handler) {
    try {
      if (!cfg.api_key.empty() && !constant_time_equal(req.get_header_value("Authorization"), "Bearer " + cfg.api_key)) {
        res.set_header("WWW-Authenticate", "Bearer");
        throw HttpError{401, "unauthorized", "a valid 'Authorization: Bearer <key>' header is required"};
      }
      handler();
    } catch (const HttpError& e) {
      send_error(res, e.status, e.code, e.message);
    } catch (const std::bad_alloc&) {
      send_error(res, 413, "too_large", "the request needs more memory than the server has");
    }
  };
  // A GET handler whose answer a Range header may slice.
  auto ranged = [](auto handler) {
    return [handler](const httplib::Request& req, httplib::Response& res) {
      handler(req, res);
      fit_ranges(const_cast<httplib::Request&>(req), res);
    };
  };
  auto wrap = [&](auto handler) {
    return ranged([&, handler](const httplib::Request& req, httplib::Response& res) { guard(req, res, [&] { handler(req, res); }); });
  };
  // For a POST whose body the handler reads itself (read_upload). A body
  // the handler did not read (a missing API key) is read and dropped after
  // it answered, up to the limit and kDrainBytes more; past that, or when it
  // cannot be read, the connection is closed.
  auto wrap_upload = [&](auto handler) {
    return [&, handler](const httplib::Request& req, httplib::Response& res, const httplib::ContentReader& reader) {
      guard(req, res, [&] { handler(req, res, reader); });
      if (t_bytes_in >= 0) return;
      size_t seen = 0;
      auto drop = [&](const char*, size_t n) {
        seen += n;
        return seen <= size_t(cfg.max_upload_bytes) + kDrainBytes;
      };
      const int status = res.status;  // httplib sets 413 for a declared length over the limit
      const bool ok = read_body(req, reader, [](const httplib::MultipartFormData&) { return true; }, drop);
      res.status = status;
      t_bytes_in = int64_t(seen);
      if (!ok) close_after_answer(req, res);
    };
  };

  svr.Post("/v1/refine", wrap_upload([&](const httplib::Request& req, httplib::Response& res,
                                         const httplib::ContentReader& reader) {
    auto job = make_job(req, read_upload(req, res, reader), false);
    submit(job, res);
    std::unique_lock<std::mutex> lock(job->mu);
    if (!job->changed.wait_for(lock, std::chrono::seconds(cfg.request_timeout_s), [&] { return job->finished_state(); })) {
      job->cancel = true;
      throw HttpError{422, "timeout", "the refinement did not finish within the server's request timeout; "
                                      "use the job API or a smaller max_triangles"};
    }
    if (job->state == JobState::kFailed) throw HttpError{status_for(job->error), job->error.code, job->error.message};
    if (job->state != JobState::kDone) throw HttpError{503, "cancelled", "the job was cancelled (the server is shutting down)"};
    metrics.triangles(job->stats["input"]["triangles"].get<int64_t>(), job->stats["output"]["triangles"].get<int64_t>());
    res.set_header("X-IteAS-Stats", json_text(job->stats));
    res.set_content(reinterpret_cast<const char*>(job->result.data()), job->result.size(),
                    content_type_for(job->request.output_format));
  }));
  svr.Post("/v1/jobs", wrap_upload([&](const httplib::Request& req, httplib::Response& res,
                                       const httplib::ContentReader& reader) {
    auto job = make_job(req, read_upload(req, res, reader), true);
    submit(job, res);
    res.status = 202;
    res.set_header("Location", "/v1/jobs/" + job->id);
    res.set_content(json_text(job->status_json()), "application/json");
  }));
  svr.Get(kJobRoute, wrap([&](const httplib::Request& req, httplib::Response& res) {
    auto job = queue.find(req.matches[1]);
    if (!job) {
      // Another replica's job, through the shared store.
      const auto stored = store.get(req.matches[1]);
      if (!stored) throw HttpError{404, "job_not_found", "no job with that id (it may have expired)"};
      res.set_content(json_text(stored->status), "application/json");
      return;
    }
    res.set_content(json_text(job->status_json()), "application/json");
  }));
  svr.Get(kJobResultRoute, wrap([&](const httplib::Request& req, httplib::Response& res) {
    auto job = queue.find(req.matches[1]);
    if (!job) {
      const auto stored = store.get(req.matches[1]);
      if (!stored) throw HttpError{404, "job_not_found", "no job with that id (it may have expired)"};
      const std::string state = stored->status.value("status", std::string("failed"));
      if (state == "failed") {
        const json err = stored->status.value("error", json::object());
        throw HttpError{stored->http_status, err.value("code", std::string("failed")), err.value("message", std::string("the job failed"))};
      }
      if (state != "done") throw HttpError{409, "not_ready", "the job is " + state};
      if (!stored->result_error.empty()) {
        res.set_header("Retry-After", "1");
        throw HttpError{503, "result_unavailable",
                        "the replica that ran this job holds its result, but the job store could not take it (" +
                            stored->result_error + ")"};
      }
      std::string bytes;
      if (!store.result(req.matches[1], &bytes))
        throw HttpError{404, "job_not_found", "the job's result has expired or was deleted"};
      if (stored->status.contains("statistics")) res.set_header("X-IteAS-Stats", json_text(stored->status["statistics"]));
      res.set_content(std::move(bytes), stored->content_type);
      return;
    }
    std::lock_guard<std::mutex> lock(job->mu);
    if (job->state == JobState::kFailed) throw HttpError{status_for(job->error), job->error.code, job->error.message};
    if (job->state != JobState::kDone) throw HttpError{409, "not_ready", std::string("the job is ") + job_state_name(job->state)};
    res.set_header("X-IteAS-Stats", json_text(job->stats));
    res.set_content(reinterpret_cast<const char*>(job->result.data()), job->result.size(),
                    content_type_for(job->request.output_format));
  }));
  svr.Delete(kJobRoute, wrap([&](const httplib::Request& req, httplib::Response& res) {
    const std::string id = req.matches[1];
    const bool local = queue.remove(id);
    const bool stored = store.remove(id);
    if (!local && !stored) throw HttpError{404, "job_not_found", "no job with that id (it may have expired)"};
    res.set_content(json_text(json{{"id", id}, {"deleted", true}}), "application/json");
  }));
  svr.Get("/healthz", ranged([](const httplib::Request&, httplib::Response& res) {
    res.set_content(R"({"status":"ok"})", "application/json");
  }));
  svr.Get("/readyz", ranged([&](const httplib::Request&, httplib::Response& res) {
    if (draining) send_error(res, 503, "draining", "the server is shutting down");
    else res.set_content(R"({"status":"ready"})", "application/json");
  }));
  svr.Get("/metrics", ranged([&](const httplib::Request&, httplib::Response& res) {
    res.set_content(metrics.text(queue), "text/plain; version=0.0.4");
  }));
  svr.Get("/v1/openapi.yaml", wrap([](const httplib::Request&, httplib::Response& res) {
    res.set_content(kOpenApiYaml, "application/yaml");
  }));

  // The web page (static files, no authentication: the page asks for the key).
  std::string web_root = cfg.web_root;
  if (web_root.empty()) {
    char exe[4096];
    const ssize_t n = readlink("/proc/self/exe", exe, sizeof exe - 1);
    if (n > 0) {
      const std::string dir = std::string(exe, size_t(n)).substr(0, std::string(exe, size_t(n)).rfind('/'));
      if (access((dir + "/web/index.html").c_str(), R_OK) == 0) web_root = dir + "/web";
    }
  }
  // A file of the web page is fitted to its ranges as the API's answers are
  // (httplib has set 206 already whenever the request has a Range header;
  // -1 lets it choose between 200 and 206 once they are fitted).
  svr.set_file_request_handler([](const httplib::Request& req, httplib::Response& res) {
    res.status = -1;
    fit_ranges(const_cast<httplib::Request&>(req), res);
  });
  if (!web_root.empty() && !svr.set_mount_point("/", web_root)) {
    log_event(spdlog::level::err, {{"event", "web_root_unusable"}, {"path", web_root}},
              "cannot serve the web page from " + web_root);
    return 2;
  }
  svr.set_file_extension_and_mimetype_mapping("wasm", "application/wasm");
  svr.set_file_extension_and_mimetype_mapping("mjs", "text/javascript");

  int port = cfg.port;
  if (port == 0) {
    port = svr.bind_to_any_port(cfg.host);
  } else if (!svr.bind_to_port(cfg.host, port)) {
    port = -1;
  }
  if (port < 0) {
    log_event(spdlog::level::err, {{"event", "listen_failed"}, {"host", cfg.host}, {"port", cfg.port}},
              "cannot listen on " + cfg.host + ":" + std::to_string(cfg.port));
    return 4;
  }
  if (!svr.raise_listen_backlog(kListenBacklog))
    log_event(spdlog::level::warn, {{"event", "listen_backlog"}, {"backlog", kListenBacklog}},
              "could not raise the listen backlog to " + std::to_string(kListenBacklog) +
                  "; bursts of connections may be dropped");
  logger->info(json_log ? R"("event":"listening","host":"{}","port":{},"workers":{},"lone_job_threads":{},"memory_limit_mib":{},"trim_delay_ms":{})"
                        : "listening on {}:{} with {} workers (at most {} threads a job), memory limit {} MiB, trim delay {} ms",
               cfg.host, port, workers, resolve_threads(limits.lone_job_threads), limits.memory_limit >> 20,
               cfg.trim_delay_ms);
  if (cfg.on_listening) cfg.on_listening(port);
  std::thread http([&] { svr.listen_after_bind(); });

  int sig = 0;
  sigwait(&sigs, &sig);
  logger->info(json_log ? R"("event":"draining","signal":{})" : "signal {}: draining", sig);
  draining = true;
  queue.drain(std::chrono::seconds(cfg.grace_s));
  // Give waiting synchronous requests a moment to write their responses.
  std::this_thread::sleep_for(std::chrono::milliseconds(200));
  svr.stop();
  http.join();
  logger->info(json_log ? R"("event":"stopped")" : "stopped");
  return 0;
}

}  // namespace iteas
