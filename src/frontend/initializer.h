#pragma once
/// @file initializer.h
/// Map initialization, asked by the tracker for every frame while its map segment has no map
/// (`spin_once(frame, features, K, focal) -> InitDecision`): the frame either starts the
/// segment or is refused, with a reason.
/// - Monocular: the initializer keeps a reference frame and searches its keypoints in each
///   new frame (from where each was last matched, within `tracking.init.search_radius_px`);
///   the matched pairs go to the two-view reconstruction (geometry/two_view.h). A start is two
///   keyframes, the reference (the segment's world frame) and the frame, with the points
///   triangulated in the reference, at unit median depth. A frame with too few keypoints drops
///   the reference; one with too few matches, or one refused while the reference is older than
///   `max_reference_age_s` (`max_plane_hint_reference_age_s` once the reference holds plane
///   hints), becomes the new reference.
///   With `tracking.init.align` each match then moves to where the reference keypoint's patch
///   (its pixels in the reference's pyramid, at its level) aligns in the frame's, and a match
///   whose alignment does not converge within `align.max_shift_px` of the detection is
///   dropped (`drop_refused`): every frame measures the point the reference saw.
///   When the two-view reconstruction refuses an essential model's motion as uncertain (low
///   parallax: the translation direction is not sharp), the window decides
///   (`tracking.init.window`). The initializer keeps up to `max_views` of the frames tracked
///   since the reference, spread evenly, with the pixel where each reference keypoint was
///   matched in each. The current frame is held at the candidate motion and the frames in
///   between and the inverse depths of the points tracked through all of them are solved
///   (geometry/window_ba.h; wrong tracks dropped at the chi2 gate). Then the current frame is
///   released: if the whole window's solution moves it more than `max_moved_rotation_deg` /
///   `max_moved_direction_deg`, the motion is not determined yet and the frame is refused.
///   A start keeps the candidate's motion; its points are triangulated from every view that
///   saw them, and a point must reproject within the chi2 gate in each.
///   Ties (a wall's homography and its twin) are decided on the window only with
///   `decide_ties`: each candidate is solved as above, and the one of least truncated cost
///   wins when it beats every other by `min_evidence_sigmas` standard errors of the mean
///   per-point difference. Off by default: when the camera moves along a line the twin
///   explains the frames in between as well as the truth (docs/decisions/window-start.md).
/// - Orientation before a map (monocular): a frame the two-view reconstruction refuses as a
///   pure rotation of the reference has a known orientation, the rotation fitted to the
///   matches' bearings. References chain: a frame of known orientation that becomes the next
///   reference keeps its orientation, so that the orientations of a chain share one world
///   (the chain's first reference camera). A reference set without a known orientation starts
///   a new chain. While the pairs are pure rotations, a frame that keeps fewer than
///   `rotation_renew_fraction` of the matches of the reference's first matched frame becomes
///   the next reference (a sweep leaving the reference's view stays in one chain).
/// - RGB-D: a start is one keyframe, the frame (the world frame), with a point per keypoint
///   whose sensor depth is valid.
/// With `pipeline.focal: auto`, a start waits until `tracking.focal.min_init_estimates`
/// two-view focal estimates (one per frame matched to the reference with enough disparity)
/// are in the FocalEstimator (RGB-D keeps a reference for them too: a frame with too few
/// keypoints or matches, or a reference too old, makes a new one); a start fixes the focal
/// unless `refine_after_init`.
///
/// The initializer holds the reference and the state since it, and the last start
/// (fill_segment_start copies it into the keyframe job that creates the segment's keyframes:
/// the tracker never takes the map's writer lock). Setup (reserve) allocates; spin_once does
/// not (frames of at most the reserved keypoints). Not thread-safe: the tracking thread's.

#include <array>
#include <cstddef>
#include <cstdint>
#include <limits>
#include <span>
#include <vector>

#include <opencv2/core.hpp>

#include "core/pose.h"
#include "core/sensor_mode.h"
#include "features/keypoint.h"
#include "features/patch_align.h"
#include "frontend/focal_estimator.h"
#include "frontend/keypoint_grid.h"
#include "frontend/tracking_options.h"
#include "geometry/camera_model.h"
#include "geometry/two_view.h"
#include "geometry/window_ba.h"
#include "hal/camera.h"
#include "map/keyframe_job.h"

namespace mer::frontend {

/// Why a frame did not start the map.
enum class InitRefusal : std::uint8_t {
  kNone = 0,            ///< not refused: the frame started the map
  kNoDepth,             ///< RGB-D: the frame has no depth image
  kTooFewFeatures,      ///< fewer keypoints than `init.min_features`
  kNoReference,         ///< there was no reference frame: this frame is the reference now
  kTooFewMatches,       ///< fewer matches to the reference than `init.two_view.min_matches`
  kReferenceTooOld,     ///< RGB-D, estimating the focal: the reference was too old to match
  kFocalPending,        ///< fewer two-view focal estimates than `focal.min_init_estimates`
  kTwoView,             ///< the two-view reconstruction refused (InitDecision::two_view says why)
  kTooFewDepthPoints,   ///< RGB-D: fewer keypoints with valid depth than `init.rgbd_min_points`
  kWindowAmbiguous,     ///< the window (decide_ties): another motion explains it nearly as well
  kWindowUncertain,     ///< the window: released, the motion moved (not determined yet)
  kWindowTooFewPoints,  ///< the window's solution triangulates too few points, or under too
                        ///< little parallax
};
/// Number of InitRefusal values (counters indexed by it).
inline constexpr std::size_t kInitRefusalCount =
    static_cast<std::size_t>(InitRefusal::kWindowTooFewPoints) + 1;

/// Short name of a refusal ("too_few_matches", ...; "two_view" for kTwoView).
const char* to_string(InitRefusal r);

/// The initializer's answer for one frame.
struct InitDecision {
  bool started = false;                      ///< the frame starts the segment (fields below)
  InitRefusal refusal = InitRefusal::kNone;  ///< otherwise, why not
  geometry::TwoViewRefusal two_view = geometry::TwoViewRefusal::kNone;  ///< kTwoView: why
  bool two_view_tried = false;  ///< a two-view reconstruction was tried on this frame
  geometry::Pinhole K;          ///< intrinsics after the frame (`focal: auto` moves the focal)
  // A start:
  int num_views = 0;              ///< keyframes it makes: 2 (monocular) or 1 (RGB-D)
  SE3d T_c_w = SE3d::Identity();  ///< the frame's world-to-camera pose (world: reference camera)
  SE3d T_w_c = SE3d::Identity();  ///< and camera-to-world (RGB-D: both exactly the identity)
  int num_points = 0;             ///< points made
  int num_matches = 0;            ///< monocular: matches to the reference
  int window_views = 0;           ///< monocular: frames in between that decided the start (0:
                                  ///< the two-view reconstruction alone)
  // Not started, monocular: the orientation of a rotation-only motion.
  bool has_orientation = false;  ///< the frame was refused as a pure rotation of a reference
                                 ///< whose orientation is known: R_c_w below is valid
  Eigen::Matrix3d R_c_w = Eigen::Matrix3d::Identity();  ///< camera from the chain's world
  std::uint32_t orientation_chain = 0;  ///< the chain: a run of references, each a frame of
                                        ///< known orientation, whose world is the first one's
  double median_depth = 1.0;            ///< median depth of the points in the frame
  std::uint64_t ref_seq = 0;            ///< the world frame's sequence number (RGB-D: this frame)
  // Diagnosis, monocular, sources with ground truth and depth (synthetic): the frame's matches
  // to the reference checked against the true projection of the reference keypoint's point.
  int gt_checked = 0;  ///< matches whose reference keypoint has a true depth
  int gt_wrong = 0;    ///< of those, matched more than kGtWrongMatchPx from the true pixel
};

/// A match to the reference further than this from the true projection counts as wrong in
/// the ground-truth audit (InitDecision::gt_wrong), px.
inline constexpr double kGtWrongMatchPx = 2.0;

/// Name of a decision's refusal for logs and summary.json `last_init_refusal`: for kTwoView the
/// two-view reason (geometry::to_string(TwoViewRefusal): "ambiguous", ...), else
/// to_string(refusal).
const char* refusal_name(const InitDecision& d);

/// Monocular two-view / RGB-D one-frame initialization of a map segment.
class Initializer {
 public:
  /// Reads `opts.init`, `opts.focal.min_disparity_px`, `opts.pnp.seed` (the focal estimate's
  /// RANSAC) and `opts.rgbd_max_depth_step`.
  Initializer(const TrackingOptions& opts, SensorMode mode);

  /// Sizes the buffers for frames of at most `max_keypoints` keypoints of `width` x `height`
  /// images (setup: allocates; a frame of another size makes the match alignment allocate).
  void reserve(int max_keypoints, int width, int height);

  /// Decides on one frame: `features` holds its keypoints and descriptors (at most
  /// reserve's max_keypoints), `K` the intrinsics it is seen with. Two-view focal estimates go
  /// to `focal` (which a start fixes). A start's keyframes and points are kept for
  /// fill_segment_start until the next start.
  InitDecision spin_once(const hal::Frame& frame, const KeypointGrid& features,
                         const geometry::Pinhole& K, FocalEstimator& focal);

  /// Copies the last start into `st`, the segment start of a keyframe job whose
  /// `keypoints` are the start frame's; with init.align the keypoints of the start's points
  /// move to where their matches were aligned (where the points were triangulated from). No
  /// allocation (st sized by reserve).
  void fill_segment_start(map::SegmentStart& st, std::span<features::Keypoint> keypoints) const;
  /// Points of the last start.
  int start_points() const { return start_.num_points; }

  /// Forgets the reference frame and its plane hints (a new segment, or a start the map
  /// refused): the next frame with enough keypoints becomes the reference.
  void drop_reference();
  /// Whether a reference frame is held.
  bool has_reference() const { return ref_valid_; }
  /// Sequence number of the reference frame (valid with has_reference()).
  std::uint64_t reference_seq() const { return ref_seq_; }
  /// Orientation chain of the reference frame (InitDecision::orientation_chain).
  std::uint32_t orientation_chain() const { return chain_; }

 private:
  void initialize_mono(const hal::Frame& frame, const KeypointGrid& features, FocalEstimator& focal,
                       InitDecision& d);
  void initialize_rgbd(const hal::Frame& frame, const KeypointGrid& features, FocalEstimator& focal,
                       InitDecision& d);
  /// Makes the frame the reference; with `R_c_w` (its orientation in the current chain) the
  /// chain goes on, without it a new chain starts at the frame.
  void set_reference(const hal::Frame& frame, const KeypointGrid& features,
                     const Eigen::Matrix3d* R_c_w = nullptr);
  /// Matches the reference's keypoints in `features` (init_* and ref_prev_); returns the count.
  int match_reference(const KeypointGrid& features);
  /// Pyramid of `gray` at the extractor's level sizes into `levels` (init.align).
  void build_levels(const cv::Mat& gray, std::vector<cv::Mat>& levels);
  /// The reference keypoints' patches (ref_patch_), from ref_levels_.
  void sample_reference_patches();
  /// Aligns the last matches to the reference patches (init_uv1_ and ref_prev_ move; refused
  /// ones are dropped with drop_refused); returns the matches left.
  int align_matches(const hal::Frame& frame);
  /// Keypoint `kp`'s position in level `l` pixels, and back.
  Eigen::Vector2f to_level(float x, float y, std::size_t l) const;
  Eigen::Vector2d from_level(const Eigen::Vector2f& uv, std::size_t l) const;
  /// Ground-truth audit of the last matches (d.gt_checked / gt_wrong) when the reference and
  /// the frame carry a true pose and the reference a depth image.
  void audit_matches(const hal::Frame& frame, const geometry::Pinhole& K, InitDecision& d) const;
  /// Adds a two-view focal estimate from the last matches to `focal` (d.K follows it).
  void focal_from_reference(int matches, FocalEstimator& focal, InitDecision& d);
  bool reference_too_old(std::int64_t t_ns) const;
  /// Keeps the frame's matches in the window if its turn has come (every win_stride_ frames).
  void remember_frame(const hal::Frame& frame);
  /// ref_match_ / kp_ref_ value of no match.
  static constexpr int kNoMatch = -1;
  /// Motion candidates checked on the window, at most.
  static constexpr std::size_t kMaxWindowCandidates = 8;
  /// The window's choice among the motion candidates.
  struct WindowVote {
    std::size_t best = 0;  ///< the candidate with the least truncated cost
    int slot = 0;          ///< ba_ slot holding its solution
    /// Smallest margin of the best over another distinct candidate: mean per-point cost
    /// difference over its standard error (infinite with one candidate).
    double evidence = std::numeric_limits<double>::infinity();
  };
  /// Decides a refused pair on the window; returns true when the frame starts the map.
  bool decide_on_window(const hal::Frame& frame, std::span<const SE3d> candidates,
                        const geometry::Pinhole& K, InitDecision& d);
  /// Selects the window adjustment's points (win_sel_): matches tracked through every view of
  /// the window that lie on an epipolar line of a candidate, spread evenly; returns how many.
  std::size_t select_window_points(std::span<const SE3d> candidates, const geometry::Pinhole& K);
  /// Solves the window with each candidate held fixed and picks the one of least truncated
  /// cost, with the evidence it beats the others by.
  WindowVote vote_on_window(const hal::Frame& frame, std::span<const SE3d> candidates,
                            const geometry::Pinhole& K);
  /// Triangulates every match from all the window's views (win_T_, the current frame at `T`)
  /// into win_points_c0_ / win_good_; returns the good points and their median parallax.
  int triangulate_window(const SE3d& T, const geometry::Pinhole& K, double& median_parallax);
  /// Solves the window with the current frame held at candidate `T_cur_ref`, in ba_[slot].
  void solve_candidate(const hal::Frame& frame, const SE3d& T_cur_ref, const geometry::Pinhole& K,
                       int slot);
  /// Writes the start of two keyframes (the reference and the frame) from the points of the
  /// matches (`points_c0`, where `good`), scaled to unit median depth in the reference.
  void make_start(const hal::Frame& frame, const KeypointGrid& features,
                  std::span<const Eigen::Vector3d> points_c0, std::span<const std::uint8_t> good,
                  const SE3d& T_cur_ref, int matches, FocalEstimator& focal, InitDecision& d);

  InitOptions opts_;
  double min_disparity_px_;  // tracking.focal.min_disparity_px
  double scale_factor_;      // tracking.extractor.scale_factor: keypoint sigma per level
  std::uint64_t seed_;       // tracking.pnp.seed
  double rgbd_max_depth_step_;
  bool rgbd_;

  // The reference frame.
  bool ref_valid_ = false;
  std::uint64_t ref_seq_ = 0;
  std::int64_t ref_t_ns_ = 0;
  Eigen::Matrix3d ref_R_ref_w_ = Eigen::Matrix3d::Identity();  // reference in its chain's world
  std::uint32_t chain_ = 0;                                    // the reference's chain
  int ref_first_matches_ = 0;  // matches of the first frame matched to the reference
  // Match alignment (init.align): the pyramids of the reference and the frame, each reference
  // keypoint's patch at its level, and where each match is now (level 0 px).
  int num_levels_ = 1;
  std::vector<cv::Mat> ref_levels_;
  std::vector<cv::Mat> cur_levels_;
  std::vector<double> level_to_x0_;
  std::vector<double> level_to_y0_;
  std::vector<features::WarpedPatch> ref_patch_;
  std::vector<std::uint8_t> ref_patch_ok_;
  bool ref_gt_ = false;                       // the reference has a true pose and depth (audit)
  SE3d ref_T_w_c_gt_ = SE3d::Identity();      // its true pose
  cv::Mat ref_depth_gt_;                      // its true depth, m (CV_32FC1)
  std::vector<Eigen::Vector3d> plane_hints_;  // plane normals of the reference's first planar tie
  geometry::TwoViewWorkspace two_view_ws_;    // reserved by reserve(): no allocation per frame
  geometry::TwoViewResult two_view_;          // the last two-view reconstruction
  std::vector<features::Keypoint> ref_kps_;
  std::vector<features::Descriptor> ref_descs_;
  std::vector<Eigen::Vector2d> ref_prev_;  // last matched position of each reference keypoint
  std::vector<std::int32_t> ref_match_;    // current keypoint matched to each reference keypoint
  // The last frame's matches to it.
  std::vector<std::int32_t> kp_ref_;   // per keypoint: reference keypoint matched, or -1
  std::vector<std::int32_t> kp_dist_;  // per keypoint: descriptor distance of that match
  std::vector<Eigen::Vector2d> init_uv0_;
  std::vector<Eigen::Vector2d> init_uv1_;
  std::vector<std::int32_t> init_ref_idx_;
  std::vector<std::int32_t> init_cur_idx_;
  std::vector<double> scratch_;
  // The window: frames since the reference, every win_stride_-th one (slot k holds frame
  // (k + 1) * win_stride_ after the reference), with the pixel of each reference keypoint
  // (NaN: not matched).
  int max_keypoints_ = 0;
  int win_views_ = 0;
  int win_stride_ = 1;
  int frames_since_ref_ = 0;
  std::vector<std::uint64_t> win_seq_;
  std::vector<Eigen::Vector2f> win_uv_;       // max_views x max_keypoints_
  std::vector<std::int32_t> win_consistent_;  // matches on an epipolar line of a candidate
  std::vector<std::int32_t> win_sel_;         // matches (indices into init_*) in the adjustment
  std::array<geometry::WindowBundleAdjuster, 2> ba_;  // the best candidate's and the next
  std::vector<double> point_cost_;              // per candidate and adjusted point: truncated cost
  std::vector<SE3d> win_T_;                     // the winner's views (camera from reference)
  std::vector<Eigen::Vector3d> win_points_c0_;  // per match: the window's point
  std::vector<std::uint8_t> win_good_;          // per match: a good point
  std::vector<SE3d> tri_T_;                     // triangulation views
  std::vector<Eigen::Vector3d> tri_x_;          // and their normalized rays
  // The last start: its keyframes' depths and points.
  map::SegmentStart start_;
  std::vector<Eigen::Vector2f> start_uv_;  // per start point: its match in the start frame
};

}  // namespace mer::frontend
