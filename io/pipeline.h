// The one path every front end takes: decode -> refine each mesh -> encode,
// with statistics (SPEC §5). The CLI and the HTTP server both call run_job().
#pragma once

#include <atomic>
#include <cstdint>
#include <functional>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "core/refine.h"
#include "io/document.h"

namespace iteas {

struct JobRequest {
  const uint8_t* data = nullptr;
  size_t size = 0;
  std::string name_hint;      // file name (for formats without magic)
  std::string output_format;  // glb, gltf, drc, obj, ply
  Options options;
  bool refine = true;         // false: convert only
  ReadLimits limits;
  // Threads for the work around the core's loops: several meshes refined at
  // once (one thread each) and several Draco payloads encoded at once. 0:
  // options.refine.threads. The server gives 1, so that all a job allocates
  // outside the core's loops stays on its own thread, under its memory
  // budget (a cap per thread).
  int outer_threads = 0;
};

struct JobHooks {
  std::function<double()> now_ms;  // the caller's clock
  std::function<void(int level, const char* phase, double fraction)> progress;
  const std::atomic<bool>* cancel = nullptr;
};

struct JobResult {
  std::vector<uint8_t> bytes;
  nlohmann::json stats;
  bool cancelled = false;
};

Status run_job(const JobRequest& request, const JobHooks& hooks, JobResult* result);

// Upper bound, before decoding, of the heap a job needs: the input, the decoded
// mesh (triangles bounded from the byte count, Draco by its bomb limit), and the
// refined output (bounded by max_triangles), at per-triangle costs measured on
// a 1.1M -> 5M triangle job (about 140 bytes per output triangle of peak RSS).
int64_t estimate_job_bytes(const JobRequest& request);

// Facts about a file without refining it (iteas inspect).
Status inspect(const uint8_t* data, size_t size, const std::string& name_hint, const ReadLimits& limits,
               nlohmann::json* out);

// The statistics document from its parts (io/stats_json.cpp).
nlohmann::json stats_json(const Document& doc, const std::vector<RefineStats>& per_mesh, const Options& options,
                          const std::string& output_format, const WriteCounts& out_counts, bool refined);

nlohmann::json options_json(const Options& options, const std::string& output_format);

// |j| as text, with any string that is not valid UTF-8 written with U+FFFD in
// place of its bad bytes. nlohmann::json::dump throws on such a string, and
// they come from clients: a request path or option name with a %AD in it, a
// reader's message quoting a malformed token (or 32 bytes of it, which can
// cut a character in two). Everything this program writes as JSON goes
// through here.
std::string json_text(const nlohmann::json& j, int indent = -1);

}  // namespace iteas
