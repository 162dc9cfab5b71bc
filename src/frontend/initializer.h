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
/// the tracker never takes the map's writer lock). Setup (reserve) allocates; spin_once may
/// allocate (the two-view reconstruction does). Not thread-safe: the tracking thread's.

#include <cstddef>
#include <cstdint>
#include <vector>

#include "core/pose.h"
#include "core/sensor_mode.h"
#include "features/keypoint.h"
#include "frontend/focal_estimator.h"
#include "frontend/keypoint_grid.h"
#include "frontend/tracking_options.h"
#include "geometry/camera_model.h"
#include "geometry/two_view.h"
#include "hal/camera.h"
#include "map/keyframe_job.h"

namespace mer::frontend {

/// Why a frame did not start the map.
enum class InitRefusal : std::uint8_t {
  kNone = 0,           ///< not refused: the frame started the map
  kNoDepth,            ///< RGB-D: the frame has no depth image
  kTooFewFeatures,     ///< fewer keypoints than `init.min_features`
  kNoReference,        ///< there was no reference frame: this frame is the reference now
  kTooFewMatches,      ///< fewer matches to the reference than `init.two_view.min_matches`
  kReferenceTooOld,    ///< RGB-D, estimating the focal: the reference was too old to match
  kFocalPending,       ///< fewer two-view focal estimates than `focal.min_init_estimates`
  kTwoView,            ///< the two-view reconstruction refused (InitDecision::two_view says why)
  kTooFewDepthPoints,  ///< RGB-D: fewer keypoints with valid depth than `init.rgbd_min_points`
};
/// Number of InitRefusal values (counters indexed by it).
inline constexpr std::size_t kInitRefusalCount =
    static_cast<std::size_t>(InitRefusal::kTooFewDepthPoints) + 1;

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
  double median_depth = 1.0;      ///< median depth of the points in the frame
  std::uint64_t ref_seq = 0;      ///< the world frame's sequence number (RGB-D: this frame)
};

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

  /// Sizes the buffers for frames of at most `max_keypoints` keypoints (setup: allocates).
  void reserve(int max_keypoints);

  /// Decides on one frame: `features` holds its keypoints and descriptors (at most
  /// reserve's max_keypoints), `K` the intrinsics it is seen with. Two-view focal estimates go
  /// to `focal` (which a start fixes). A start's keyframes and points are kept for
  /// fill_segment_start until the next start.
  InitDecision spin_once(const hal::Frame& frame, const KeypointGrid& features,
                         const geometry::Pinhole& K, FocalEstimator& focal);

  /// Copies the last start into `st`, the segment start of a keyframe job of
  /// `num_keypoints` keypoints (the start frame's). No allocation (st sized by reserve).
  void fill_segment_start(map::SegmentStart& st, int num_keypoints) const;
  /// Points of the last start.
  int start_points() const { return start_.num_points; }

  /// Forgets the reference frame and its plane hints (a new segment, or a start the map
  /// refused): the next frame with enough keypoints becomes the reference.
  void drop_reference();
  /// Whether a reference frame is held.
  bool has_reference() const { return ref_valid_; }
  /// Sequence number of the reference frame (valid with has_reference()).
  std::uint64_t reference_seq() const { return ref_seq_; }

 private:
  void initialize_mono(const hal::Frame& frame, const KeypointGrid& features, FocalEstimator& focal,
                       InitDecision& d);
  void initialize_rgbd(const hal::Frame& frame, const KeypointGrid& features, FocalEstimator& focal,
                       InitDecision& d);
  void set_reference(const hal::Frame& frame, const KeypointGrid& features);
  /// Matches the reference's keypoints in `features` (init_* and ref_prev_); returns the count.
  int match_reference(const KeypointGrid& features);
  /// Adds a two-view focal estimate from the last matches to `focal` (d.K follows it).
  void focal_from_reference(int matches, FocalEstimator& focal, InitDecision& d);
  bool reference_too_old(std::int64_t t_ns) const;

  InitOptions opts_;
  double min_disparity_px_;  // tracking.focal.min_disparity_px
  std::uint64_t seed_;       // tracking.pnp.seed
  double rgbd_max_depth_step_;
  bool rgbd_;

  // The reference frame.
  bool ref_valid_ = false;
  std::uint64_t ref_seq_ = 0;
  std::int64_t ref_t_ns_ = 0;
  std::vector<Eigen::Vector3d> plane_hints_;  // plane normals of the reference's first planar tie
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
  // The last start: its keyframes' depths and points.
  map::SegmentStart start_;
};

}  // namespace mer::frontend
