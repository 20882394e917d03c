// Refinement and output options (SPEC §3), parsed from name/value pairs so the
// CLI (--kebab-case) and HTTP (query parameters) share one parser.
#pragma once

#include <cstdint>
#include <string>
#include <utility>
#include <vector>

#include "core/angles.h"

namespace iteas {

enum class Mode { kIteas, kUniform, kFixed };
enum class Scope { kInput, kLevel };
enum class Select { kAbove, kBelow };

struct RefineOptions {
  Mode mode = Mode::kIteas;
  int levels = 6;  // resolved default: 6 for iteas, 2 for uniform/fixed
  ThresholdSpec threshold;
  Scope threshold_scope = Scope::kInput;
  Select select = Select::kAbove;
  double crease_angle = 0;  // 0 = off
  // A face is not selected again while its bend falls slower than this ratio
  // per level (its largest θ is at least stall_ratio × its parent's when that
  // was split). -1 = the mode's default (kStallRatioDefault for iteas, off for
  // fixed); 0 = off.
  double stall_ratio = -1;
  // Geometric tolerances (beyond the thesis), as fractions of the input's
  // bounding-box diagonal; -1 = the mode's default, 0 = off. A face's
  // deviation is how far splitting it would move the surface: the largest
  // distance between the Butterfly vertex of one of its edges and that
  // edge's midpoint. A face whose deviation is at most `tolerance` is not
  // selected (the split would not show); a face that bends no more than T is
  // selected when its deviation exceeds `flat_limit` (it is visibly faceted).
  double tolerance = -1;
  double flat_limit = -1;
  int64_t max_triangles = 5000000;
  double tension = 0;
  int threads = 0;  // 0 = all cores
};

// The most triangles a mesh may have: its corners are indexed by 32-bit
// signed integers, three a triangle. A larger max_triangles is capped to it
// (as the server caps it to its own limit), and refine_mesh caps it too.
inline constexpr int64_t kMaxTriangles = 715827882;  // (2^31 - 1) / 3
static_assert(3 * kMaxTriangles <= INT32_MAX && 3 * (kMaxTriangles + 1) > INT32_MAX, "the most a corner index numbers");

// 2^-1/2: a bend falling at less than half the smooth-surface rate, in octaves
// (the modified Butterfly halves θ per level on a smooth surface).
inline constexpr double kStallRatioDefault = 0.70710678118654752;

// 1/4096 of the diagonal: less than a pixel with the whole model on a
// 4096-pixel-wide screen.
inline constexpr double kToleranceDefault = 1.0 / 4096.0;
// 1/512 of the diagonal: a pixel or more even on a 512-pixel thumbnail.
inline constexpr double kFlatLimitDefault = 1.0 / 512.0;

// The values in effect (0 = off). The defaults apply to iteas with
// select=above; fixed mode (the thesis's baseline) has them off unless asked,
// uniform mode never.
double effective_stall_ratio(const RefineOptions& o);
double effective_tolerance(const RefineOptions& o);
double effective_flat_limit(const RefineOptions& o);

struct OutputOptions {
  std::string output;  // glb, gltf, drc, obj, ply; empty = by context
  bool draco = true;
  int position_bits = 14, normal_bits = 10, texcoord_bits = 12, color_bits = 10, generic_bits = 12;
  int draco_level = 7;
  // Not an option of its own: the job's thread count (the refinement's),
  // on which Draco payloads of several primitives are encoded at once.
  int threads = 1;
};

struct Options {
  RefineOptions refine;
  OutputOptions out;
};

// Parses |pairs| (names in snake_case or kebab-case). On error returns false
// and sets |error| to a message that names the option.
bool parse_options(const std::vector<std::pair<std::string, std::string>>& pairs, Options* options,
                   std::string* error, std::string* bad_option = nullptr);

const char* mode_name(Mode m);

}  // namespace iteas
