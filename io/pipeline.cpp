#include "io/pipeline.h"

#include <algorithm>
#include <atomic>
#include <cmath>
#include <mutex>

#include "core/angles.h"
#include "core/corner_table.h"
#include "core/parallel.h"

namespace iteas {

int64_t estimate_job_bytes(const JobRequest& r) {
  const int64_t size = int64_t(r.size);
  const std::string fmt = sniff_format(r.data, r.size, r.name_hint);
  static const std::string kDraco = "KHR_draco_mesh_compression";
  const bool draco = fmt == "drc" || std::search(r.data, r.data + r.size, kDraco.begin(), kDraco.end()) != r.data + r.size;
  // Plain formats spend at least 6 bytes per triangle (three 16-bit indices or
  // more); a Draco payload decodes within its bomb limit at >= 40 B/triangle.
  int64_t tris_in = draco ? (r.limits.draco_base_bytes + r.limits.draco_expansion * size) / 40 : size / 6 + 1;
  tris_in = std::min(tris_in, r.limits.max_triangles);
  int64_t tris_out = tris_in;
  if (r.refine)
    for (int l = 0; l < r.options.refine.levels && tris_out < r.options.refine.max_triangles; ++l) tris_out *= 4;
  tris_out = std::min(tris_out, std::max(tris_in, r.options.refine.max_triangles));
  return (64LL << 20) + 4 * size + 100 * tris_in + 160 * tris_out;
}

Status run_job(const JobRequest& rq, const JobHooks& hooks, JobResult* result) {
  auto now = [&] { return hooks.now_ms ? hooks.now_ms() : 0.0; };
  const double t0 = now();
  // Threads for the work around the core's loops (JobRequest::outer_threads).
  const int outer = rq.outer_threads > 0 ? rq.outer_threads : rq.options.refine.threads;
  const std::string format = sniff_format(rq.data, rq.size, rq.name_hint);
  if (format.empty())
    return Status::Error(ErrorKind::kUnsupported, "unsupported_format",
                         "unrecognised input format (expected glb, gltf, drc, obj, ply, off or stl)");
  Document doc;
  Status s = read_document(rq.data, rq.size, format, rq.limits, &doc);
  if (!s.ok()) return s;
  const double t_decoded = now();

  std::vector<RefineStats> per_mesh(doc.meshes.size());
  double ms_topology = 0, ms_refine = 0;
  if (rq.refine) {
    // max_triangles bounds the whole output: each mesh gets a share in
    // proportion to its input (never less than what it already has).
    int64_t total_in = 0, largest = 0;
    for (const MeshSlot& m : doc.meshes) {
      total_in += m.mesh.num_faces();
      largest = std::max<int64_t>(largest, m.mesh.num_faces());
    }
    // Several meshes, none of them most of the work: refined at once, one
    // thread each; otherwise one after another on all the job's threads.
    // (A mesh's result is the same on any number of threads.)
    const int threads = resolve_threads(outer);
    const bool at_once = threads > 1 && doc.meshes.size() > 1 && 2 * largest <= total_in;
    std::mutex progress_mutex;
    std::atomic<bool> cancelled{false};
    auto refine_one = [&](size_t i, int mesh_threads) {
      RefineOptions ro = rq.options.refine;
      ro.threads = mesh_threads;
      const int64_t own = doc.meshes[i].mesh.num_faces();
      if (doc.meshes.size() > 1 && total_in > 0)
        ro.max_triangles = std::max<int64_t>(own, int64_t(double(ro.max_triangles) * double(own) / double(total_in)));
      RefineHooks rh;
      rh.now_ms = hooks.now_ms;
      if (hooks.progress && at_once)
        rh.progress = [&](int level, const char* phase, double fraction) {
          std::lock_guard<std::mutex> lock(progress_mutex);
          hooks.progress(level, phase, fraction);
        };
      else
        rh.progress = hooks.progress;
      rh.cancel = hooks.cancel;
      if (refine_mesh(doc.meshes[i].mesh, ro, rh, &per_mesh[i]) == RefineResult::kCancelled) cancelled = true;
    };
    if (at_once) {
      parallel_for_chunks(int64_t(doc.meshes.size()), threads, [&](int64_t b, int64_t e) {
        for (int64_t i = b; i < e && !cancelled; ++i) refine_one(size_t(i), 1);
      });
    } else {
      for (size_t i = 0; i < doc.meshes.size() && !cancelled; ++i) refine_one(i, rq.options.refine.threads);
    }
    if (cancelled) {
      result->cancelled = true;
      return Status::Ok();
    }
    for (const RefineStats& st : per_mesh) {
      ms_topology += st.ms_topology;
      ms_refine += st.ms_refine;
    }
    if (at_once && ms_topology + ms_refine > 0) {
      // The meshes' own times overlap: the phase's wall time, split between
      // topology and refinement as theirs are.
      const double wall = now() - t_decoded, share = ms_topology / (ms_topology + ms_refine);
      ms_topology = wall * share;
      ms_refine = wall - ms_topology;
    }
  } else {
    per_mesh.clear();
  }
  const double t_refined = now();
  if (hooks.progress) hooks.progress(0, "encode", 0.0);

  WriteCounts counts;
  const std::string out_format = rq.output_format.empty() ? "glb" : rq.output_format;
  auto make_stats = [&](const WriteCounts& c) { return stats_json(doc, per_mesh, rq.options, out_format, c, rq.refine); };
  OutputOptions out = rq.options.out;
  out.threads = outer;
  s = write_document(doc, out, out_format, make_stats, &result->bytes, &counts);
  if (!s.ok()) return s;
  const double t_encoded = now();
  result->stats = make_stats(counts);
  result->stats["output"]["bytes"] = int64_t(result->bytes.size());
  auto r3 = [](double x) { return std::round(x * 1000.0) / 1000.0; };
  result->stats["timings_ms"] = {{"decode", r3(t_decoded - t0)},   {"topology", r3(ms_topology)},
                                 {"refine", r3(ms_refine)},         {"encode", r3(t_encoded - t_refined)},
                                 {"total", r3(t_encoded - t0)}};
  return Status::Ok();
}

Status inspect(const uint8_t* data, size_t size, const std::string& name_hint, const ReadLimits& limits,
               nlohmann::json* out) {
  const std::string format = sniff_format(data, size, name_hint);
  if (format.empty()) return Status::Error(ErrorKind::kUnsupported, "unsupported_format", "unrecognised input format");
  Document doc;
  Status s = read_document(data, size, format, limits, &doc);
  if (!s.ok()) return s;
  nlohmann::json meshes = nlohmann::json::array();
  int64_t tris = 0, verts = 0, welded = 0, boundary = 0, cut = 0, dropped = 0, prims = 0;
  std::vector<int64_t> hist(18, 0);
  double theta_sum = 0;
  int64_t theta_edges = 0;
  for (MeshSlot& slot : doc.meshes) {
    Mesh m = slot.mesh;
    CornerTable ct;
    const TopologyReport rep = ct.build(m, true, 0);
    Array<float> theta;
    edge_angles(m, ct, theta, 0);
    const AngleSummary a = summarize_angles(m, ct, &theta, 0, 0, 0);
    for (int i = 0; i < 18; ++i) hist[i] += a.histogram[i];
    theta_sum += a.mean * double(a.edges);
    theta_edges += a.edges;
    nlohmann::json attrs = nlohmann::json::array({"POSITION"});
    for (const Channel& ch : slot.mesh.channels) attrs.push_back(ch.name);
    meshes.push_back({{"index", slot.gltf_mesh >= 0 ? slot.gltf_mesh : 0},
                      {"name", slot.name},
                      {"primitives", slot.input_primitives},
                      {"triangles", slot.input_triangles},
                      {"vertices", slot.input_vertices},
                      {"welded_vertices", slot.welded_vertices},
                      {"boundary_edges", rep.boundary_edges},
                      {"non_manifold_edges_cut", rep.non_manifold_edges},
                      {"orientation_conflicts_cut", rep.orientation_conflicts},
                      {"non_manifold_vertices_split", rep.split_vertices},
                      {"dropped_faces", slot.dropped_faces},
                      {"morph_targets", slot.targets},
                      {"attributes", attrs},
                      {"mean_theta", std::round(a.mean * 1000) / 1000},
                      {"max_theta", std::round(a.max * 1000) / 1000}});
    tris += slot.input_triangles;
    verts += slot.input_vertices;
    welded += slot.welded_vertices;
    boundary += rep.boundary_edges;
    cut += rep.non_manifold_edges + rep.orientation_conflicts;
    dropped += slot.dropped_faces;
    prims += slot.input_primitives;
  }
  nlohmann::json histogram = nlohmann::json::array();
  for (int i = 0; i < 18; ++i) histogram.push_back({{"from", i * 10}, {"to", i * 10 + 10}, {"edges", hist[i]}});
  *out = {{"format", format},
          {"bytes", int64_t(size)},
          {"meshes", int64_t(doc.meshes.size())},
          {"primitives", prims},
          {"passthrough_primitives", doc.passthrough_primitives},
          {"triangles", tris},
          {"vertices", verts},
          {"welded_vertices", welded},
          {"boundary_edges", boundary},
          {"cut_edges", cut},
          {"dropped_faces", dropped},
          {"mean_theta", std::round((theta_edges ? theta_sum / double(theta_edges) : 0) * 1000) / 1000},
          {"theta_histogram", histogram},
          {"per_mesh", meshes},
          {"warnings", doc.warnings}};
  return Status::Ok();
}

}  // namespace iteas
