#pragma once
/// @file trajectory_eval.h
/// Trajectory evaluation (mer_eval, and mer_slam's summary): timestamp association (as evo's
/// `associate`), Umeyama alignment (none / SE(3) / Sim(3)), absolute trajectory error (ATE) and
/// relative pose error (RPE).

#include <cstddef>
#include <cstdint>
#include <optional>
#include <string>
#include <vector>

#include "core/pose.h"
#include "core/status.h"
#include "hal/ground_truth.h"

namespace mer::eval {

/// How the estimate is aligned to the ground truth before errors are computed.
enum class Alignment {
  kNone,  ///< no alignment
  kSe3,   ///< rotation + translation (Umeyama without scale)
  kSim3,  ///< rotation + translation + scale (Umeyama with scale)
  /// rotation only, fitted to the orientations (positions unused): for estimates that know
  /// their orientation and not their position (mer_slam's orientation.txt)
  kRotation,
};

/// Parses "none", "se3", "sim3" or "rotation"; nullopt otherwise.
std::optional<Alignment> parse_alignment(const std::string& s);
/// The name parse_alignment accepts for `a`.
const char* alignment_name(Alignment a);

/// One associated pair: an index into the ground truth and one into the estimate.
struct PosePair {
  std::size_t gt = 0;   ///< index into the ground-truth poses
  std::size_t est = 0;  ///< index into the estimated poses
};

/// Associates two trajectories by timestamp, one to one: among all (estimate, ground
/// truth) pairs with |dt| <= max_dt_ns, pairs are taken greedily by increasing |dt| (ties:
/// earlier estimate, then earlier ground truth), each pose of either trajectory used at most
/// once (the TUM benchmark's associate.py rule; this reproduces the published evo figures,
/// e.g. fr2/desk ORB: 2223 pairs at 0.02 s, where plain per-estimate nearest matching would
/// reuse two ground-truth poses and give 2225). Pairs are sorted by estimate index.
std::vector<PosePair> associate(const hal::Trajectory& gt, const hal::Trajectory& est,
                                std::int64_t max_dt_ns);

/// Index matching for formats without timestamps (KITTI): pair i = (i, i) for
/// i < min(|gt|, |est|).
std::vector<PosePair> associate_by_index(const hal::Trajectory& gt, const hal::Trajectory& est);

/// A similarity transform p' = scale * R * p + t.
struct Sim3 {
  Eigen::Matrix3d R = Eigen::Matrix3d::Identity();  ///< rotation
  Eigen::Vector3d t = Eigen::Vector3d::Zero();      ///< translation
  double scale = 1.0;                               ///< scale (1 unless Sim(3))

  /// Applies the transform to a point.
  Eigen::Vector3d apply(const Eigen::Vector3d& p) const { return scale * (R * p) + t; }
  /// Applies the transform to a camera-to-world pose (rotation R * R_wc, centre apply(t_wc)).
  SE3d apply(const SE3d& T) const;
};

/// The transform that maps `src` positions onto `dst` positions in the least-squares
/// sense (Umeyama 1991, via Eigen::umeyama). Identity for Alignment::kNone or when fewer
/// than 3 points are given.
Sim3 align_positions(const std::vector<Eigen::Vector3d>& src,
                     const std::vector<Eigen::Vector3d>& dst, Alignment alignment);

/// Relative pose error settings. A frame delta, when set, takes precedence over the
/// distance delta.
struct RpeOptions {
  double delta_m = 100.0;                   ///< ground-truth path length per segment, metres
  std::optional<std::size_t> delta_frames;  ///< pairs per segment (instead of distance)
};

/// Summary of one evaluation.
struct EvalResult {
  std::size_t pairs = 0;                  ///< associated pose pairs
  Alignment alignment = Alignment::kSe3;  ///< alignment applied
  double scale = 1.0;                     ///< Sim(3) scale (1 for se3/none)
  double ate_rmse_m = 0.0;                ///< ATE root mean square, metres
  double ate_mean_m = 0.0;                ///< ATE mean, metres
  double ate_median_m = 0.0;              ///< ATE median, metres
  double ate_max_m = 0.0;                 ///< ATE maximum, metres
  std::size_t rpe_segments = 0;           ///< segments the RPE averages over (0: none fit)
  double rpe_trans_pct = 0.0;             ///< mean translational RPE, % of segment length
  double rpe_rot_deg_per_m = 0.0;         ///< mean rotational RPE, degrees per metre of segment
  double are_rmse_deg = 0.0;  ///< absolute rotation error after the alignment, RMS, degrees
  double are_max_deg = 0.0;   ///< and its maximum
};

/// The rotation R that best maps the estimated orientations onto the true ones,
/// R_gt_i ~ R R_est_i (chordal least squares: the SVD projection of sum R_gt_i R_est_i^T onto
/// SO(3)). Identity when `pairs` is empty.
Eigen::Matrix3d align_orientations(const hal::Trajectory& gt, const hal::Trajectory& est,
                                   const std::vector<PosePair>& pairs);

/// Evaluates `est` against `gt` over the associated `pairs` (must not be empty).
///
/// ATE: the estimated positions are aligned to the ground-truth positions (Umeyama), and
/// the translation error |p_gt - S(p_est)| of each pair gives RMSE, mean, median and max.
///
/// RPE (on the aligned estimate, so a Sim(3) scale is applied): over the pair sequence,
/// each segment runs from pair i to pair j, where j = i + delta_frames, or (distance mode)
/// the first pair whose ground-truth path length from i reaches delta_m. For each segment
/// E = (G_i^-1 G_j)^-1 (P_i^-1 P_j); the translational error is |trans(E)| / L and the
/// rotational error angle(E) / L, with L the ground-truth path length of the segment
/// (KITTI devkit style). Both are averaged over the segments, translational reported in %,
/// rotational in deg/m. No segment fits: rpe_segments = 0 and both are 0.
///
/// ARE: the angle of R_gt_i^T (R R_est_i) per pair, R the alignment's rotation, as RMS and
/// max. With Alignment::kRotation, R comes from the orientations (align_orientations), the
/// positions are only rotated (scale 1, no translation), and the ATE and RPE figures compare
/// them as they are (an estimate of orientations alone has no positions to score).
EvalResult evaluate(const hal::Trajectory& gt, const hal::Trajectory& est,
                    const std::vector<PosePair>& pairs, Alignment alignment,
                    const RpeOptions& rpe = {});

/// The result as one JSON object (keys pairs, align, scale, ate_rmse_m, ate_mean_m,
/// ate_median_m, ate_max_m, rpe_trans_pct, rpe_rot_deg_per_m, are_rmse_deg, are_max_deg; the
/// RPE values are null when no segment fits).
std::string to_json(const EvalResult& r);

/// A human-readable multi-line summary.
std::string to_text(const EvalResult& r);

}  // namespace mer::eval
