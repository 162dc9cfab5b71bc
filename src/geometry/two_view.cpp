#include "geometry/two_view.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <numbers>
#include <optional>

#include <Eigen/Eigenvalues>
#include <Eigen/LU>
#include <Eigen/SVD>

#include "core/median.h"
#include "geometry/lie.h"
#include "geometry/triangulation.h"
#include "geometry/two_view_models.h"
#include "geometry/two_view_motion.h"

namespace mer::geometry {
namespace {

using two_view_detail::CandidateCheck;
using two_view_detail::check_candidate;
using two_view_detail::decompose_essential;
using two_view_detail::decompose_homography;
using two_view_detail::fit_models;
using two_view_detail::FitScratch;
using two_view_detail::fundamental_from_motion;
using two_view_detail::k_matrix;
using two_view_detail::kConsistent;
using two_view_detail::kGood;
using two_view_detail::kHomographySampleSize;
using two_view_detail::kResidualVarianceFactor;
using two_view_detail::kSampleSize;
using two_view_detail::kUndecided;
using two_view_detail::MotionList;
using two_view_detail::MotionSigma;
using two_view_detail::ParallaxScratch;
using two_view_detail::plane_and_parallax_fundamental;
using two_view_detail::PlaneParallaxFit;
using two_view_detail::refine_motion;
using two_view_detail::RefineScratch;
using two_view_detail::score_fundamental;
using two_view_detail::tie_broken_by_plane_hints;
using two_view_detail::unit_motion;

/// A rotation alone explaining this fraction of the best model's inliers means there is no
/// usable baseline (a translation large enough to initialize moves most points off the
/// rotation-only prediction by more than the 2-dof chi2 gate).
constexpr double kPureRotationInlierFraction = 0.7;
// Refits of a pure rotation on the correspondences it explains.
constexpr int kRotationRefineRounds = 3;
/// A motion candidate that is not consistent with at least this fraction of the winner's good
/// points is refuted by them and does not make the choice ambiguous.
constexpr double kMinRefutedFraction = 0.05;
/// Refine / re-gate rounds of the essential model's local optimization.
constexpr int kLocalOptimizationRounds = 4;

/// Upper median of v (0 when empty), reordering a copy in `scratch`.
double median_of(std::span<const double> v, std::vector<double>& scratch) {
  scratch.assign(v.begin(), v.end());
  return upper_median(scratch);
}

/// Whether the rotation-only model x1 ~ K R K^-1 x0 maps uv0 onto uv1 within the chi2 gate
/// (`inv_var`: 1 / the variance of a two-image residual).
bool explained_by_rotation(const Eigen::Matrix3d& R, const Pinhole& K, const Eigen::Vector2d& uv0,
                           const Eigen::Vector2d& uv1, double inv_var) {
  const Eigen::Vector3d p = R * K.unproject(uv0);
  return p.z() > 0.0 && (K.project(p) - uv1).squaredNorm() * inv_var <= kChi2TwoDof95;
}

/// Inliers of the best rotation-only model x1 ~ K R K^-1 x0, fitted (orthogonal Procrustes
/// on bearing vectors) to the homography inliers; the rotation goes to `R_out`.
int rotation_only_inliers(std::span<const Eigen::Vector2d> uv0,
                          std::span<const Eigen::Vector2d> uv1,
                          std::span<const std::uint8_t> inliers_h, const Pinhole& K,
                          double sigma_px, Eigen::Matrix3d& R_out) {
  Eigen::Matrix3d M = Eigen::Matrix3d::Zero();
  for (std::size_t i = 0; i < uv0.size(); ++i) {
    if (inliers_h[i]) M += K.bearing(uv1[i]) * K.bearing(uv0[i]).transpose();
  }
  R_out = nearest_rotation(M);
  const double inv_var = 1.0 / (kResidualVarianceFactor * sigma_px * sigma_px);
  int count = 0;
  for (std::size_t i = 0; i < uv0.size(); ++i) {
    if (explained_by_rotation(R_out, K, uv0[i], uv1[i], inv_var)) ++count;
  }
  return count;
}

/// Refits a rotation-only model to every correspondence it explains (chi2 gate on the pixel
/// error), from `R`, `rounds` times (as LO-RANSAC's local optimization): the homography's
/// inliers it started from can hold a few wrong matches of a repeated texture.
void refine_rotation(std::span<const Eigen::Vector2d> uv0, std::span<const Eigen::Vector2d> uv1,
                     const Pinhole& K, double sigma_px, int rounds, Eigen::Matrix3d& R) {
  const double inv_var = 1.0 / (kResidualVarianceFactor * sigma_px * sigma_px);
  for (int round = 0; round < rounds; ++round) {
    Eigen::Matrix3d M = Eigen::Matrix3d::Zero();
    int count = 0;
    for (std::size_t i = 0; i < uv0.size(); ++i) {
      if (!explained_by_rotation(R, K, uv0[i], uv1[i], inv_var)) continue;
      M += K.bearing(uv1[i]) * K.bearing(uv0[i]).transpose();
      ++count;
    }
    if (count < kHomographySampleSize) return;
    R = nearest_rotation(M);
  }
}

/// A refused result: no map (the diagnostics filled so far are kept).
void refuse(TwoViewResult& r, TwoViewRefusal why) {
  r.ok = false;
  r.refusal = why;
  r.T_c1_c0 = SE3d::Identity();
  r.points_c0.clear();
  r.triangulated.clear();
  r.num_triangulated = 0;
}

/// r as default-constructed, its vectors emptied but keeping their capacity.
void reset_keeping_capacity(TwoViewResult& r) {
  std::vector<Eigen::Vector3d> points = std::move(r.points_c0);
  std::vector<std::uint8_t> triangulated = std::move(r.triangulated);
  std::vector<Eigen::Vector3d> normals = std::move(r.plane_normals_c0);
  std::vector<SE3d> motions = std::move(r.candidate_motions);
  r = TwoViewResult{};
  points.clear();
  triangulated.clear();
  normals.clear();
  motions.clear();
  r.points_c0 = std::move(points);
  r.triangulated = std::move(triangulated);
  r.plane_normals_c0 = std::move(normals);
  r.candidate_motions = std::move(motions);
}

}  // namespace

const char* to_string(TwoViewRefusal r) {
  switch (r) {
    case TwoViewRefusal::kNone:
      return "none";
    case TwoViewRefusal::kTooFewMatches:
      return "too_few_matches";
    case TwoViewRefusal::kStatic:
      return "static";
    case TwoViewRefusal::kPureRotation:
      return "pure_rotation";
    case TwoViewRefusal::kLowParallax:
      return "low_parallax";
    case TwoViewRefusal::kTooFewTriangulated:
      return "too_few_triangulated";
    case TwoViewRefusal::kAmbiguous:
      return "ambiguous";
    case TwoViewRefusal::kUncertainMotion:
      return "uncertain_motion";
  }
  return "unknown";
}

const char* to_string(TwoViewModel m) {
  switch (m) {
    case TwoViewModel::kNone:
      return "none";
    case TwoViewModel::kHomography:
      return "homography";
    case TwoViewModel::kEssential:
      return "essential";
  }
  return "unknown";
}

namespace {

/// Essential fallback for an ambiguous homography: at most this fraction of the F inliers
/// may lie on the homography's plane.
constexpr double kEssentialFallbackMaxPlanarFraction = 0.85;

}  // namespace

/// Every buffer of a reconstruction (TwoViewWorkspace).
struct TwoViewWorkspace::Buffers {
  FitScratch fit_scratch;
  TwoViewModelFit fit;
  ParallaxScratch parallax_scratch;
  PlaneParallaxFit pp;
  RefineScratch refine;
  MotionList candidates;
  std::array<CandidateCheck, MotionList::kCapacity> checks;
  CandidateCheck final_check;
  std::vector<double> values;  // disparities, depths
  std::vector<double> median;  // median_of's copy
  std::vector<std::uint8_t> refined_inliers;
  std::vector<std::uint8_t> mask;
  TwoViewResult retry;  // the essential model's try after an ambiguous homography

  void reserve(std::size_t n) {
    fit_scratch.reserve(n, fit);
    parallax_scratch.reserve(n, pp);
    refine.reserve(n);
    for (CandidateCheck& c : checks) reserve_check(c, n);
    reserve_check(final_check, n);
    values.reserve(n);
    median.reserve(n);
    refined_inliers.reserve(n);
    mask.reserve(n);
    reserve_result(retry, n);
  }
  static void reserve_check(CandidateCheck& c, std::size_t n) {
    c.parallax_deg.reserve(n);
    c.status.reserve(n);
  }
  static void reserve_result(TwoViewResult& r, std::size_t n) {
    r.points_c0.reserve(n);
    r.triangulated.reserve(n);
    r.plane_normals_c0.reserve(MotionList::kCapacity);
    // Both models' candidates (an ambiguous homography, then the essential model's).
    r.candidate_motions.reserve(2 * MotionList::kCapacity);
  }
};

TwoViewWorkspace::TwoViewWorkspace() : b_(std::make_unique<Buffers>()) {}
TwoViewWorkspace::~TwoViewWorkspace() = default;
TwoViewWorkspace::TwoViewWorkspace(TwoViewWorkspace&&) noexcept = default;
TwoViewWorkspace& TwoViewWorkspace::operator=(TwoViewWorkspace&&) noexcept = default;

void TwoViewWorkspace::reserve(std::size_t max_correspondences, TwoViewResult& out) {
  b_->reserve(max_correspondences);
  Buffers::reserve_result(out, max_correspondences);
}

namespace {

/// One reconstruct_impl call: its inputs, buffers and result, and what its steps pass on.
struct Reconstruction {
  std::span<const Eigen::Vector2d> uv0;
  std::span<const Eigen::Vector2d> uv1;
  const Pinhole& K;
  const TwoViewOptions& o;
  TwoViewWorkspace::Buffers& ws;
  TwoViewResult& r;
  std::span<const std::uint8_t> inliers;  ///< of the chosen model (in ws)
  std::size_t best = 0;                   ///< the winning candidate (ws.candidates)
};

/// Steps 1-4: the static-scene and pure-rotation refusals, both models' fit, the model choice
/// and its motion candidates (ws.candidates, the model's inliers). False: refused.
bool choose_model(Reconstruction& x, bool force_essential) {
  const TwoViewOptions& o = x.o;
  TwoViewWorkspace::Buffers& ws = x.ws;
  TwoViewResult& r = x.r;
  const std::size_t n = x.uv0.size();
  if (x.uv1.size() != n || n < static_cast<std::size_t>(std::max(o.min_matches, kSampleSize))) {
    refuse(r, TwoViewRefusal::kTooFewMatches);
    return false;
  }

  // 1. Static scene: the camera did not move (or barely).
  ws.values.resize(n);
  for (std::size_t i = 0; i < n; ++i) ws.values[i] = (x.uv1[i] - x.uv0[i]).norm();
  r.median_disparity_px = median_of(ws.values, ws.median);
  if (r.median_disparity_px < o.min_median_disparity_px) {
    refuse(r, TwoViewRefusal::kStatic);
    return false;
  }

  // 2. Both models, same samples.
  TwoViewModelFit& fit = ws.fit;
  fit_models(x.uv0, x.uv1, o.ransac_iterations, o.sigma_px, o.seed, ws.fit_scratch, fit);
  r.score_h = fit.score_h;
  r.score_f = fit.score_f;
  const int best_inliers = std::max(fit.num_inliers_h, fit.num_inliers_f);
  if (best_inliers < o.min_triangulated) {
    refuse(r, TwoViewRefusal::kTooFewTriangulated);
    return false;
  }

  // 3. Pure rotation: the image moved, but a rotation alone explains it. Then F is not
  //    unique (any F = [e]x H fits) and any "translation" is noise.
  if (fit.num_inliers_h >= kHomographySampleSize) {
    Eigen::Matrix3d R = Eigen::Matrix3d::Identity();
    const int n_rot = rotation_only_inliers(x.uv0, x.uv1, fit.inliers_h, x.K, o.sigma_px, R);
    if (n_rot >= kPureRotationInlierFraction * best_inliers) {
      refine_rotation(x.uv0, x.uv1, x.K, o.sigma_px, kRotationRefineRounds, R);
      r.rotation_c1_c0 = R;
      r.rotation_inliers = n_rot;
      refuse(r, TwoViewRefusal::kPureRotation);
      return false;
    }
  }

  // 4. Model selection and motion candidates.
  const double r_h =
      fit.score_h / std::max(fit.score_h + fit.score_f, std::numeric_limits<double>::min());
  const Eigen::Matrix3d Km = k_matrix(x.K);
  MotionList& candidates = ws.candidates;
  candidates.size = 0;
  // The essential fallback needs points off the plane: when the homography explains nearly
  // all of F's inliers, E is as undetermined as the plane's twin solution.
  // Then F = [e1]x H from the points off the plane (plane and parallax) replaces the 8-point
  // F; without enough of them agreeing on the epipole the pair stays ambiguous.
  Eigen::Matrix3d F = fit.F;
  std::span<const std::uint8_t> inliers_f = fit.inliers_f;
  int num_inliers_f = fit.num_inliers_f;
  PlaneParallaxFit& pp = ws.pp;
  pp.F = Eigen::Matrix3d::Zero();
  pp.inliers.clear();
  pp.num_inliers = 0;
  pp.num_off_plane_inliers = 0;
  if (force_essential &&
      fit.num_inliers_h > kEssentialFallbackMaxPlanarFraction * fit.num_inliers_f) {
    if (!plane_and_parallax_fundamental(fit.H, x.uv0, x.uv1, o.sigma_px, o.ransac_iterations,
                                        o.seed, ws.parallax_scratch, pp)) {
      refuse(r, TwoViewRefusal::kAmbiguous);
      return false;
    }
    F = pp.F;
    inliers_f = pp.inliers;
    num_inliers_f = pp.num_inliers;
  }
  if (!force_essential && r_h > o.homography_ratio) {
    r.model = TwoViewModel::kHomography;
    r.num_inliers = fit.num_inliers_h;
    x.inliers = fit.inliers_h;
    decompose_homography(Km.inverse() * fit.H * Km, candidates);
    if (candidates.size == 0) {
      refuse(r, TwoViewRefusal::kPureRotation);
      return false;
    }
  } else {
    r.model = TwoViewModel::kEssential;
    r.num_inliers = num_inliers_f;
    x.inliers = inliers_f;
    decompose_essential(Km.transpose() * F * Km, candidates);
  }
  return true;
}

/// Refuses for too little parallax or too few triangulated points of candidate x.best
/// (medians its check's parallax into r). False: refused.
bool winner_has_parallax(Reconstruction& x) {
  const CandidateCheck& c = x.ws.checks[x.best];
  x.r.median_parallax_deg = median_of(c.parallax_deg, x.ws.median);
  if (x.r.median_parallax_deg < x.o.min_parallax_deg) {
    refuse(x.r, TwoViewRefusal::kLowParallax);
    return false;
  }
  if (c.good < x.o.min_triangulated) {
    refuse(x.r, TwoViewRefusal::kTooFewTriangulated);
    return false;
  }
  return true;
}

/// Step 5: the cheirality / reprojection / parallax vote among the candidates, and the
/// ambiguity test (the plane hints may break a homography's tie). Sets x.best. False: refused.
bool vote(Reconstruction& x, std::span<const Eigen::Vector3d> plane_hints) {
  const TwoViewOptions& o = x.o;
  TwoViewResult& r = x.r;
  const MotionList& candidates = x.ws.candidates;
  std::array<CandidateCheck, MotionList::kCapacity>& checks = x.ws.checks;
  std::size_t& best = x.best;
  best = 0;
  for (std::size_t k = 0; k < candidates.size; ++k) {
    check_candidate(candidates[k], x.uv0, x.uv1, x.inliers, x.K, o, nullptr, nullptr, checks[k]);
    const auto key = [](const CandidateCheck& c) { return std::pair(c.good, c.consistent); };
    if (key(checks[k]) > key(checks[best])) best = k;
  }
  if (!winner_has_parallax(x)) return false;
  // Ambiguity: another candidate consistent with nearly as many points that also agrees with
  // (almost) all of the winner's good points. A candidate that puts a fraction of the
  // winner's well-triangulated points behind a camera or off their pixels is refuted by them
  // (they are model inliers; chance outliers among them are rare), e.g. the twin solution of
  // a homography whose virtual plane crosses the field of view. The pre-filter counts
  // consistent points, not good ones: under forward motion the true decomposition sees less
  // parallax than its twin (which moves sideways), so fewer of its points pass the parallax
  // bar, though it explains them all.
  std::array<std::size_t, MotionList::kCapacity> tied_buf{best};
  std::size_t num_tied = 1;
  for (std::size_t k = 0; k < candidates.size; ++k) {
    if (k == best || checks[k].consistent <= o.ambiguity_ratio * checks[best].consistent) {
      continue;
    }
    int refuted = 0;
    for (std::size_t i = 0; i < x.uv0.size(); ++i) {
      if ((checks[best].status[i] & kGood) && !(checks[k].status[i] & (kConsistent | kUndecided))) {
        ++refuted;
      }
    }
    if (refuted < kMinRefutedFraction * checks[best].good) tied_buf[num_tied++] = k;
  }
  const std::span<const std::size_t> tied(tied_buf.data(), num_tied);
  if (tied.size() == 1) return true;
  const bool planar = r.model == TwoViewModel::kHomography;
  const std::optional<std::size_t> winner =
      planar ? tie_broken_by_plane_hints(candidates.span(), tied, plane_hints, o) : std::nullopt;
  if (!winner) {
    if (planar && r.median_parallax_deg >= o.plane_hint_min_parallax_deg) {
      for (const std::size_t k : tied) r.plane_normals_c0.push_back(candidates[k].n);
    }
    for (const std::size_t k : tied) r.candidate_motions.push_back(unit_motion(candidates[k]));
    refuse(r, TwoViewRefusal::kAmbiguous);
    return false;
  }
  if (*winner == best) return true;
  best = *winner;
  return winner_has_parallax(x);
}

/// Step 6, essential model: refine the winning motion on the Sampson error (the 8-point F is an
/// algebraic fit, and its inlier set was gated with that biased F), re-gate all
/// correspondences with the refined motion and repeat until the inlier set settles
/// (local optimization, as in LO-RANSAC). The homography is kept as decomposed: its DLT
/// fit on a plane is already constrained by every inlier in both images.
void refine_essential(Reconstruction& x) {
  TwoViewWorkspace::Buffers& ws = x.ws;
  TwoViewResult& r = x.r;
  if (r.model != TwoViewModel::kEssential) return;
  const double inv_var = 1.0 / (kResidualVarianceFactor * x.o.sigma_px * x.o.sigma_px);
  const Eigen::Matrix3d Km = k_matrix(x.K);
  std::vector<std::uint8_t>& refined_inliers = ws.refined_inliers;
  refined_inliers.assign(x.inliers.begin(), x.inliers.end());
  std::vector<std::uint8_t>& mask = ws.mask;
  mask.assign(x.uv0.size(), 0);
  for (int round = 0; round < kLocalOptimizationRounds; ++round) {
    const MotionSigma sig = refine_motion(ws.candidates[x.best], x.uv0, x.uv1, refined_inliers, x.K,
                                          x.o.sigma_px, ws.refine);
    r.rotation_sigma_deg = sig.rotation_deg;
    r.translation_dir_sigma_deg = sig.translation_dir_deg;
    int count = 0;
    score_fundamental(fundamental_from_motion(ws.candidates[x.best], Km), x.uv0, x.uv1, inv_var,
                      -std::numeric_limits<double>::infinity(), mask, count);
    if (mask == refined_inliers) break;
    refined_inliers.swap(mask);
    r.num_inliers = count;
  }
  x.inliers = refined_inliers;
}

/// Step 7: the map of the winner, scaled to median depth 1 in camera 0, after the same tests
/// as the vote and the motion's certainty test.
void finish(Reconstruction& x) {
  const TwoViewOptions& o = x.o;
  TwoViewWorkspace::Buffers& ws = x.ws;
  TwoViewResult& r = x.r;
  const std::size_t n = x.uv0.size();
  const two_view_detail::Motion& motion = ws.candidates[x.best];
  r.points_c0.assign(n, Eigen::Vector3d::Zero());
  r.triangulated.assign(n, 0);
  CandidateCheck& final_check = ws.final_check;
  check_candidate(motion, x.uv0, x.uv1, x.inliers, x.K, o, &r.points_c0, &r.triangulated,
                  final_check);
  r.num_triangulated = final_check.good;
  // The refined motion and the DLT points must pass the same tests as the vote.
  r.median_parallax_deg = median_of(final_check.parallax_deg, ws.median);
  if (r.median_parallax_deg < o.min_parallax_deg) {
    return refuse(r, TwoViewRefusal::kLowParallax);
  }
  // The plane-and-parallax F rests on the few points off the plane: it must show a sharp
  // translation direction whatever the parallax.
  const bool from_plane_parallax = ws.pp.num_inliers > 0;
  if ((r.median_parallax_deg < o.confident_parallax_deg || from_plane_parallax) &&
      (r.model != TwoViewModel::kEssential ||
       r.translation_dir_sigma_deg > o.max_translation_dir_sigma_deg)) {
    r.candidate_motions.push_back(unit_motion(motion));
    return refuse(r, TwoViewRefusal::kUncertainMotion);
  }
  if (final_check.good < o.min_triangulated) {
    return refuse(r, TwoViewRefusal::kTooFewTriangulated);
  }
  std::vector<double>& depths = ws.values;
  depths.clear();
  for (std::size_t i = 0; i < n; ++i) {
    if (r.triangulated[i]) depths.push_back(r.points_c0[i].z());
  }
  const double scale = 1.0 / median_of(depths, ws.median);
  for (std::size_t i = 0; i < n; ++i) {
    if (r.triangulated[i]) r.points_c0[i] *= scale;
  }
  r.T_c1_c0 = SE3d::Identity();
  r.T_c1_c0.linear() = motion.R;
  r.T_c1_c0.translation() = motion.t * scale;
  r.ok = true;
}

void reconstruct_impl(std::span<const Eigen::Vector2d> uv0, std::span<const Eigen::Vector2d> uv1,
                      const Pinhole& K, const TwoViewOptions& o, bool force_essential,
                      std::span<const Eigen::Vector3d> plane_hints, TwoViewWorkspace::Buffers& ws,
                      TwoViewResult& r) {
  reset_keeping_capacity(r);
  Reconstruction x{uv0, uv1, K, o, ws, r, {}, 0};
  if (!choose_model(x, force_essential)) return;
  if (!vote(x, plane_hints)) return;
  refine_essential(x);
  finish(x);
}

}  // namespace

TwoViewResult reconstruct_two_view(std::span<const Eigen::Vector2d> uv0,
                                   std::span<const Eigen::Vector2d> uv1, const Pinhole& K,
                                   const TwoViewOptions& o,
                                   std::span<const Eigen::Vector3d> plane_hints) {
  TwoViewWorkspace ws;
  TwoViewResult r;
  reconstruct_two_view(uv0, uv1, K, o, plane_hints, ws, r);
  return r;
}

void reconstruct_two_view(std::span<const Eigen::Vector2d> uv0,
                          std::span<const Eigen::Vector2d> uv1, const Pinhole& K,
                          const TwoViewOptions& o, std::span<const Eigen::Vector3d> plane_hints,
                          TwoViewWorkspace& ws, TwoViewResult& r) {
  TwoViewWorkspace::Buffers& b = *ws.b_;
  reconstruct_impl(uv0, uv1, K, o, false, plane_hints, b, r);
  // A homography preferred by the scores can still be ambiguous (a dominant plane seen
  // under forward-ish motion has two physically valid decompositions) while the points off
  // the plane (boxes in front of a wall, another wall) pin down the essential matrix: try
  // the essential model before refusing. Its own checks (parallax, cheirality, ambiguity)
  // still apply, so a truly degenerate pair is refused either way.
  if (!r.ok && r.model == TwoViewModel::kHomography &&
      (r.refusal == TwoViewRefusal::kAmbiguous ||
       r.refusal == TwoViewRefusal::kTooFewTriangulated)) {
    TwoViewResult& e = b.retry;
    reconstruct_impl(uv0, uv1, K, o, true, plane_hints, b, e);
    if (e.ok) {
      std::swap(r, e);  // (both keep their buffers)
      return;
    }
    r.candidate_motions.insert(r.candidate_motions.end(), e.candidate_motions.begin(),
                               e.candidate_motions.end());
  }
}

}  // namespace mer::geometry
