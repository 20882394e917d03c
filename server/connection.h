// The HTTP server's connections, read and written through a guarded stream.
//
// Debian's cpp-httplib 0.11 reads a request line and headers of any length
// (a 300 MB request line took the server to 600 MB), for as long as bytes
// keep coming (a client sending a header line a second held a connection
// thread for ever: 64 such clients stopped the server), and buffers a body
// no route reads whole. Its connection loop is a virtual function of
// httplib::Server; GuardedServer replaces it with one over GuardedStream,
// which bounds each request:
//   * the head (request line and headers) must all come within the read
//     timeout of its first byte, and within kHeadBytes;
//   * the body may take the bytes its route allows (connection_body_budget);
//   * a body and a response must each average min_rate bytes a second once
//     the read timeout has passed since they began;
//   * any single wait for the client is at most the read timeout.
// A request that breaks a limit is answered (httplib's error handler sees
// connection_limit_hit()) and its connection closed.
#pragma once

#include <httplib.h>

#include <cstddef>
#include <cstdint>
#include <string>

namespace iteas {

// The request line and headers, together.
constexpr size_t kHeadBytes = size_t(64) << 10;

// The name httplib is given each Range header under (see defer_range in
// connection.cpp): it answered 416 itself, before any handler, to one it
// could not parse. The server takes it back before routing.
constexpr char kDeferredRange[] = "Range ";

struct ConnectionLimits {
  int read_timeout_s = 10;
  int keep_alive_timeout_s = 2;
  int keep_alive_max = 8;   // requests a connection, then it is closed
  int64_t min_rate = 16384; // bytes a second; 0: no rate rule
};

// Why the current request's stream stopped.
enum class LimitHit { kNone, kHeadTimeout, kHeadTooLarge, kBodyTooLarge, kTooSlow };

class GuardedServer : public httplib::Server {
 public:
  // Its listening socket takes SO_REUSEADDR alone: httplib's default set
  // SO_REUSEPORT, so a second server on the same port started silently and
  // the kernel split the connections between the two.
  explicit GuardedServer(const ConnectionLimits& limits);

  // httplib 0.11 listens with a backlog of 5 (CPPHTTPLIB_LISTEN_BACKLOG,
  // compiled into Debian's library). A burst of connections then overflows
  // the kernel's accept queue: SYNs are dropped (the client waits 1 s to
  // send its again) or answered with cookies, and some connections are reset
  // on their first data (200 connections at once: 32-33 reset in two rounds
  // of three, up to 123 waiting over 0.9 s). After bind_to_port, this listens
  // again on the bound socket with |backlog| (the kernel caps it at
  // net.core.somaxconn). False when there is no bound listening socket.
  bool raise_listen_backlog(int backlog);

 private:
  bool process_and_close_socket(socket_t sock) override;
  ConnectionLimits limits_;
  // The last socket httplib's socket options were applied to: the one it
  // bound, once bind_to_port has succeeded (it tries its addresses in turn,
  // closing each that fails).
  socket_t last_socket_ = INVALID_SOCKET;
};

// For handlers, on the connection's thread (no-ops elsewhere, as in tests
// that call handlers directly):
// The head is read; the body may take up to |bytes| bytes off the wire.
void connection_body_budget(size_t bytes);
// What stopped the current request's stream, if anything.
LimitHit connection_limit_hit();
// The current response could not all be written (the client went, or read
// slower than the rate rule allows).
bool connection_response_cut();
// The connection is closed after the current answer (some of the body is
// left unread, or what follows cannot be trusted to be framed).
void connection_close_after_answer();
// The current request is the connection's last (httplib then says
// "Connection: close" itself).
bool connection_last_request();
// What is wrong with the current request's header lines as they came, which
// httplib does not say (it drops a line without a colon or with a space
// before it, and unfolds nothing), or empty. Called once the head is read.
std::string connection_head_fault();

}  // namespace iteas
