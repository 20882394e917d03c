#include "core/options.h"

#include <algorithm>
#include <cerrno>
#include <cmath>
#include <cstdlib>

namespace iteas {
namespace {

bool parse_double(const std::string& s, double* out) {
  if (s.empty() || s.size() > 64) return false;
  char* end = nullptr;
  errno = 0;
  const double v = std::strtod(s.c_str(), &end);
  if (errno != 0 || end != s.c_str() + s.size() || !std::isfinite(v)) return false;
  *out = v;
  return true;
}

bool parse_int(const std::string& s, int64_t* out) {
  if (s.empty() || s.size() > 20) return false;
  char* end = nullptr;
  errno = 0;
  const long long v = std::strtoll(s.c_str(), &end, 10);
  if (errno != 0 || end != s.c_str() + s.size()) return false;
  *out = v;
  return true;
}

// The value of an adaptive-only option in effect: off in uniform mode, the
// explicit value when given, else the iteas (select=above) default.
double effective(const RefineOptions& o, double value, double iteas_default) {
  if (o.mode == Mode::kUniform) return 0;
  if (value >= 0) return value;
  return o.mode == Mode::kIteas && o.select == Select::kAbove ? iteas_default : 0;
}

}  // namespace

const char* mode_name(Mode m) {
  switch (m) {
    case Mode::kIteas: return "iteas";
    case Mode::kUniform: return "uniform";
    case Mode::kFixed: return "fixed";
  }
  return "iteas";
}

double effective_stall_ratio(const RefineOptions& o) {
  // A stall is a bend that does not fall: meaningless when selecting below T.
  return o.select == Select::kAbove ? effective(o, o.stall_ratio, kStallRatioDefault) : 0;
}
double effective_tolerance(const RefineOptions& o) { return effective(o, o.tolerance, kToleranceDefault); }
double effective_flat_limit(const RefineOptions& o) { return effective(o, o.flat_limit, kFlatLimitDefault); }

bool parse_options(const std::vector<std::pair<std::string, std::string>>& pairs, Options* o,
                   std::string* error, std::string* bad_option) {
  bool levels_set = false, threshold_set = false;
  auto fail = [&](const std::string& name, const std::string& msg) {
    *error = "option '" + name + "': " + msg;
    if (bad_option) *bad_option = name;
    return false;
  };
  for (const auto& [raw, value] : pairs) {
    std::string name = raw;
    std::replace(name.begin(), name.end(), '-', '_');
    int64_t i = 0;
    double d = 0;
    if (name == "mode") {
      if (value == "iteas") o->refine.mode = Mode::kIteas;
      else if (value == "uniform") o->refine.mode = Mode::kUniform;
      else if (value == "fixed") o->refine.mode = Mode::kFixed;
      else return fail(name, "expected iteas, uniform or fixed");
    } else if (name == "levels") {
      if (!parse_int(value, &i) || i < 1 || i > 8) return fail(name, "expected an integer from 1 to 8");
      o->refine.levels = int(i);
      levels_set = true;
    } else if (name == "threshold") {
      ThresholdSpec t;
      if (value == "mean") t.kind = ThresholdSpec::Kind::kMean;
      else if (value == "median") t.kind = ThresholdSpec::Kind::kMedian;
      else if (value.size() >= 2 && value[0] == 'p' && parse_double(value.substr(1), &d) && d >= 0 && d <= 100) {
        t.kind = ThresholdSpec::Kind::kPercentile;
        t.value = d;
      } else if (parse_double(value, &d) && d >= 0 && d <= 180) {
        t.kind = ThresholdSpec::Kind::kDegrees;
        t.value = d;
      } else {
        return fail(name, "expected mean, median, pNN (0-100) or degrees (0-180)");
      }
      o->refine.threshold = t;
      threshold_set = true;
    } else if (name == "threshold_scope") {
      if (value == "input") o->refine.threshold_scope = Scope::kInput;
      else if (value == "level") o->refine.threshold_scope = Scope::kLevel;
      else return fail(name, "expected input or level");
    } else if (name == "select") {
      if (value == "above") o->refine.select = Select::kAbove;
      else if (value == "below") o->refine.select = Select::kBelow;
      else return fail(name, "expected above or below");
    } else if (name == "crease_angle") {
      if (value == "off") o->refine.crease_angle = 0;
      else if (parse_double(value, &d) && d > 0 && d <= 180) o->refine.crease_angle = d;
      else return fail(name, "expected degrees in (0, 180] or off");
    } else if (name == "stall_ratio") {
      if (value == "off") o->refine.stall_ratio = 0;
      else if (parse_double(value, &d) && d > 0 && d <= 1) o->refine.stall_ratio = d;
      else return fail(name, "expected a ratio in (0, 1] or off");
    } else if (name == "tolerance" || name == "flat_limit") {
      double* target = name == "tolerance" ? &o->refine.tolerance : &o->refine.flat_limit;
      if (value == "off") *target = 0;
      else if (parse_double(value, &d) && d > 0 && d <= 1) *target = d;
      else return fail(name, "expected a fraction of the bounding-box diagonal in (0, 1] or off");
    } else if (name == "max_triangles") {
      if (!parse_int(value, &i) || i < 1) return fail(name, "expected a positive integer");
      o->refine.max_triangles = std::min<int64_t>(i, kMaxTriangles);
    } else if (name == "tension") {
      if (!parse_double(value, &d) || d < 0 || d > 1.0 / 16.0) return fail(name, "expected 0 <= w <= 0.0625");
      o->refine.tension = d;
    } else if (name == "threads") {
      if (!parse_int(value, &i) || i < 0 || i > 256) return fail(name, "expected an integer from 0 to 256");
      o->refine.threads = int(i);
    } else if (name == "output") {
      if (value != "glb" && value != "gltf" && value != "drc" && value != "obj" && value != "ply")
        return fail(name, "expected glb, gltf, drc, obj or ply");
      o->out.output = value;
    } else if (name == "compression") {
      if (value == "draco") o->out.draco = true;
      else if (value == "none") o->out.draco = false;
      else return fail(name, "expected draco or none");
    } else if (name == "position_bits" || name == "normal_bits" || name == "texcoord_bits" ||
               name == "color_bits" || name == "generic_bits") {
      if (!parse_int(value, &i) || i < 8 || i > 30) return fail(name, "expected an integer from 8 to 30");
      int* target = name == "position_bits"   ? &o->out.position_bits
                    : name == "normal_bits"   ? &o->out.normal_bits
                    : name == "texcoord_bits" ? &o->out.texcoord_bits
                    : name == "color_bits"    ? &o->out.color_bits
                                              : &o->out.generic_bits;
      *target = int(i);
    } else if (name == "draco_level") {
      if (!parse_int(value, &i) || i < 0 || i > 10) return fail(name, "expected an integer from 0 to 10");
      o->out.draco_level = int(i);
    } else {
      return fail(raw, "unknown option");
    }
  }
  if (!levels_set) o->refine.levels = o->refine.mode == Mode::kIteas ? 6 : 2;
  if (o->refine.mode == Mode::kFixed &&
      (!threshold_set || o->refine.threshold.kind != ThresholdSpec::Kind::kDegrees))
    return fail("threshold", "mode=fixed needs a threshold in degrees");
  return true;
}

}  // namespace iteas
