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
  int64_t max_triangles = 5000000;
  double tension = 0;
  int threads = 0;  // 0 = all cores
};

// 2^-1/2: a bend falling at less than half the smooth-surface rate, in octaves
// (the modified Butterfly halves θ per level on a smooth surface).
inline constexpr double kStallRatioDefault = 0.70710678118654752;

// The stall ratio in effect (0 = off).
double effective_stall_ratio(const RefineOptions& o);

struct OutputOptions {
  std::string output;  // glb, gltf, drc, obj, ply; empty = by context
  bool draco = true;
  int position_bits = 14, normal_bits = 10, texcoord_bits = 12, color_bits = 10, generic_bits = 12;
  int draco_level = 7;
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
