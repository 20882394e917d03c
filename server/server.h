// `iteas serve`: the HTTP API of SPEC §7 on a bounded worker pool (SPEC §8).
#pragma once

#include <cstdint>
#include <functional>
#include <string>
#include <vector>

namespace iteas {

struct ServerConfig {
  std::string host = "127.0.0.1";
  int port = 8080;
  int workers = 0;                 // 0: all cores
  int queue = 16;                  // jobs waiting for a worker
  int http_threads = 0;            // connection threads; 0: max(64, 8 x workers)
  int64_t max_upload_bytes = 256LL << 20;
  int64_t max_output_triangles = 5000000;
  int request_timeout_s = 300;     // synchronous requests
  int job_ttl_s = 600;
  int64_t result_bytes_cap = 1LL << 30;
  int64_t memory_limit = 0;        // bytes for uploads + work; 0: 3/4 of RAM or of the cgroup limit
  int grace_s = 30;                // SIGTERM: time running work gets to finish
  int read_timeout_s = 10;         // a stalled client is dropped after this; a request's head must all come within it
  int64_t min_rate = 16384;        // bytes/s a body or response averages once read_timeout has passed; 0: no rule
  int trim_delay_ms = 1000;        // idle time before freed memory goes back; 0: after every job
  int lone_job_threads = 0;        // a job alone in the queue gets these threads; 0: all cores
  std::string web_root;             // the page at /; empty: <binary dir>/web when it exists
  std::string job_dir;              // shared job store (all replicas); empty: in memory only
  std::string api_key;             // empty: no authentication
  std::string log_format = "text"; // text or json
  // Called once the port is bound, with its number (port 0 lets the system
  // pick one): for callers that run the server in their own process.
  std::function<void(int port)> on_listening;
};

// Parses `--name value` flags, each with an ITEAS_NAME environment
// equivalent (flags win). Returns false with |error| set on a bad flag.
bool parse_server_flags(const std::vector<std::string>& args, ServerConfig* config, std::string* error);

// Runs until SIGTERM/SIGINT, then drains. Returns the process exit code.
int serve(const ServerConfig& config);

}  // namespace iteas
