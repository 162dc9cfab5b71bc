#pragma once
/// @file triangulation_depth.h
/// `triangulation` depth inference (monocular default): every keypoint of the new keyframe
/// that is not yet a map-point is searched along its epipolar line in the neighbouring
/// keyframes (descriptor distance + ratio test, levels close, one-to-one per view),
/// triangulated with the widest-baseline view (the most accurate depth), then re-triangulated
/// over every view whose match agrees with it. Kept when it lies in front of the cameras,
/// reprojects within a few sigmas and has enough parallax. Confidence grows with parallax
/// and with the number of agreeing views. Depth is in map units.

#include <vector>

#include <Eigen/Core>

#include "depth/depth_inference.h"
#include "depth/depth_options.h"

namespace mer::depth {

/// Epipolar matching + two-view triangulation backend.
class TriangulationDepth final : public DepthInference {
 public:
  explicit TriangulationDepth(const TriangulationOptions& opts) : opts_(opts) {}
  std::string_view name() const override { return "triangulation"; }
  DepthScale scale() const override { return DepthScale::kMap; }
  Status infer(const DepthRequest& req, DepthResult& out) override;

 private:
  /// The keyframe's and its views' geometry for one infer() call (triangulation_depth.cpp).
  struct Views;
  /// Epipolar matches (match_) of the request's free keypoints in view `vi`: the closest
  /// descriptor within the band and the ratio, one-to-one per view.
  void match_view(const Views& g, std::size_t vi);
  /// Depth of free keypoint `i` from its matches (out.depth, confidence, support, fates).
  void triangulate_keypoint(const Views& g, std::size_t i, DepthResult& out) const;

  TriangulationOptions opts_;
  std::vector<std::uint32_t> match_;    // [keypoint * views + view]: matched keypoint or none
  std::vector<int> best_dist_;          // per keypoint of one view: distance of its match
  std::vector<std::uint32_t> best_of_;  // per keypoint of one view: the keypoint it went to
  // The free keypoints of one view, computed once per view rather than once per pair.
  struct Candidate {
    Eigen::Vector3d x;     // normalized image point
    double band_px = 0.0;  // epipolar band half-width at its level, px
    std::uint32_t j = 0;   // keypoint index in the view
    int level = 0;
  };
  std::vector<Candidate> candidates_;
  // The same, ordered by level (keypoint index ascending within a level), and where each
  // level starts in it: a keypoint is compared with the levels near its own only.
  std::vector<Candidate> by_level_;
  std::vector<std::size_t> level_begin_;
  std::vector<std::size_t> level_next_;  // fill cursor per level
};

}  // namespace mer::depth
