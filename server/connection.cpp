#include "server/connection.h"

#include <netdb.h>
#include <netinet/in.h>
#include <poll.h>
#include <strings.h>
#include <sys/socket.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <cctype>
#include <cerrno>
#include <chrono>
#include <cstring>
#include <string>
#include <string_view>

namespace iteas {
namespace {

using Clock = std::chrono::steady_clock;

int64_t ms_until(Clock::time_point t) {
  return std::chrono::duration_cast<std::chrono::milliseconds>(t - Clock::now()).count();
}

// Waits up to |ms| for |events| on |sock|: true when they came (or the
// socket closed or failed: the next recv or send says which).
bool wait_for(socket_t sock, short events, int64_t ms) {
  for (const auto end = Clock::now() + std::chrono::milliseconds(ms);;) {
    pollfd p{sock, events, 0};
    const int r = ::poll(&p, 1, int(std::clamp<int64_t>(ms_until(end), 0, 1 << 30)));
    if (r > 0) return true;
    if (r == 0 || errno != EINTR) return false;
  }
}

class GuardedStream final : public httplib::Stream {
 public:
  GuardedStream(socket_t sock, const ConnectionLimits& limits) : sock_(sock), limits_(limits) {}

  // Waits up to the keep-alive timeout for a request's first byte; false
  // when none came or the server is stopping. (A client's close counts as
  // a byte: the request's read then finds the end.)
  bool wait_for_request(const std::atomic<socket_t>& server_socket) {
    if (off_ < len_) return true;
    const auto end = Clock::now() + std::chrono::seconds(limits_.keep_alive_timeout_s);
    while (server_socket != INVALID_SOCKET) {
      const int64_t left = ms_until(end);
      if (left <= 0) return false;
      if (wait_for(sock_, POLLIN, std::min<int64_t>(left, 100))) return true;
    }
    return false;
  }

  void begin_request(bool last) {
    last_ = last;
    head_.clear();
    phase_ = Phase::kHead;
    phase_start_ = Clock::now();
    phase_bytes_ = 0;
    budget_ = kHeadBytes;
    line_ended_ = false;
    hit_ = LimitHit::kNone;
    cut_ = false;
    line_ = 0;
    line_pos_ = 0;
    last_byte_ = 0;
    range_name_ = true;
    space_due_ = false;
  }
  void set_body_budget(size_t bytes) {
    phase_ = Phase::kBody;
    phase_start_ = Clock::now();
    phase_bytes_ = 0;
    budget_ = bytes;
  }
  LimitHit hit() const { return hit_; }
  bool cut() const { return cut_; }
  bool close_requested() const { return close_; }
  bool last() const { return last_; }
  const std::string& head() const { return head_; }
  void request_close() { close_ = true; }

  // Closes the socket. With |linger|, the client may still be sending (a
  // body left unread, a limit hit): the write side is shut first and what
  // comes is read and dropped for a moment, so that a reset does not destroy
  // the answer before the client has read it.
  void close(bool linger) {
    if (linger && ::shutdown(sock_, SHUT_WR) == 0) {
      char scratch[16384];
      const auto end = Clock::now() + std::chrono::milliseconds(std::min(2000, limits_.read_timeout_s * 1000));
      for (int64_t left; (left = ms_until(end)) > 0 && wait_for(sock_, POLLIN, left);) {
        const ssize_t n = ::recv(sock_, scratch, sizeof scratch, 0);
        if (n == 0 || (n < 0 && errno != EINTR)) break;
      }
    }
    ::shutdown(sock_, SHUT_RDWR);
    ::close(sock_);
  }

  bool is_readable() const override {
    return off_ < len_ || wait_for(sock_, POLLIN, int64_t(limits_.read_timeout_s) * 1000);
  }
  bool is_writable() const override { return wait_for(sock_, POLLOUT, int64_t(limits_.read_timeout_s) * 1000); }

  ssize_t read(char* ptr, size_t size) override {
    if (hit_ != LimitHit::kNone || size == 0) return -1;
    if (space_due_) {  // see defer_range
      space_due_ = false;
      *ptr = kDeferredRange[kRangeName];
      return 1;
    }
    if (budget_ == 0) return stop(phase_ == Phase::kHead ? LimitHit::kHeadTooLarge : LimitHit::kBodyTooLarge, ptr);
    size = std::min(size, budget_);
    // The head goes through the buffer, where defer_range can look at it
    // before httplib does (httplib reads it a byte at a time).
    const bool in_head = line_ != kHeadEnded;
    const bool direct = size >= sizeof buf_ && !in_head;  // straight into |ptr|
    if (off_ == len_) {
      LimitHit why = LimitHit::kNone;
      const int64_t ms = wait_ms(&why);
      if (ms <= 0 || !wait_for(sock_, POLLIN, ms)) return stop(why != LimitHit::kNone ? why : timeout_kind(), ptr);
      ssize_t n;
      do {
        n = direct ? ::recv(sock_, ptr, size, 0) : ::recv(sock_, buf_, sizeof buf_, 0);
      } while (n < 0 && errno == EINTR);
      if (n <= 0) return n;
      if (direct) return took(ptr, size_t(n));
      off_ = 0;
      len_ = size_t(n);
    }
    size_t n = std::min(size, len_ - off_);
    if (in_head) {
      n = defer_range(buf_ + off_, n);
      if (n == 0) return read(ptr, size);  // a space is due first
    }
    std::memcpy(ptr, buf_ + off_, n);
    off_ += n;
    return took(ptr, n);
  }

  ssize_t write(const char* ptr, size_t size) override {
    if (phase_ != Phase::kResponse) {
      phase_ = Phase::kResponse;
      phase_start_ = Clock::now();
      phase_bytes_ = 0;
    }
    // Each send takes what the socket has room for (MSG_DONTWAIT): a blocking
    // send of a whole 17 MB response waited for as long as the client did not
    // read. httplib calls again for the rest.
    for (;;) {
      LimitHit why = LimitHit::kNone;
      const int64_t ms = wait_ms(&why);
      if (ms <= 0 || !wait_for(sock_, POLLOUT, ms)) {
        if (hit_ == LimitHit::kNone) hit_ = LimitHit::kTooSlow;
        cut_ = true;
        return -1;
      }
      const ssize_t n = ::send(sock_, ptr, size, MSG_NOSIGNAL | MSG_DONTWAIT);
      if (n < 0 && (errno == EINTR || errno == EAGAIN || errno == EWOULDBLOCK)) continue;
      if (n < 0) cut_ = true;
      if (n > 0) phase_bytes_ += uint64_t(n);
      return n;
    }
  }

  void get_remote_ip_and_port(std::string& ip, int& port) const override { address(&getpeername, ip, port); }
  void get_local_ip_and_port(std::string& ip, int& port) const override { address(&getsockname, ip, port); }
  socket_t socket() const override { return sock_; }

 private:
  enum class Phase { kHead, kBody, kResponse };

  LimitHit timeout_kind() const { return phase_ == Phase::kHead ? LimitHit::kHeadTimeout : LimitHit::kTooSlow; }

  // httplib answers 416 itself, before any handler, to a Range header it
  // cannot parse, on any method: a POST with "Range: pages=1" lost its
  // upload. RFC 9110 §14.2 has a server ignore such a header. So each header
  // line named Range (any case) is handed to httplib with a space before its
  // colon, under the name kDeferredRange; the server takes it back before
  // routing (take_deferred_range). A client cannot send that name: a space
  // before a colon is refused (connection_head_fault), and head_ keeps the
  // line as it came. Of the |n| head bytes at |p|, returns how many may be
  // handed now; 0 when the space is due first.
  size_t defer_range(const char* p, size_t n) {
    for (size_t i = 0; i < n; ++i) {
      const char c = p[i];
      if (line_ > 0 && line_pos_ == kRangeName && range_name_ && c == ':') {
        if (i > 0) return i;
        space_due_ = true;
        ++line_pos_;  // the space is the line's next byte
        return 0;
      }
      if (line_pos_ < kRangeName)
        range_name_ = range_name_ && std::tolower(static_cast<unsigned char>(c)) ==
                                         std::tolower(static_cast<unsigned char>(kDeferredRange[line_pos_]));
      if (c == '\n') {
        // The head ends with its first line of CR LF alone (a line of LF
        // alone httplib skips, reading on).
        const bool blank = line_ > 0 && line_pos_ == 1 && last_byte_ == '\r';
        line_ = blank ? kHeadEnded : line_ + 1;
        line_pos_ = 0;
        range_name_ = true;
        last_byte_ = c;
        if (blank) return i + 1;
        continue;
      }
      ++line_pos_;
      last_byte_ = c;
    }
    return n;
  }

  // How long the next wait may take: at most the read timeout; for the
  // head, until its deadline; for a body or a response, until the rate
  // rule (bytes >= min_rate x (elapsed - read timeout)) would be broken.
  // <= 0 with |why| set when that time has passed.
  int64_t wait_ms(LimitHit* why) const {
    const auto grace = std::chrono::seconds(limits_.read_timeout_s);
    int64_t wait = int64_t(limits_.read_timeout_s) * 1000;
    if (phase_ == Phase::kHead) {
      wait = std::min(wait, ms_until(phase_start_ + grace));
      if (wait <= 0) *why = LimitHit::kHeadTimeout;
    } else if (limits_.min_rate > 0) {
      const auto due = phase_start_ + grace + std::chrono::microseconds(phase_bytes_ * 1000000 / uint64_t(limits_.min_rate));
      wait = std::min(wait, ms_until(due));
      if (wait <= 0) *why = LimitHit::kTooSlow;
    }
    return wait;
  }

  ssize_t took(const char* ptr, size_t n) {
    budget_ -= n;
    phase_bytes_ += n;
    if (phase_ == Phase::kHead) {
      if (!line_ended_) line_ended_ = std::memchr(ptr, '\n', n) != nullptr;
      head_.append(ptr, n);  // at most kHeadBytes: the head's budget
    }
    return ssize_t(n);
  }

  // A limit is hit: every read from now fails. In the request line, httplib
  // would take a failed read for the client's close and answer nothing; the
  // line is ended instead, so that httplib answers it (414 past 8,192
  // bytes, else 400) and its error handler sees why. No request can be
  // routed after this: its headers' read fails.
  ssize_t stop(LimitHit why, char* ptr) {
    hit_ = why;
    if (phase_ != Phase::kHead || line_ended_) return -1;
    line_ended_ = true;
    *ptr = '\n';
    return 1;
  }

  void address(int (*get)(int, sockaddr*, socklen_t*), std::string& ip, int& port) const {
    sockaddr_storage addr{};
    socklen_t len = sizeof addr;
    if (get(sock_, reinterpret_cast<sockaddr*>(&addr), &len) != 0) return;
    char host[NI_MAXHOST];
    if (getnameinfo(reinterpret_cast<sockaddr*>(&addr), len, host, sizeof host, nullptr, 0, NI_NUMERICHOST) == 0) ip = host;
    if (addr.ss_family == AF_INET) port = ntohs(reinterpret_cast<sockaddr_in*>(&addr)->sin_port);
    if (addr.ss_family == AF_INET6) port = ntohs(reinterpret_cast<sockaddr_in6*>(&addr)->sin6_port);
  }

  const socket_t sock_;
  const ConnectionLimits limits_;
  char buf_[4096];
  size_t off_ = 0, len_ = 0;
  Phase phase_ = Phase::kHead;
  Clock::time_point phase_start_ = Clock::now();
  uint64_t phase_bytes_ = 0;
  size_t budget_ = kHeadBytes;
  bool line_ended_ = false;
  LimitHit hit_ = LimitHit::kNone;
  bool cut_ = false;  // a write failed: the response did not all go
  bool close_ = false;
  bool last_ = false;  // the connection's last request
  std::string head_;   // the request line and headers as they came
  // Where defer_range is in the head: its line (0: the request line;
  // kHeadEnded past the head), the bytes of that line handed so far, the
  // last of them, whether they begin "range", and whether a space is due.
  static constexpr size_t kHeadEnded = ~size_t(0);
  // kDeferredRange is the name "Range" and the byte added after it.
  static constexpr size_t kRangeName = sizeof kDeferredRange - 2;
  size_t line_ = 0, line_pos_ = 0;
  char last_byte_ = 0;
  bool range_name_ = true;
  bool space_due_ = false;
};

// tchar of RFC 9110 §5.6.2: what a header name is made of.
bool is_token_char(unsigned char c) {
  return std::isalnum(c) || std::strchr("!#$%&'*+-.^_`|~", c) != nullptr;
}

thread_local GuardedStream* t_stream = nullptr;

}  // namespace

GuardedServer::GuardedServer(const ConnectionLimits& limits) : limits_(limits) {
  // What httplib writes in each response's Keep-Alive header.
  set_keep_alive_timeout(limits.keep_alive_timeout_s);
  set_keep_alive_max_count(size_t(std::max(1, limits.keep_alive_max)));
  set_socket_options([this](socket_t sock) {
    const int yes = 1;
    ::setsockopt(sock, SOL_SOCKET, SO_REUSEADDR, &yes, sizeof yes);
    last_socket_ = sock;
  });
}

bool GuardedServer::raise_listen_backlog(int backlog) {
  int listening = 0;
  socklen_t size = sizeof listening;
  if (last_socket_ == INVALID_SOCKET || ::getsockopt(last_socket_, SOL_SOCKET, SO_ACCEPTCONN, &listening, &size) != 0 ||
      !listening)
    return false;
  return ::listen(last_socket_, backlog) == 0;
}

bool GuardedServer::process_and_close_socket(socket_t sock) {
  GuardedStream strm(sock, limits_);
  t_stream = &strm;
  bool ret = false;
  for (int left = std::max(1, limits_.keep_alive_max); left > 0 && strm.wait_for_request(svr_sock_); --left) {
    strm.begin_request(left == 1);
    bool connection_closed = false;
    ret = process_request(strm, left == 1, connection_closed, nullptr);
    if (!ret || connection_closed || strm.close_requested() || strm.hit() != LimitHit::kNone) break;
  }
  t_stream = nullptr;
  strm.close(strm.close_requested() || strm.hit() != LimitHit::kNone);
  return ret;
}

void connection_body_budget(size_t bytes) {
  if (t_stream) t_stream->set_body_budget(bytes);
}

LimitHit connection_limit_hit() { return t_stream ? t_stream->hit() : LimitHit::kNone; }

bool connection_response_cut() { return t_stream && t_stream->cut(); }

void connection_close_after_answer() {
  if (t_stream) t_stream->request_close();
}

bool connection_last_request() { return t_stream && t_stream->last(); }

std::string connection_head_fault() {
  if (!t_stream) return "";
  std::string_view head = t_stream->head();
  const size_t request_line = head.find('\n');
  if (request_line == std::string_view::npos) return "";
  head.remove_prefix(request_line + 1);
  while (!head.empty()) {
    const size_t end = head.find('\n');
    std::string_view line = head.substr(0, end);
    head.remove_prefix(end == std::string_view::npos ? head.size() : end + 1);
    if (!line.empty() && line.back() == '\r') line.remove_suffix(1);
    if (line.empty()) break;  // the end of the head
    if (line[0] == ' ' || line[0] == '\t') return "a header line is folded onto the one before it";
    const size_t colon = line.find(':');
    if (colon == std::string_view::npos) return "a header line has no colon";
    const std::string_view name = line.substr(0, colon);
    if (name.empty() || !std::all_of(name.begin(), name.end(), [](char c) { return is_token_char(static_cast<unsigned char>(c)); }))
      return "a header name is not a token (no space may come before its colon)";
    // httplib decodes %XX in every header value: "%36%34" framed as 64.
    for (const char* framing : {"Content-Length", "Transfer-Encoding"})
      if (name.size() == std::strlen(framing) && strncasecmp(name.data(), framing, name.size()) == 0 &&
          line.find('%', colon) != std::string_view::npos)
        return std::string(framing) + " is percent-encoded";
  }
  return "";
}

}  // namespace iteas
