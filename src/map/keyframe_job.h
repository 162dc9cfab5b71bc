#pragma once
/// @file keyframe_job.h
/// What the tracking stage hands to keyframe creation (depth inference + map insertion)
/// when it decides a frame becomes a keyframe, or when its initialization has made the first
/// keyframes and points of a map segment (the tracking thread never writes the map itself).
/// Slots are preallocated for the largest frame; the tracker copies into them, so handing a
/// job over never allocates.

#include <cstdint>
#include <vector>

#include <Eigen/Core>
#include <opencv2/core/mat.hpp>

#include "core/pose.h"
#include "features/keypoint.h"
#include "geometry/camera_model.h"

namespace mer::map {

/// What a job asks keyframe creation to do.
enum class KeyframeJobKind : std::uint8_t {
  kTracked,       ///< a tracked frame becomes a keyframe (depth inference, then insertion)
  kSegmentStart,  ///< a map segment's first keyframes and points, as initialization made them
};

/// The start of a map segment (KeyframeJobKind::kSegmentStart): monocular, two keyframes, the
/// reference view (`ref_*`, the segment's world frame) and the job's frame; RGB-D, the job's
/// frame alone (the world frame). The points are in the world frame, each created in the
/// first keyframe and, in monocular, also observed by the second.
struct SegmentStart {
  int num_views = 0;                              ///< keyframes to create: 1 (RGB-D) or 2
  std::uint64_t ref_seq = 0;                      ///< reference frame (monocular)
  std::int64_t ref_t_ns = 0;                      ///< its timestamp, ns
  int ref_num_keypoints = 0;                      ///< valid entries of ref_keypoints
  std::vector<features::Keypoint> ref_keypoints;  ///< capacity = max keypoints
  std::vector<features::Descriptor> ref_descriptors;
  std::vector<float> ref_depth;           ///< per reference keypoint, camera z (0: none)
  std::vector<float> ref_confidence;      ///< and its confidence (0: none)
  std::vector<float> depth;               ///< per keypoint of the job's frame, camera z (0: none)
  std::vector<float> confidence;          ///< and its confidence (0: none)
  int num_points = 0;                     ///< valid entries of the arrays below
  std::vector<Eigen::Vector3d> points_w;  ///< world position
  std::vector<std::uint32_t> first_keypoint;   ///< keypoint of the first keyframe that made it
  std::vector<std::uint32_t> second_keypoint;  ///< keypoint of the second keyframe (monocular)

  /// Sizes every buffer for `max_keypoints` keypoints.
  void reserve(int max_keypoints) {
    const auto n = static_cast<std::size_t>(max_keypoints);
    ref_keypoints.resize(n);
    ref_descriptors.resize(n);
    ref_depth.resize(n);
    ref_confidence.resize(n);
    depth.resize(n);
    confidence.resize(n);
    points_w.resize(n);
    first_keypoint.resize(n);
    second_keypoint.resize(n);
  }
};

/// One keyframe to create (or a segment's start).
struct KeyframeJob {
  KeyframeJobKind kind = KeyframeJobKind::kTracked;  ///< what to do with it
  std::uint64_t seq = 0;                             ///< frame sequence number
  std::int64_t t_ns = 0;                             ///< frame timestamp, ns
  SE3d T_w_c = SE3d::Identity();                     ///< tracked camera-to-world pose
  geometry::Pinhole K;                               ///< intrinsics the frame was tracked with
  int num_keypoints = 0;                             ///< valid entries in the arrays below
  std::uint8_t reason = 0;                    ///< frontend::KeyframeReason that fired (for logs)
  std::uint16_t segment = 0;                  ///< map segment the frame was tracked in
  std::vector<features::Keypoint> keypoints;  ///< capacity = max keypoints
  std::vector<features::Descriptor> descriptors;  ///< one per keypoint
  std::vector<std::uint32_t> point_ids;           ///< tracked map point per keypoint, or kNoId
  /// Generation of each tracked point when it was tracked (map.h: slots are reused, so
  /// keyframe creation drops an id whose slot has a newer occupant by now).
  std::vector<std::uint32_t> point_gens;
  std::vector<float> sensor_depth;  ///< sensor depth at keypoints (m, 0 = none)
  bool has_sensor_depth = false;    ///< sensor_depth is filled (RGB-D)
  cv::Mat gray;                     ///< copy of the image (dense backends)
  /// Recent tracked frames before this one (dense multi-view backends), newest first:
  /// `num_recent` valid entries of `recent_gray` / `recent_T_w_c`.
  std::vector<cv::Mat> recent_gray;
  std::vector<SE3d> recent_T_w_c;
  int num_recent = 0;
  SegmentStart start;  ///< kind kSegmentStart: the segment's first keyframes and points

  /// Sizes every buffer for `max_keypoints` keypoints and `width` x `height` images.
  void reserve(int max_keypoints, int width, int height) {
    const auto n = static_cast<std::size_t>(max_keypoints);
    keypoints.resize(n);
    descriptors.resize(n);
    point_ids.resize(n);
    point_gens.resize(n);
    sensor_depth.resize(n);
    start.reserve(max_keypoints);
    gray.create(height, width, CV_8UC1);
  }
  /// Room for `count` recent frames of `width` x `height` (0: none).
  void reserve_recent(int count, int width, int height) {
    recent_gray.resize(static_cast<std::size_t>(count));
    for (auto& g : recent_gray) g.create(height, width, CV_8UC1);
    recent_T_w_c.resize(static_cast<std::size_t>(count));
    num_recent = 0;
  }
  /// Keypoints this job can hold.
  int capacity() const { return static_cast<int>(keypoints.size()); }
};

}  // namespace mer::map
