// Dihedral angles between neighbouring face normals (SPEC §2.1) and the
// statistical threshold derived from them (§2.2). Normals are computed on the
// fly in double precision rather than stored: memory per triangle matters more
// than the few extra cross products.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "core/corner_table.h"
#include "core/mesh.h"

namespace iteas {

// Unit normal of face f in double; returns false for a zero-area face.
bool face_normal(const Mesh& mesh, int32_t f, double n[3]);

// Unit normals of faces[0, n), one array per coordinate: face_normal's bits
// (its operations, vectorised), NaN where it says zero area.
void face_normals(const Mesh& mesh, const int32_t* faces, int64_t n, double* nx, double* ny, double* nz);

// Angle in degrees between the normals of faces f and g; NaN if either has
// zero area.
float normal_angle(const Mesh& mesh, int32_t f, int32_t g);

// theta[c] for every corner whose edge is interior (NaN at boundaries, cuts
// and zero-area faces). Both corners of an edge get the same value.
void edge_angles(const Mesh& mesh, const CornerTable& ct, Array<float>& theta, int threads = 1);

// What edge_angles may take from the level before instead of computing it
// (all per the mesh given, as refine's adaptive levels record them): corner
// k of face f with kept_from[f] >= 0 and neither end touched has the angle
// theta[3 * kept_from[f] + k] had. (Both faces of such an edge are then kept
// unchanged, their normals the same bits, in the same order: a face that
// changed touches all its vertices. So both corners of a carried edge are
// carried, each from its own face, with the angle both had.)
// refine's deviations are carried by the same rule.
struct CarriedAngles {
  const float* theta = nullptr;
  const int32_t* kept_from = nullptr;
  const uint8_t* touched = nullptr;
  // The rule for face f of the current mesh (cv: its corner -> vertex map):
  // its face on the level before, or -1 when it changed; bit k of |carried|
  // tells whether corner k's edge (between the face's other two vertices) is
  // carried. The face's three touched flags are read once.
  int64_t carried_corners(const int32_t* cv, int64_t f, unsigned& carried) const {
    const int64_t from = kept_from[f];
    carried = 0;
    if (from < 0) return -1;
    const unsigned t0 = touched[cv[3 * f]], t1 = touched[cv[3 * f + 1]], t2 = touched[cv[3 * f + 2]];
    carried = unsigned(!(t1 | t2)) | unsigned(!(t2 | t0)) << 1 | unsigned(!(t0 | t1)) << 2;
    return from;
  }
};
void edge_angles(const Mesh& mesh, const CornerTable& ct, Array<float>& theta, int threads,
                 const CarriedAngles& carried);

struct AngleSummary {
  int64_t edges = 0;  // interior edges with a theta
  double mean = 0, max = 0;
  int64_t above = 0;  // edges with theta > the threshold given
  std::vector<int64_t> histogram = std::vector<int64_t>(18, 0);  // 10-degree bins
};

// Summary over each interior edge once. Edges with theta >= |exclude_at_or_above|
// (creases) are left out when it is > 0. |theta| may be null: computed on the fly.
// Deterministic for any thread count (counts, the maximum and an exact sum).
// With |quality| and without |theta| (the angles computed on the fly from
// the faces' normals), it also writes triangle_quality(mesh)'s result, each
// face's points gathered once for both (|quality| untouched with |theta|).
struct QualitySummary;
AngleSummary summarize_angles(const Mesh& mesh, const CornerTable& ct, const Array<float>* theta,
                              double threshold, double exclude_at_or_above = 0, int threads = 1,
                              QualitySummary* quality = nullptr);
// summarize_angles(mesh, ct, &theta, threshold, exclude_at_or_above, threads).above
// alone: the interior edges whose angle is counted and exceeds |threshold|,
// without the rest of the tally (the summary with another threshold has the
// other fields already).
int64_t count_angles_above(const CornerTable& ct, const Array<float>& theta, double threshold,
                           double exclude_at_or_above = 0, int threads = 1);
// The same summary (angles from the faces' normals) of a uniform split's
// children (face f's children are 4f..4f+3, as uniform_level makes them)
// whose own corner table is not made: their opposites come from the
// parent's, |parent_opposites|, a block of faces at a time (split_opposites).
// Equal to summarize_angles on the children's table.
AngleSummary summarize_split_angles(const Mesh& children, const Array<int32_t>& parent_opposites, double threshold,
                                    double exclude_at_or_above = 0, int threads = 1,
                                    QualitySummary* quality = nullptr);

// The threshold statistic: "mean", "median", "pNN" or a number of degrees.
struct ThresholdSpec {
  enum class Kind { kMean, kMedian, kPercentile, kDegrees } kind = Kind::kMean;
  double value = 0;  // percentile (0-100) or degrees
  std::string text() const;
};
double compute_threshold(const ThresholdSpec& spec, const Mesh& mesh, const CornerTable& ct,
                         const Array<float>& theta, double exclude_at_or_above = 0, int threads = 1);

// Smallest interior angle (degrees) per face; the minimum and 1st percentile.
struct QualitySummary {
  double min_angle = 0, p1_angle = 0;
};
QualitySummary triangle_quality(const Mesh& mesh, int threads = 1);

// sin² of the smallest angle of triangle (p, q, r): the smallest angle lies
// opposite the shortest edge and is at most 60°, so it is
// |cross|² e_min / (e0 e1 e2) with squared edge lengths e — no trigonometry,
// and sin² orders angles up to 60°. Negative when two points coincide.
double smallest_angle_sin2(const double* p, const double* q, const double* r);

// smallest_angle_sin2 of triangles i < n whose points p, q, r lie in nine
// arrays (p's x, y, z, then q's, then r's): its operations, vectorised, so
// its values bit for bit.
void smallest_angle_sin2s(const double* const* pqr, int n, double* out);

}  // namespace iteas
