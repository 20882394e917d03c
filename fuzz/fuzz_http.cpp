// Fuzz target: the HTTP server, whole, as a client reaches it. The input is
// the bytes a client sends on one connection (one request or several,
// pipelined); they go to a real `iteas serve` started in this process on a
// loopback port (routes, guarded connection stream, httplib's parser, the
// upload readers, the refinement of what parses as a mesh), and the client's
// half is closed after them. Oracles, each a finding (abort):
//   * the server stops answering (a new connection is refused);
//   * the connection neither answers nor closes within 20 s of the input's
//     last byte (a hang: the server's own limits are 1-2 s here);
//   * a response's status is 5xx other than 503 (overload), 501 (a method
//     or transfer coding the server does not know) and 505 (an HTTP version
//     it does not speak), or an answer does not start with a status line;
//   * a complete request head (a blank line after a request line) gets no
//     answer at all.
// libFuzzer's coverage sees our code; Debian's httplib is a compiled library,
// which a campaign can replace with an instrumented build of the same source
// (fuzz/README.md).
#include <arpa/inet.h>
#include <fcntl.h>
#include <netinet/in.h>
#include <netinet/tcp.h>
#include <poll.h>
#include <sys/socket.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <cctype>
#include <cerrno>
#include <chrono>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <string>
#include <thread>

#include "server/server.h"

namespace {

int g_port = 0;

[[noreturn]] void finding(const char* what, const std::string& detail) {
  std::fprintf(stderr, "fuzz_http finding: %s\n%s\n", what, detail.substr(0, 2000).c_str());
  std::fflush(stderr);
  std::abort();
}

// A connection to the server, or -1. A connect interrupted by a signal
// (libFuzzer's timer) is tried again on a new socket.
int connect_loopback() {
  sockaddr_in a{};
  a.sin_family = AF_INET;
  a.sin_port = htons(uint16_t(g_port));
  a.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  int s = -1;
  for (int attempt = 0; s < 0 && attempt < 10; ++attempt) {
    s = socket(AF_INET, SOCK_STREAM | SOCK_CLOEXEC, 0);
    if (s < 0) return -1;
    if (connect(s, reinterpret_cast<sockaddr*>(&a), sizeof a) != 0) {
      const int error = errno;
      close(s);
      s = -1;
      if (error != EINTR) {
        errno = error;
        return -1;
      }
    }
  }
  if (s < 0) return -1;
  const int one = 1;
  setsockopt(s, IPPROTO_TCP, TCP_NODELAY, &one, sizeof one);
  return s;
}

// Sends |in| and reads until the server closes, both at once (a server that
// answers early and stops reading must not stall the sender). Returns false
// on a hang: no answer or close within |patience| of the last byte sent.
bool exchange(int s, const std::string& in, std::string* out, std::chrono::seconds patience) {
  fcntl(s, F_SETFL, fcntl(s, F_GETFL) | O_NONBLOCK);
  size_t sent = 0;
  bool closed_write = false;
  auto idle_since = std::chrono::steady_clock::now();
  char buf[65536];
  for (;;) {
    if (sent == in.size() && !closed_write) {
      shutdown(s, SHUT_WR);
      closed_write = true;
      idle_since = std::chrono::steady_clock::now();
    }
    pollfd p{s, short(POLLIN | (closed_write ? 0 : POLLOUT)), 0};
    const int r = poll(&p, 1, 100);
    if (r < 0 && errno != EINTR) return true;
    if (r > 0 && (p.revents & (POLLIN | POLLHUP | POLLERR))) {
      const ssize_t n = recv(s, buf, sizeof buf, 0);
      if (n == 0) return true;
      if (n < 0 && errno != EAGAIN && errno != EINTR) return true;  // reset: the server closed first
      if (n > 0) {
        out->append(buf, size_t(n));
        idle_since = std::chrono::steady_clock::now();
      }
    }
    if (!closed_write && r > 0 && (p.revents & POLLOUT)) {
      const ssize_t n = send(s, in.data() + sent, in.size() - sent, MSG_NOSIGNAL);
      if (n > 0) sent += size_t(n);
      else if (n < 0 && errno != EAGAIN && errno != EINTR) sent = in.size();  // the server is gone from this one
    }
    if (closed_write && std::chrono::steady_clock::now() - idle_since > patience) return false;
  }
}

// Walks the responses in |out|, framed by their Content-Length or chunks (a
// HEAD answer carries its length and no body: where the length's worth of
// bytes does not end at the next status line, the body is taken as empty).
// Every response must start with a status line; a 5xx other than 503, 501
// and 505 is a finding. Returns how many responses were read; the walk
// stops, without a finding, where the framing cannot be followed.
size_t check_responses(const std::string& in, const std::string& out) {
  size_t at = 0, n = 0;
  auto fail = [&](const std::string& what) { finding(what.c_str(), "request:\n" + in + "\nanswer:\n" + out); };
  while (at < out.size()) {
    if (out.compare(at, 9, "HTTP/1.1 ") != 0 || at + 12 > out.size()) fail("an answer does not start with a status line");
    const std::string code = out.substr(at + 9, 3);
    if (code[0] == '5' && code != "503" && code != "501" && code != "505") fail("a " + code + " answer");
    ++n;
    const size_t head_end = out.find("\r\n\r\n", at);
    if (head_end == std::string::npos) fail("an answer's headers do not end");
    std::string head = out.substr(at, head_end - at);
    for (char& c : head) c = char(std::tolower(static_cast<unsigned char>(c)));
    size_t body = head_end + 4;
    if (head.find("\r\ntransfer-encoding: chunked") != std::string::npos) {
      for (;;) {
        const size_t line_end = out.find("\r\n", body);
        if (line_end == std::string::npos) return n;
        const size_t chunk = std::strtoul(out.c_str() + body, nullptr, 16);
        body = line_end + 2 + chunk + 2;
        if (chunk == 0) break;
        if (body > out.size()) return n;
      }
      at = body;
      continue;
    }
    const size_t cl = head.find("\r\ncontent-length: ");
    const size_t length = cl == std::string::npos ? 0 : std::strtoul(head.c_str() + cl + 18, nullptr, 10);
    if (body + length <= out.size() && (body + length == out.size() || out.compare(body + length, 9, "HTTP/1.1 ") == 0))
      at = body + length;
    else if (body == out.size() || out.compare(body, 9, "HTTP/1.1 ") == 0) at = body;
    else return n;
  }
  return n;
}

// Whether |in| holds a request line and a blank line after it, which
// httplib reads as a complete head (it takes "\n" line ends too).
bool has_complete_head(const std::string& in) {
  const size_t end = std::min(in.find("\r\n\r\n"), in.find("\n\n"));
  if (end == std::string::npos || end > 8000) return false;
  const size_t first = in.find_first_not_of("\r\n");
  return first != std::string::npos && first < end;
}

}  // namespace

extern "C" int LLVMFuzzerInitialize(int*, char***) {
  // The access log goes to stdout: away with it (libFuzzer writes to stderr).
  const int null = open("/dev/null", O_WRONLY);
  if (null >= 0) dup2(null, 1);
  // The server runs until the process ends: it ends at once, with the
  // status it was given, before anything the server uses is destroyed.
  std::atexit([] { std::_Exit(0); });
  static std::atomic<int> port{0};
  iteas::ServerConfig cfg;
  cfg.host = "127.0.0.1";
  cfg.port = 0;  // the system picks a free one
  cfg.workers = 1;
  cfg.queue = 4;
  cfg.http_threads = 8;
  cfg.max_upload_bytes = 1 << 20;
  cfg.max_output_triangles = 100000;
  cfg.request_timeout_s = 60;
  cfg.job_ttl_s = 2;
  cfg.result_bytes_cap = 64 << 20;
  cfg.memory_limit = int64_t(512) << 20;
  cfg.read_timeout_s = 1;
  cfg.min_rate = 16384;
  cfg.trim_delay_ms = 0;
  cfg.web_root = "";
  // Other paths of the server, for a campaign's second worker: an API key
  // (requests without it get 401 before their route) and a shared job store.
  if (const char* key = std::getenv("FUZZ_HTTP_API_KEY")) cfg.api_key = key;
  if (const char* dir = std::getenv("FUZZ_HTTP_JOB_DIR")) cfg.job_dir = dir;
  if (const char* format = std::getenv("FUZZ_HTTP_LOG_FORMAT")) cfg.log_format = format;
  // A third: limits an input reaches with a few bytes (a 96 MiB budget, so
  // that work gets 72 MiB and a job's estimate, 64 MiB and more, turns
  // plain-format uploads over about 180 KB away; a queue of one; 4,000 output
  // triangles; results over 32 KiB not kept; jobs kept 1 s), a job alone
  // refined on two threads (the pool's loops under the fuzzer), freed
  // memory given back after an idle second (the server's default path, not
  // after every job), and the web page's files when a directory is given.
  if (std::getenv("FUZZ_HTTP_TIGHT")) {
    cfg.queue = 1;
    cfg.memory_limit = int64_t(96) << 20;
    cfg.max_output_triangles = 4000;
    cfg.result_bytes_cap = 32 << 10;
    cfg.job_ttl_s = 1;
    cfg.request_timeout_s = 5;
    cfg.lone_job_threads = 2;
    cfg.trim_delay_ms = 1000;
  }
  if (const char* web = std::getenv("FUZZ_HTTP_WEB_ROOT")) cfg.web_root = web;
  cfg.on_listening = [](int p) { port = p; };
  std::thread([cfg] { std::_Exit(iteas::serve(cfg) == 0 ? 0 : 3); }).detach();
  for (int i = 0; i < 1000 && port == 0; ++i) std::this_thread::sleep_for(std::chrono::milliseconds(10));
  g_port = port;
  if (g_port == 0) finding("the server did not start", "");
  for (int i = 0; i < 500; ++i) {
    const int s = connect_loopback();
    if (s >= 0) {
      close(s);
      return 0;
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(10));
  }
  finding("the server does not take connections", "port " + std::to_string(g_port));
}

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  if (size > (size_t(2) << 20)) return 0;
  const std::string in(reinterpret_cast<const char*>(data), size);
  const int s = connect_loopback();
  if (s < 0) finding("the server refused a connection", std::strerror(errno));
  std::string out;
  const bool ended = exchange(s, in, &out, std::chrono::seconds(20));
  close(s);
  if (!ended) finding("no answer and no close within 20 s", "request:\n" + in + "\nanswer so far:\n" + out);
  const size_t answers = check_responses(in, out);
  if (out.empty() && has_complete_head(in)) finding("a complete request head got no answer", in);
  static const bool verbose = std::getenv("FUZZ_HTTP_VERBOSE") != nullptr;
  if (verbose) {  // each answer's status line, to see what the inputs reach
    std::fprintf(stderr, "%zu bytes -> %zu answers, %zu bytes:", size, answers, out.size());
    for (size_t at = out.find("HTTP/1.1 "); at != std::string::npos; at = out.find("HTTP/1.1 ", at + 1))
      std::fprintf(stderr, " %s", out.substr(at + 9, 3).c_str());
    std::fprintf(stderr, "\n");
  }
  return 0;
}
