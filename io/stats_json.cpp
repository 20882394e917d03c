#include <algorithm>
#include <cmath>

#include "io/pipeline.h"

namespace iteas {
namespace {

using json = nlohmann::json;

double round3(double x) { return std::isfinite(x) ? std::round(x * 1000.0) / 1000.0 : 0.0; }

// An option that is a positive number or off (0).
json number_or_off(double v) { return v > 0 ? json(v) : json("off"); }

const char* scope_name(Scope s) { return s == Scope::kLevel ? "level" : "input"; }

}  // namespace

json options_json(const Options& o, const std::string& output_format) {
  const RefineOptions& r = o.refine;
  json j = {{"mode", mode_name(r.mode)},
            {"levels", r.levels},
            {"threshold", r.threshold.text()},
            {"threshold_scope", scope_name(r.threshold_scope)},
            {"select", r.select == Select::kAbove ? "above" : "below"},
            {"max_triangles", r.max_triangles},
            {"tension", r.tension},
            {"output", output_format},
            {"compression", o.out.draco ? "draco" : "none"},
            {"position_bits", o.out.position_bits},
            {"normal_bits", o.out.normal_bits},
            {"texcoord_bits", o.out.texcoord_bits},
            {"color_bits", o.out.color_bits},
            {"generic_bits", o.out.generic_bits},
            {"draco_level", o.out.draco_level}};
  j["crease_angle"] = number_or_off(r.crease_angle);
  j["stall_ratio"] = number_or_off(effective_stall_ratio(r));
  // Fractions of the bounding-box diagonal in effect.
  j["tolerance"] = number_or_off(effective_tolerance(r));
  j["flat_limit"] = number_or_off(effective_flat_limit(r));
  return j;
}

json stats_json(const Document& doc, const std::vector<RefineStats>& per_mesh, const Options& options,
                const std::string& output_format, const WriteCounts& out_counts, bool refined) {
  json j;
  j["options"] = options_json(options, output_format);
  int64_t in_prims = 0, in_tris = 0, in_verts = 0, welded = 0, dropped = 0;
  for (const MeshSlot& s : doc.meshes) {
    in_prims += s.input_primitives;
    in_tris += s.input_triangles;
    in_verts += s.input_vertices;
    welded += s.welded_vertices;
    dropped += s.dropped_faces;
  }
  j["input"] = {{"format", doc.format}, {"bytes", doc.input_bytes}, {"meshes", int64_t(doc.meshes.size())},
                {"primitives", in_prims}, {"vertices", in_verts}, {"welded_vertices", welded}, {"triangles", in_tris}};
  j["output"] = {{"format", output_format}, {"meshes", out_counts.meshes}, {"primitives", out_counts.primitives},
                 {"vertices", out_counts.vertices}, {"triangles", out_counts.triangles},
                 {"triangles_collapsed_by_quantization", out_counts.quantization_collapsed}};

  // Aggregate over meshes: counts add up; angle means are weighted by edges.
  size_t main_mesh = 0;
  for (size_t i = 0; i < doc.meshes.size(); ++i)
    if (doc.meshes[i].input_triangles > doc.meshes[main_mesh].input_triangles) main_mesh = i;
  json levels = json::array();
  size_t max_levels = 0;
  for (const RefineStats& r : per_mesh) max_levels = std::max(max_levels, r.levels.size());
  for (size_t l = 0; l < max_levels; ++l) {
    LevelStats sum;
    sum.level = int(l) + 1;
    double theta_weight = 0, theta_sum = 0;
    for (size_t mi = 0; mi < per_mesh.size(); ++mi) {
      const RefineStats& r = per_mesh[mi];
      if (l >= r.levels.size()) {
        sum.triangles_after += r.triangles_out;
        continue;
      }
      const LevelStats& ls = r.levels[l];
      if (mi == main_mesh) sum.threshold = ls.threshold;
      sum.faces_selected += ls.faces_selected;
      sum.faces_stalled += ls.faces_stalled;
      sum.faces_within_tolerance += ls.faces_within_tolerance;
      sum.faces_over_flat_limit += ls.faces_over_flat_limit;
      sum.red_splits += ls.red_splits;
      sum.green_splits += ls.green_splits;
      sum.greens_merged += ls.greens_merged;
      sum.vertices_added += ls.vertices_added;
      sum.vertices_guarded += ls.vertices_guarded;
      sum.triangles_after += ls.triangles_after;
      theta_sum += ls.mean_theta_after * double(ls.triangles_after);
      theta_weight += double(ls.triangles_after);
      sum.max_theta_after = std::max(sum.max_theta_after, ls.max_theta_after);
      sum.ms += ls.ms;
    }
    levels.push_back({{"level", sum.level}, {"threshold", round3(sum.threshold)}, {"faces_selected", sum.faces_selected},
                      {"faces_stalled", sum.faces_stalled}, {"faces_within_tolerance", sum.faces_within_tolerance},
                      {"faces_over_flat_limit", sum.faces_over_flat_limit},
                      {"red_splits", sum.red_splits}, {"green_splits", sum.green_splits},
                      {"greens_merged", sum.greens_merged}, {"vertices_added", sum.vertices_added},
                      {"vertices_guarded", sum.vertices_guarded}, {"triangles_after", sum.triangles_after},
                      {"mean_theta_after", round3(theta_weight > 0 ? theta_sum / theta_weight : 0)},
                      {"max_theta_after", round3(sum.max_theta_after)}, {"ms", round3(sum.ms)}});
  }
  j["levels"] = levels;
  const RefineStats* main = per_mesh.empty() ? nullptr : &per_mesh[main_mesh];
  j["threshold"] = main ? round3(main->threshold) : 0.0;
  j["stopped_by"] = main ? main->stopped_by : (refined ? "converged" : "not_refined");
  if (!refined) j["stopped_by"] = "not_refined";

  auto angle_side = [&](bool after) {
    int64_t edges = 0, above = 0;
    double sum = 0, mx = 0;
    for (const RefineStats& r : per_mesh) {
      const AngleSummary& a = after ? r.after : r.before;
      edges += a.edges;
      above += a.above;
      sum += a.mean * double(a.edges);
      mx = std::max(mx, a.max);
    }
    return json{{"mean_theta", round3(edges ? sum / double(edges) : 0)}, {"max_theta", round3(mx)},
                {"edges", edges}, {"edges_above_threshold", above}};
  };
  j["smoothness"] = {{"before", angle_side(false)}, {"after", angle_side(true)}};
  auto quality_side = [&](bool after) {
    double mn = 180, p1 = 180;
    for (const RefineStats& r : per_mesh) {
      const QualitySummary& q = after ? r.quality_after : r.quality_before;
      mn = std::min(mn, q.min_angle);
      p1 = std::min(p1, q.p1_angle);
    }
    if (per_mesh.empty()) mn = p1 = 0;
    return json{{"min_angle", round3(mn)}, {"p1_angle", round3(p1)}};
  };
  j["quality"] = {{"before", quality_side(false)}, {"after", quality_side(true)}};
  int64_t uniform = 0, out_tris = 0, levels_done = 0;
  for (const RefineStats& r : per_mesh) {
    uniform += r.uniform_triangles;
    out_tris += r.triangles_out;
    levels_done = std::max<int64_t>(levels_done, int64_t(r.levels.size()));
  }
  j["uniform"] = {{"levels", levels_done}, {"triangles", uniform},
                  {"reduction_percent", round3(uniform > 0 ? 100.0 * (1.0 - double(out_tris) / double(uniform)) : 0)}};

  int64_t boundary = 0, nm = 0, orient = 0, split = 0, peak = 0;
  bool clamped = false;
  for (const RefineStats& r : per_mesh) {
    boundary += r.topology.boundary_edges;
    nm += r.topology.non_manifold_edges;
    orient += r.topology.orientation_conflicts;
    split += r.topology.split_vertices;
    peak = std::max(peak, r.peak_bytes);
    clamped = clamped || r.budget_clamped;
  }
  j["topology"] = {{"boundary_edges", boundary}, {"non_manifold_edges_cut", nm}, {"orientation_conflicts_cut", orient},
                   {"non_manifold_vertices_split", split}, {"degenerate_faces_dropped", dropped}};
  json warnings = doc.warnings;
  if (nm) warnings.push_back(std::to_string(nm) + " non-manifold edges cut into boundaries");
  if (orient) warnings.push_back(std::to_string(orient) + " edges with inconsistent orientation cut into boundaries");
  if (split) warnings.push_back(std::to_string(split) + " non-manifold vertices split");
  if (clamped) warnings.push_back("triangle budget (max_triangles) limited the refinement");
  if (doc.passthrough_primitives)
    warnings.push_back(std::to_string(doc.passthrough_primitives) + " non-triangle primitives passed through unchanged");
  for (const MeshSlot& s : doc.meshes)
    if (s.targets > 0 && options.out.draco && (output_format == "glb" || output_format == "gltf")) {
      warnings.push_back("primitives with morph targets are written without Draco compression");
      break;
    }
  if (out_counts.quantization_collapsed > 0)
    warnings.push_back(std::to_string(out_counts.quantization_collapsed) +
                       " triangles collapsed to zero area by Draco position quantization and were dropped"
                       " (raise position_bits to keep them)");
  j["warnings"] = warnings;
  j["memory"] = {{"peak_bytes", peak},
                 {"bytes_per_output_triangle", round3(out_tris > 0 ? double(peak) / double(out_tris) : 0)}};
  json meshes = json::array();
  for (size_t i = 0; i < doc.meshes.size() && i < per_mesh.size(); ++i) {
    const RefineStats& r = per_mesh[i];
    meshes.push_back({{"index", doc.meshes[i].gltf_mesh >= 0 ? doc.meshes[i].gltf_mesh : int(i)},
                      {"name", doc.meshes[i].name},
                      {"triangles_in", r.triangles_in},
                      {"triangles_out", r.triangles_out},
                      {"threshold", round3(r.threshold)},
                      {"levels", int64_t(r.levels.size())},
                      {"stopped_by", r.stopped_by}});
  }
  j["meshes"] = meshes;
  return j;
}

std::string json_text(const nlohmann::json& j, int indent) {
  return j.dump(indent, ' ', false, nlohmann::json::error_handler_t::replace);
}

}  // namespace iteas
