#pragma once
/// @file two_view.h
/// Monocular map initialization from two views (after ORB-SLAM, Mur-Artal et al. 2015,
/// sec. IV): a homography H and a fundamental matrix F are fitted by RANSAC in parallel on
/// the same samples (Hartley-normalized 4-point DLT for H, 8-point for F), scored by their
/// truncated symmetric transfer errors (chi2 gates at 95 %), and one is selected with
/// R_H = S_H / (S_H + S_F) (H above homography_ratio). The selected model is decomposed into
/// motion candidates (Faugeras-Lustman SVD method for H: 8 candidates; E = K^T F K: 4
/// candidates); the candidate that triangulates the most inliers in front of both cameras with
/// a small reprojection error and enough parallax wins. The essential model's motion is then
/// refined (Levenberg-Marquardt on the Sampson error, re-gating the inliers).
///
/// Refusals (TwoViewRefusal) instead of a wrong map:
/// - static: median disparity below min_median_disparity_px;
/// - pure rotation: a rotation-only model (fitted to the homography inliers) explains >= 70 %
///   of the best model's inliers, whatever the rotation angle;
/// - low parallax: median parallax of the consistent points below min_parallax_deg;
/// - uncertain motion: median parallax below confident_parallax_deg, unless the model is the
///   essential matrix and its refined translation direction has a 1-sigma uncertainty of at
///   most max_translation_dir_sigma_deg. At low parallax a homography's decomposition and a
///   poorly constrained essential matrix trade a rotation for a sideways translation (forward
///   motion while turning, facing a wall), and the map they build is bent;
/// - ambiguous: a second candidate is consistent with >= ambiguity_ratio of the points the
///   winner is consistent with and is not refuted by the winner's good points (fewer than 5 %
///   of them behind its cameras or off their pixels; points near its epipole, which moved
///   too little once its rotation is taken out, count for neither), e.g. the two-fold
///   homography ambiguity of a plane under forward motion.
///
/// An ambiguous (or under-triangulated) homography falls back to the essential model. When
/// the plane holds more than 85 % of the points, the 8-point F is ill-conditioned and the
/// fallback uses F = [e1]x H instead (plane and parallax, the idea behind DEGENSAC): the
/// epipole comes from the parallax lines of the points well off the plane (H transfer error
/// above 6 sigma; at least 40 of them must agree), and the motion must then have a sharp
/// translation direction (max_translation_dir_sigma_deg) whatever the parallax. This is what
/// initializes a car driving towards a far facade, whose plane's two decompositions nearly
/// agree, from the road's parallax.
///
/// Scoring note: ORB-SLAM offsets both scores by the 2-dof chi2 threshold, which makes a
/// correct F out-score a correct H even on a plane (a point-to-line residual is smaller than
/// a point-to-point one). Here F's offset is one less (the difference of the expected chi2),
/// so R_H ~ 0.5 on planes and ~0.1-0.3 on general scenes, and residuals are normalized by the
/// variance of a two-image residual (2 sigma^2).
///
/// Only used during initialization; ~6 ms CPU for 1000 matches (x86, Release). With a reserved
/// TwoViewWorkspace it does not allocate.

#include <cstddef>
#include <cstdint>
#include <limits>
#include <memory>
#include <span>
#include <vector>

#include <Eigen/Core>

#include "core/options.h"
#include "core/pose.h"
#include "geometry/camera_model.h"

namespace mer::geometry {

/// Options of the two-view initializer (config section `tracking.init`).
struct TwoViewOptions {
  int ransac_iterations = 200;
  double sigma_px = 1.0;
  double min_parallax_deg = 1.0;
  int min_matches = 100;
  int min_triangulated = 50;
  double min_median_disparity_px = 8.0;
  double homography_ratio = 0.45;
  double min_point_parallax_deg = 0.5;
  double confident_parallax_deg = 3.0;
  double max_translation_dir_sigma_deg = 0.25;
  double ambiguity_ratio = 0.7;
  double plane_hint_min_parallax_deg = 2.0;
  double plane_hint_agree_deg = 5.0;
  double plane_hint_refute_deg = 12.0;
  std::uint64_t seed = 1;

  template <class V>
  void visit(V& v) {
    v.field("ransac_iterations", ransac_iterations,
            "RANSAC iterations, each testing one homography and one fundamental hypothesis",
            options::Range<int>{1, 100000});
    v.field("sigma_px", sigma_px, "keypoint position noise (1 sigma) for chi2 thresholds, px",
            options::Range<double>{0.01, 100.0});
    v.field("min_parallax_deg", min_parallax_deg,
            "median parallax of the triangulated points needed to initialize, deg",
            options::Range<double>{0.0, 90.0});
    v.field("min_matches", min_matches, "fewer correspondences: refuse to initialize",
            options::Range<int>{8, 1000000});
    v.field("min_triangulated", min_triangulated,
            "fewer well-triangulated points: refuse to initialize",
            options::Range<int>{1, 1000000});
    v.field("min_median_disparity_px", min_median_disparity_px,
            "median image motion below this: static scene, refuse, px",
            options::Range<double>{0.0, 10000.0});
    v.field("homography_ratio", homography_ratio,
            "R_H = S_H / (S_H + S_F) above this selects the homography model",
            options::Range<double>{0.0, 1.0});
    v.field("min_point_parallax_deg", min_point_parallax_deg,
            "points triangulated under less parallax are not kept in the map, deg",
            options::Range<double>{0.0, 90.0});
    v.field("confident_parallax_deg", confident_parallax_deg,
            "median parallax at which either model initializes; below it (and above "
            "min_parallax_deg) only an essential model with a well-determined translation "
            "direction does, deg",
            options::Range<double>{0.0, 90.0});
    v.field("max_translation_dir_sigma_deg", max_translation_dir_sigma_deg,
            "below confident_parallax_deg: the largest 1-sigma uncertainty of the essential "
            "model's refined translation direction that initializes, deg",
            options::Range<double>{0.0, 180.0});
    v.field("ambiguity_ratio", ambiguity_ratio,
            "refuse when another motion candidate is consistent with this fraction of the "
            "points the winner is consistent with (unless the winner's good points refute it)",
            options::Range<double>{0.0, 1.0});
    v.field("plane_hint_min_parallax_deg", plane_hint_min_parallax_deg,
            "an ambiguous homography reports the plane normals of its tied candidates "
            "(TwoViewResult::plane_normals_c0) once the winner's median parallax reaches this, "
            "deg",
            options::Range<double>{0.0, 90.0});
    v.field("plane_hint_agree_deg", plane_hint_agree_deg,
            "with plane hints from an earlier pair of the same reference: a tied candidate "
            "whose plane normal is within this angle of a hint agrees with it, deg",
            options::Range<double>{0.0, 90.0});
    v.field("plane_hint_refute_deg", plane_hint_refute_deg,
            "the agreeing candidate wins the tie only if every other tied candidate's normal is "
            "at least this far from all hints (the twin's normal moves with the translation), "
            "deg",
            options::Range<double>{0.0, 90.0});
    // The YAML layer reads signed 64-bit integers: go through one (seeds are small).
    std::int64_t seed_value = static_cast<std::int64_t>(seed);
    v.field("seed", seed_value, "RANSAC random seed",
            options::Range<std::int64_t>{0, std::numeric_limits<std::int64_t>::max()});
    seed = static_cast<std::uint64_t>(seed_value);
  }
};

/// Model used for the reconstruction.
enum class TwoViewModel : std::uint8_t { kNone, kHomography, kEssential };

/// Why the initializer refused the pair.
enum class TwoViewRefusal : std::uint8_t {
  kNone,                ///< accepted
  kTooFewMatches,       ///< fewer than min_matches correspondences (or mismatched inputs)
  kStatic,              ///< median disparity below min_median_disparity_px
  kPureRotation,        ///< a rotation alone explains the motion: no baseline
  kLowParallax,         ///< median parallax below min_parallax_deg
  kTooFewTriangulated,  ///< fewer than min_triangulated good points (or model inliers)
  kAmbiguous,           ///< two motion candidates explain the data about equally well
  kUncertainMotion,     ///< below confident_parallax_deg without a well-determined direction
};
/// Number of TwoViewRefusal values (counters indexed by it).
inline constexpr std::size_t kTwoViewRefusalCount =
    static_cast<std::size_t>(TwoViewRefusal::kUncertainMotion) + 1;

/// Short name of a refusal reason ("pure_rotation", ...).
const char* to_string(TwoViewRefusal r);
/// Short name of a model ("homography", ...).
const char* to_string(TwoViewModel m);

/// Most motion candidates of one model (a homography's eight decompositions): the most
/// plane normals a result lists.
inline constexpr std::size_t kMaxPlaneNormals = 8;

/// Result of reconstruct_two_view. On refusal (ok == false) there is no map: T_c1_c0 is the
/// identity, points_c0 / triangulated are empty; the diagnostics computed before the refusal
/// (disparity, scores, parallax, model) are kept.
struct TwoViewResult {
  bool ok = false;
  TwoViewModel model = TwoViewModel::kNone;
  TwoViewRefusal refusal = TwoViewRefusal::kNone;
  /// Second camera from first; scaled so that the median depth of the triangulated points
  /// in camera 0 is 1.
  SE3d T_c1_c0 = SE3d::Identity();
  std::vector<Eigen::Vector3d> points_c0;  ///< per correspondence, camera-0 frame (valid where
                                           ///< triangulated[i]; zero elsewhere)
  std::vector<std::uint8_t> triangulated;  ///< per correspondence: 1 = good 3D point
  int num_inliers = 0;                     ///< inliers of the selected model
  int num_triangulated = 0;                ///< good 3D points
  double median_parallax_deg = 0;          ///< over points in front with small reprojection error
  double median_disparity_px = 0;          ///< median |uv1 - uv0| over all correspondences
  double score_h = 0;                      ///< RANSAC score of the homography
  double score_f = 0;                      ///< RANSAC score of the fundamental matrix
  double rotation_sigma_deg = 0;           ///< 1-sigma rotation uncertainty (essential model)
  double translation_dir_sigma_deg = 0;    ///< 1-sigma translation direction uncertainty (ditto)
  /// Refused as ambiguous with the homography model at a median parallax of at least
  /// plane_hint_min_parallax_deg: the unit plane normals (camera 0, z > 0) of the tied
  /// candidates, winner first. Passed back as plane hints with a later frame of the same
  /// reference, they break the tie: the true plane keeps its normal, the twin's normal turns
  /// with the direction of translation.
  std::vector<Eigen::Vector3d> plane_normals_c0;
  /// Refused as ambiguous (the tied candidates, winner first) or as uncertain motion (the
  /// winner): the motions T_c1_c0 with a unit translation, for a check on more views (the
  /// initializer's window). An ambiguous homography that fell back to the essential model
  /// lists the essential model's candidates after its own.
  std::vector<SE3d> candidate_motions;
  /// Refused as pure rotation: the rotation (camera 1 from camera 0, fitted to the
  /// homography's inliers on their bearings) that explains the image motion, and how many
  /// correspondences it explains.
  Eigen::Matrix3d rotation_c1_c0 = Eigen::Matrix3d::Identity();
  int rotation_inliers = 0;
};

/// Monocular initialization from pixel correspondences uv0[i] <-> uv1[i] (undistorted
/// images of one pinhole camera K). Deterministic for a given seed.
///
/// A planar scene seen from two views has two valid decompositions of its homography (Faugeras
/// & Lustman): the true plane and motion, and a twin whose plane normal follows the
/// translation. `plane_hints` (the plane_normals_c0 an earlier, ambiguous pair with the same
/// first image reported) resolve the tie when exactly one tied candidate's normal agrees with
/// a hint (plane_hint_agree_deg) and all the others are far from every hint
/// (plane_hint_refute_deg): a third view, as a camera that keeps turning gives.
TwoViewResult reconstruct_two_view(std::span<const Eigen::Vector2d> uv0,
                                   std::span<const Eigen::Vector2d> uv1, const Pinhole& K,
                                   const TwoViewOptions& o,
                                   std::span<const Eigen::Vector3d> plane_hints = {});

/// Scratch buffers of reconstruct_two_view. Reserved once for at most `max_correspondences`
/// correspondences, a call with no more than that many does not allocate, nor does it grow
/// an `out` result that went through such a call before (the tracking thread initializes with
/// one workspace and one result). Move-only; not shared between threads.
class TwoViewWorkspace {
 public:
  TwoViewWorkspace();
  ~TwoViewWorkspace();
  TwoViewWorkspace(TwoViewWorkspace&&) noexcept;
  TwoViewWorkspace& operator=(TwoViewWorkspace&&) noexcept;
  TwoViewWorkspace(const TwoViewWorkspace&) = delete;
  TwoViewWorkspace& operator=(const TwoViewWorkspace&) = delete;
  /// Reserves every buffer, and those of `out`, for `max_correspondences`.
  void reserve(std::size_t max_correspondences, TwoViewResult& out);
  struct Buffers;  ///< two_view.cpp

 private:
  friend void reconstruct_two_view(std::span<const Eigen::Vector2d>,
                                   std::span<const Eigen::Vector2d>, const Pinhole&,
                                   const TwoViewOptions&, std::span<const Eigen::Vector3d>,
                                   TwoViewWorkspace&, TwoViewResult&);
  std::unique_ptr<Buffers> b_;
};

/// reconstruct_two_view into `out` (every field overwritten) with the buffers of `ws`:
/// the same result, without allocating once `ws` is reserved (TwoViewWorkspace).
void reconstruct_two_view(std::span<const Eigen::Vector2d> uv0,
                          std::span<const Eigen::Vector2d> uv1, const Pinhole& K,
                          const TwoViewOptions& o, std::span<const Eigen::Vector3d> plane_hints,
                          TwoViewWorkspace& ws, TwoViewResult& out);

// ---- Building blocks (also used by self_calibration) --------------------------------------

/// Homography and fundamental matrix fitted by RANSAC on the same samples, each then refitted
/// on its inliers. Pixel coordinates: x1 ~ H x0 and x1^T F x0 = 0 with x = (u, v, 1).
struct TwoViewModelFit {
  Eigen::Matrix3d H = Eigen::Matrix3d::Identity();
  Eigen::Matrix3d F = Eigen::Matrix3d::Zero();  ///< rank 2
  std::vector<std::uint8_t> inliers_h;          ///< per correspondence
  std::vector<std::uint8_t> inliers_f;          ///< per correspondence
  int num_inliers_h = 0;
  int num_inliers_f = 0;
  double score_h = 0;  ///< sum over inliers of (chi2 threshold - chi2), both directions
  double score_f = 0;  ///< same for F, with the H threshold as offset (comparable with score_h)
};

/// Fits both models (needs >= 8 correspondences, else returns zero inliers). `sigma_px` sets
/// the chi2 thresholds (95 %: 5.99 sigma^2 per image for H, 3.84 sigma^2 for F).
TwoViewModelFit fit_two_view_models(std::span<const Eigen::Vector2d> uv0,
                                    std::span<const Eigen::Vector2d> uv1, int iterations,
                                    double sigma_px, std::uint64_t seed);

/// Least-squares 8-point fundamental matrix on pixel coordinates (Hartley normalization, rank
/// 2 enforced), each correspondence weighted by weights[i] (0: unused; e.g. an inlier mask or
/// bootstrap counts). False when fewer than 8 correspondences have weight > 0 or the sizes
/// differ.
bool fit_fundamental_8point(std::span<const Eigen::Vector2d> uv0,
                            std::span<const Eigen::Vector2d> uv1, std::span<const double> weights,
                            Eigen::Matrix3d& F);

}  // namespace mer::geometry
