// The iteas command line (SPEC §6): refine, convert, inspect (and serve, once
// the server exists). Exit codes: 0 ok, 2 bad usage, 3 bad input, 4 I/O.
#include <signal.h>
#include <sys/stat.h>
#include <unistd.h>

#include <cerrno>
#include <chrono>
#include <cstdlib>
#include <cstring>
#include <cstdio>
#include <fstream>
#include <iostream>
#include <iterator>
#include <string>
#include <vector>

#include "io/memory_budget.h"
#include "io/pipeline.h"
#include "server/server.h"

namespace {

constexpr int kExitOk = 0, kExitUsage = 2, kExitBadInput = 3, kExitIo = 4;

const char* kUsage =
    "usage:\n"
    "  iteas refine IN -o OUT [options] [--stats FILE|-] [--threads N] [--memory-limit B|nK|nM|nG] [--quiet]\n"
    "  iteas convert IN OUT [output options] [--memory-limit B|nK|nM|nG]\n"
    "  iteas inspect IN [--memory-limit B|nK|nM|nG]\n"
    "  iteas --version\n"
    "  iteas serve [--host H] [--port P] [--workers N] [--queue N] [--max-upload-bytes B]\n"
    "              [--max-output-triangles N] [--request-timeout S] [--job-ttl S] [--result-bytes-cap B]\n"
    "              [--grace S] [--read-timeout S] [--api-key K] [--log-format text|json]\n"
    "              [--memory-limit B|nK|nM|nG] [--trim-delay MS] [--lone-job-threads N]\n"
    "              [--job-dir DIR] [--web-root DIR]\n"
    "              (or ITEAS_* env)\n"
    "options (SPEC §3): --mode iteas|uniform|fixed  --levels 1-8  --threshold mean|median|pNN|DEG\n"
    "  --threshold-scope input|level  --select above|below  --crease-angle DEG|off  --stall-ratio R|off\n"
    "  --tolerance F|off  --flat-limit F|off  (fractions of the bounding-box diagonal)\n"
    "  --max-triangles N  --tension W  --output glb|gltf|drc|obj|ply  --compression draco|none\n"
    "  --position-bits N --normal-bits N --texcoord-bits N --color-bits N --generic-bits N --draco-level 0-10\n"
    "formats in: glb gltf (data: URIs only) drc obj ply off stl; out: glb gltf drc obj ply\n"
    "IN may be - (stdin); OUT and --stats FILE may be - (stdout; OUT then with --output)\n";

int usage(const std::string& msg) {
  std::fprintf(stderr, "iteas: %s\n%s", msg.c_str(), kUsage);
  return kExitUsage;
}

// Reads all of |path| ("-": stdin). False, with errno telling why, when it
// cannot: a directory is refused before it is opened (read as a stream, its
// size showed as 2^63 bytes).
bool read_file(const std::string& path, std::vector<uint8_t>* out) {
  if (path == "-") {
    out->clear();
    char buffer[1 << 16];
    for (size_t n; (n = std::fread(buffer, 1, sizeof(buffer), stdin)) > 0;) out->insert(out->end(), buffer, buffer + n);
    return !std::ferror(stdin);
  }
  struct stat st;
  if (::stat(path.c_str(), &st) == 0 && S_ISDIR(st.st_mode)) {
    errno = EISDIR;
    return false;
  }
  errno = 0;
  std::ifstream f(path, std::ios::binary);
  if (!f) return false;
  // One read of the whole file where its size is known (stream iterators
  // copy a byte at a time); else (a pipe) the stream to its end.
  f.seekg(0, std::ios::end);
  const std::streamoff size = f.tellg();
  if (size >= 0 && f.seekg(0, std::ios::beg)) {
    out->resize(size_t(size));
    f.read(reinterpret_cast<char*>(out->data()), std::streamsize(size));
    if (f.gcount() == std::streamsize(size) && f.peek() == std::ifstream::traits_type::eof()) return true;
    if (f.bad()) return false;
    f.clear();  // the file changed size while read: the stream from the start
    f.seekg(0, std::ios::beg);
  } else {
    f.clear();
  }
  out->assign(std::istreambuf_iterator<char>(f), std::istreambuf_iterator<char>());
  return !f.bad();
}

// An existing file's path through any symbolic links (write_file replaces
// the file a link points to); |path| itself for anything else.
std::string resolved(const std::string& path) {
  char* real = ::realpath(path.c_str(), nullptr);
  if (!real) return path;
  std::string out = real;
  std::free(real);
  return out;
}

// The temporary file being written (empty when none): SIGINT, SIGTERM or
// SIGHUP while it is written removes it (only async-signal-safe calls), then
// ends the process as the signal would have.
char g_temp[4096];
volatile sig_atomic_t g_temp_set = 0;
extern "C" void remove_temp_and_reraise(int sig) {
  if (g_temp_set) ::unlink(g_temp);
  ::signal(sig, SIG_DFL);
  ::raise(sig);
}

// Writes |size| bytes to |path| ("-": stdout). A regular file (or a new one)
// is written beside it under a temporary name and renamed over it once
// whole: a failed write (a full disk, a file size limit) leaves the file
// that was there, never a truncated one, and nothing else behind. The file
// keeps its permissions, and a symbolic link its target (the file it points
// to is replaced). Anything else (a device such as /dev/null, a pipe) is
// written in place.
bool write_file(const std::string& given, const void* data, size_t size) {
  if (given == "-") return std::fwrite(data, 1, size, stdout) == size && std::fflush(stdout) == 0;
  const std::string path = resolved(given);
  struct stat st;
  const bool exists = ::stat(path.c_str(), &st) == 0;
  auto write_to = [&](const std::string& target) {
    std::ofstream f(target, std::ios::binary | std::ios::trunc);
    if (!f) return false;
    f.write(static_cast<const char*>(data), std::streamsize(size));
    f.close();
    return !f.fail();
  };
  if (exists && !S_ISREG(st.st_mode)) return write_to(path);
  const std::string temp = path + ".iteas-" + std::to_string(::getpid()) + ".tmp";
  if (temp.size() < sizeof(g_temp)) {
    std::memcpy(g_temp, temp.c_str(), temp.size() + 1);
    g_temp_set = 1;
  }
  bool ok = write_to(temp) && (!exists || ::chmod(temp.c_str(), st.st_mode & 07777) == 0) &&
            std::rename(temp.c_str(), path.c_str()) == 0;
  if (!ok) {
    const int e = errno;  // the write's reason, not the removal's
    std::remove(temp.c_str());
    errno = e;
  }
  g_temp_set = 0;
  return ok;
}

// The directory a path names its file in ("." for a bare name).
std::string directory_of(const std::string& path) {
  const size_t slash = path.find_last_of('/');
  return slash == std::string::npos ? "." : slash == 0 ? "/" : path.substr(0, slash);
}

// Can |path| be written ("-" can)? Asked before the job, so that a wrong
// path fails at once rather than after the refinement, and leaves the other
// output untouched. False, with errno telling why: a directory, a missing or
// read-only directory to write in.
bool writable(const std::string& path) {
  if (path == "-") return true;
  struct stat st;
  if (::stat(path.c_str(), &st) == 0) {
    if (S_ISDIR(st.st_mode)) {
      errno = EISDIR;
      return false;
    }
    if (!S_ISREG(st.st_mode)) return ::access(path.c_str(), W_OK) == 0;  // a device, written in place
  }
  // A regular file is written beside itself and renamed: its directory.
  return ::access(directory_of(resolved(path)).c_str(), W_OK) == 0;
}

// Do OUT and --stats name one file (through links, "./", hard links)? Then
// the statistics would replace the mesh, with exit 0. Devices (/dev/null)
// may be named twice.
bool same_file(const std::string& a, const std::string& b) {
  struct stat sa, sb;
  const bool has_a = ::stat(a.c_str(), &sa) == 0, has_b = ::stat(b.c_str(), &sb) == 0;
  if (has_a && has_b) return S_ISREG(sa.st_mode) && sa.st_dev == sb.st_dev && sa.st_ino == sb.st_ino;
  if (has_a || has_b) return false;
  // Neither exists yet: the same name in the same directory.
  auto target = [](const std::string& path) {
    const size_t slash = path.find_last_of('/');
    return resolved(directory_of(path)) + "/" + path.substr(slash == std::string::npos ? 0 : slash + 1);
  };
  return target(a) == target(b);
}

// "iteas: cannot read|write PATH: the system's reason".
int io_error(const char* what, const std::string& path) {
  const int e = errno;
  std::fprintf(stderr, "iteas: cannot %s %s%s%s\n", what, path.c_str(), e ? ": " : "", e ? std::strerror(e) : "");
  return kExitIo;
}

std::string extension_of(const std::string& path) {
  const size_t dot = path.find_last_of('.');
  const size_t slash = path.find_last_of('/');
  if (dot == std::string::npos || (slash != std::string::npos && dot < slash)) return "";
  std::string e = path.substr(dot + 1);
  for (char& c : e) c = char(std::tolower(static_cast<unsigned char>(c)));
  return e;
}

int exit_for(const iteas::Status& s) { return s.kind == iteas::ErrorKind::kIo ? kExitIo : kExitBadInput; }

double now_ms() {
  using namespace std::chrono;
  return duration<double, std::milli>(steady_clock::now().time_since_epoch()).count();
}

int refine_or_convert(const std::string& in, const std::string& out, const std::string& stats_path,
                      const std::string& out_format, const iteas::Options& options, bool refine, bool quiet);

// Runs |job| (a command's work on the file |in|) with all the process holds
// capped at |limit| bytes (0: default_memory_limit()), its input's bytes
// included: past it the job stops with one line and exit 3, where the kernel
// would kill the process. |hint| (may be empty) says what to lower.
template <typename Job>
int under_memory_limit(const std::string& in, int64_t limit, const std::string& hint, const Job& job) {
  if (limit <= 0) limit = iteas::default_memory_limit();
  iteas::set_process_heap_limit(limit);
  try {
    return job();
  } catch (const iteas::MemoryLimitExceeded&) {
    const std::string size = limit >= (1 << 20) ? std::to_string(limit >> 20) + " MiB" : std::to_string(limit) + " bytes";
    std::fprintf(stderr,
                 "iteas: %s: the job needs more memory than its limit of %s (--memory-limit; by default 3/4 of "
                 "the machine's memory or of its container's limit)%s%s (memory_limit)\n",
                 in.c_str(), size.c_str(), hint.empty() ? "" : ": ", hint.c_str());
    return kExitBadInput;
  }
}

// --memory-limit SIZE or --memory-limit=SIZE at args[i] (true, with i moved
// past its value); false for any other argument. |error| is set on a bad size.
bool memory_limit_flag(const std::vector<std::string>& args, size_t& i, int64_t* limit, std::string* error) {
  const std::string& a = args[i];
  if (a != "--memory-limit" && a.rfind("--memory-limit=", 0) != 0) return false;
  std::string v;
  if (a.size() > 14) v = a.substr(15);
  else if (i + 1 < args.size()) v = args[++i];
  else *error = "--memory-limit needs a size";
  if (error->empty() && !iteas::parse_byte_size(v, limit))
    *error = "--memory-limit: expected bytes, or a number with K, M or G, got '" + v + "'";
  return true;
}

// refine and convert share everything but the refinement itself.
int run(const std::vector<std::string>& args, bool refine) {
  std::string in, out, stats_path;
  bool quiet = false;
  int64_t memory_limit = 0;  // 0: default_memory_limit()
  std::vector<std::pair<std::string, std::string>> pairs;
  for (size_t i = 0; i < args.size(); ++i) {
    const std::string& a = args[i];
    auto value = [&](std::string* v) {
      if (i + 1 >= args.size()) return false;
      *v = args[++i];
      return true;
    };
    if (a == "-o" || a == "--out") {
      if (!value(&out)) return usage("-o needs a file");
    } else if (a == "--stats") {
      if (!value(&stats_path)) return usage("--stats needs a file or -");
    } else if (a == "--quiet" || a == "-q") {
      quiet = true;
    } else if (std::string error; memory_limit_flag(args, i, &memory_limit, &error)) {
      if (!error.empty()) return usage(error);
    } else if (a.rfind("--", 0) == 0 && a.size() > 2) {
      std::string name = a.substr(2), v;
      const size_t eq = name.find('=');
      if (eq != std::string::npos) { v = name.substr(eq + 1); name = name.substr(0, eq); }
      else if (!value(&v)) return usage("option --" + name + " needs a value");
      pairs.emplace_back(name, v);
    } else if (in.empty()) {
      in = a;
    } else if (!refine && out.empty()) {
      out = a;
    } else {
      return usage("unexpected argument '" + a + "'");
    }
  }
  if (in.empty() || out.empty()) return usage(refine ? "refine needs IN and -o OUT" : "convert needs IN and OUT");
  iteas::Options options;
  std::string error;
  if (!iteas::parse_options(pairs, &options, &error)) return usage(error);
  std::string out_format = options.out.output.empty() ? extension_of(out) : options.out.output;
  if (out_format != "glb" && out_format != "gltf" && out_format != "drc" && out_format != "obj" && out_format != "ply")
    return usage("cannot tell the output format from '" + out + "': use .glb .gltf .drc .obj .ply or --output");
  if (out == "-" && stats_path == "-") return usage("OUT and --stats cannot both be - (stdout)");
  if (!stats_path.empty() && stats_path != "-" && out != "-" && same_file(out, stats_path))
    return usage("OUT and --stats name the same file: the statistics would replace the mesh");
  for (const std::string& path : {out, stats_path})
    if (!path.empty() && !writable(path)) return io_error("write", path);

  return under_memory_limit(in, memory_limit, refine ? "lower --max-triangles or --levels" : "",
                            [&] { return refine_or_convert(in, out, stats_path, out_format, options, refine, quiet); });
}

// run()'s job once its arguments are checked.
int refine_or_convert(const std::string& in, const std::string& out, const std::string& stats_path,
                      const std::string& out_format, const iteas::Options& options, bool refine, bool quiet) {
  std::vector<uint8_t> bytes;
  if (!read_file(in, &bytes)) {
    return io_error("read", in);
  }
  iteas::JobRequest rq;
  rq.data = bytes.data();
  rq.size = bytes.size();
  rq.name_hint = in;
  rq.output_format = out_format;
  rq.options = options;
  rq.refine = refine;
  iteas::JobHooks hooks;
  hooks.now_ms = now_ms;
  const bool tty = !quiet && isatty(STDERR_FILENO);
  if (tty)
    hooks.progress = [](int level, const char* phase, double fraction) {
      if (level > 0) std::fprintf(stderr, "\r[iteas] level %d %-8s %3.0f%%", level, phase, fraction * 100.0);
      else std::fprintf(stderr, "\r[iteas] %-16s      ", phase);
      std::fflush(stderr);
    };
  iteas::JobResult result;
  const iteas::Status s = iteas::run_job(rq, hooks, &result);
  if (tty) std::fprintf(stderr, "\r%60s\r", "");
  if (!s.ok()) {
    std::fprintf(stderr, "iteas: %s: %s (%s)\n", in.c_str(), s.message.c_str(), s.code.c_str());
    return exit_for(s);
  }
  if (!write_file(out, result.bytes.data(), result.bytes.size())) {
    return io_error("write", out);
  }
  if (!stats_path.empty()) {
    const std::string text = iteas::json_text(result.stats, 2) + "\n";
    if (!write_file(stats_path, text.data(), text.size())) {
      return io_error("write", stats_path);
    }
  }
  for (const auto& w : result.stats["warnings"])
    if (!quiet) std::fprintf(stderr, "iteas: warning: %s\n", w.get<std::string>().c_str());
  return kExitOk;
}

int inspect(const std::vector<std::string>& args) {
  std::string in;
  int64_t memory_limit = 0;
  for (size_t i = 0; i < args.size(); ++i) {
    std::string error;
    if (memory_limit_flag(args, i, &memory_limit, &error)) {
      if (!error.empty()) return usage(error);
    } else if (in.empty()) {
      in = args[i];
    } else {
      return usage("inspect takes one file");
    }
  }
  if (in.empty()) return usage("inspect takes one file");
  return under_memory_limit(in, memory_limit, "", [&] {
    std::vector<uint8_t> bytes;
    if (!read_file(in, &bytes)) {
      return io_error("read", in);
    }
    nlohmann::json j;
    const iteas::Status s = iteas::inspect(bytes.data(), bytes.size(), in, iteas::ReadLimits(), &j);
    if (!s.ok()) {
      std::fprintf(stderr, "iteas: %s: %s (%s)\n", in.c_str(), s.message.c_str(), s.code.c_str());
      return exit_for(s);
    }
    std::cout << iteas::json_text(j, 2) << "\n";
    return kExitOk;
  });
}

}  // namespace

int main(int argc, char** argv) {
  iteas::keep_freed_memory();
  // Past a file size limit (ulimit -f) a write fails with EFBIG and is
  // reported, instead of the default SIGXFSZ ending the process (a CLI run
  // left its temporary file behind; a server lost every job it held).
  ::signal(SIGXFSZ, SIG_IGN);
  for (int sig : {SIGINT, SIGTERM, SIGHUP})
    if (argc >= 2 && std::string(argv[1]) != "serve") ::signal(sig, remove_temp_and_reraise);
  if (argc < 2) return usage("missing command");
  const std::string cmd = argv[1];
  const std::vector<std::string> args(argv + 2, argv + argc);
  try {
    if (cmd == "refine") return run(args, true);
    if (cmd == "convert") return run(args, false);
    if (cmd == "inspect") return inspect(args);
    if (cmd == "serve") {
      iteas::ServerConfig config;
      std::string error;
      if (!iteas::parse_server_flags(args, &config, &error)) return usage(error);
      return iteas::serve(config);
    }
    if (cmd == "--version" || cmd == "version") {
      std::printf("iteas %s\n", ITEAS_VERSION);
      return kExitOk;
    }
    if (cmd == "--help" || cmd == "-h" || cmd == "help") {
      std::fputs(kUsage, stdout);
      return kExitOk;
    }
  } catch (const std::bad_alloc&) {
    std::fprintf(stderr, "iteas: out of memory\n");
    return kExitBadInput;
  } catch (const std::exception& e) {  // what a library threw instead of reporting: one line, exit 3
    std::fprintf(stderr, "iteas: the input could not be processed: %s\n", e.what());
    return kExitBadInput;
  }
  return usage("unknown command '" + cmd + "'");
}
