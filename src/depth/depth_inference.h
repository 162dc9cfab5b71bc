#pragma once
/// @file depth_inference.h
/// The depth-inference interface: given a new keyframe (image, pose, keypoints) and a few
/// other views with their poses, produce depth and a confidence at the keyframe's keypoints
/// (optionally a dense map). Backends:
/// - `triangulation` (monocular default): keypoints matched along epipolar lines in the
///   neighbouring keyframes and triangulated with the map's poses (depth in map units);
/// - `rgbd`: the sensor's depth at the keypoints (metres);
/// - `plane_sweep`: dense multi-view stereo over the keyframe and recent tracked frames,
///   sampled at the keypoints (depth in map units);
/// - `external`: depth maps read from files, one per frame (e.g. a learned model's output
///   recorded offline), sampled at the keypoints (metres, or up to an unknown scale).
/// A backend only sees this request; the keyframe-creation stage aligns the scale and turns
/// local 3D points into map-points, so a new backend never touches the front end.

#include <cstdint>
#include <span>
#include <string_view>

#include <opencv2/core/mat.hpp>

#include "core/pose.h"
#include "core/status.h"
#include "features/keypoint.h"
#include "geometry/camera_model.h"

namespace mer::depth {

/// In which unit a backend's depth comes out.
enum class DepthScale : std::uint8_t {
  kMap,      ///< already in map units (computed from map poses)
  kMetric,   ///< metres (a depth sensor)
  kUnknown,  ///< up to an unknown scale (a monocular network): always aligned to the map
};

/// Another view of the scene with its pose (a neighbouring keyframe).
struct DepthView {
  std::uint32_t id = 0;           ///< keyframe id
  SE3d T_w_c = SE3d::Identity();  ///< camera-to-world
  std::span<const features::Keypoint> keypoints;
  std::span<const features::Descriptor> descriptors;
  std::span<const std::uint32_t> point_ids;  ///< associated map point per keypoint (or none)
  const cv::Mat* gray = nullptr;             ///< image, when the backend needs pixels
};

/// A recent tracked frame (dense multi-view backends).
struct RecentView {
  const cv::Mat* gray = nullptr;  ///< image, same size and intrinsics as the keyframe
  SE3d T_w_c = SE3d::Identity();  ///< tracked camera-to-world
};

/// The keyframe whose depth is wanted, and its neighbours.
struct DepthRequest {
  std::int64_t t_ns = 0;          ///< keyframe capture time, ns
  SE3d T_w_c = SE3d::Identity();  ///< keyframe camera-to-world
  geometry::Pinhole K;
  std::span<const features::Keypoint> keypoints;
  std::span<const features::Descriptor> descriptors;
  std::span<const std::uint32_t> point_ids;  ///< keypoints already associated to map points
  std::span<const float> sensor_depth;       ///< sensor depth per keypoint (empty: none)
  std::span<const float> level_sigma2;       ///< keypoint noise variance per pyramid level
  const cv::Mat* gray = nullptr;             ///< keyframe image
  std::span<const DepthView> views;          ///< neighbours, most relevant first
  std::span<const RecentView> recent;        ///< recent frames, newest first (may be empty)
  double depth_hint_min = 0.0;  ///< depth range of the tracked map-points (0: unknown), map
  double depth_hint_max = 0.0;  ///< units, for backends that sweep a range
};

/// Output buffers, sized by the caller for the request's keypoints.
/// What became of a keyframe's free keypoints (not yet map-points) in depth inference, by
/// the first check each failed (backends that do not match across views fill `free` and
/// `depth` only). `Count`: int for one keyframe, a 64-bit count for a run's totals.
template <class Count>
struct BasicKeypointFates {
  Count free = 0;          ///< keypoints that were not map-points yet
  Count no_match = 0;      ///< no view matched it along its epipolar line
  Count low_parallax = 0;  ///< matched, but the widest baseline saw it under too small an angle
  Count few_views = 0;     ///< fewer agreeing views than depth.triangulation.min_views
  Count rejected = 0;      ///< behind a camera, reprojected too far, or scales inconsistent
  Count depth = 0;         ///< given a depth

  /// Adds another count (one keyframe's to a run's totals).
  template <class Other>
  void add(const BasicKeypointFates<Other>& o) {
    free += static_cast<Count>(o.free);
    no_match += static_cast<Count>(o.no_match);
    low_parallax += static_cast<Count>(o.low_parallax);
    few_views += static_cast<Count>(o.few_views);
    rejected += static_cast<Count>(o.rejected);
    depth += static_cast<Count>(o.depth);
  }
};
using KeypointFates = BasicKeypointFates<int>;

struct DepthResult {
  std::span<float> depth;                     ///< camera z per keypoint (0 = unknown)
  std::span<float> confidence;                ///< [0, 1] per keypoint
  std::span<std::uint32_t> support_view;      ///< index into views of the matched view, or ~0
  std::span<std::uint32_t> support_keypoint;  ///< keypoint index in that view, or ~0
  int num_valid = 0;                          ///< keypoints that got a depth
  /// Optional (empty: not wanted), for backends that match keypoints across views: every
  /// view's keypoint that agrees with the depth, row-major [keypoint][view] with
  /// views.size() columns, kNoSupport where the view did not agree. The new map-point is
  /// observed in all of them, not only in support_view.
  std::span<std::uint32_t> view_keypoint;
  bool input_missing = false;  ///< the backend had no input for this keyframe (e.g. no depth
                               ///< map near its time): no depth, counted apart from failures
  KeypointFates fates;         ///< what became of the free keypoints
};

/// No supporting view.
inline constexpr std::uint32_t kNoSupport = 0xFFFFFFFFu;

/// A depth-inference backend. Called on the keyframe-creation thread (low priority).
class DepthInference {
 public:
  virtual ~DepthInference() = default;
  /// Backend name (config value).
  virtual std::string_view name() const = 0;
  /// Unit of the produced depth.
  virtual DepthScale scale() const = 0;
  /// Fills `out` for `req`. An error is a failure of this keyframe only.
  virtual Status infer(const DepthRequest& req, DepthResult& out) = 0;
};

}  // namespace mer::depth
