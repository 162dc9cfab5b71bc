#pragma once
/// @file depth_options.h
/// Options of keyframe creation and depth inference (config section `depth`).

#include <array>
#include <string>
#include <string_view>

#include "core/options.h"
#include "depth/plane_sweep_depth.h"

namespace mer::depth {

/// Backends selectable in config.
inline constexpr std::array<std::string_view, 4> kDepthBackends{"auto", "triangulation", "rgbd",
                                                                "plane_sweep"};

/// Options of the `triangulation` backend.
struct TriangulationOptions {
  int max_hamming = 50;           ///< largest descriptor distance of an epipolar match
  double ratio = 0.7;             ///< best / second-best distance ratio of a match
  double epipolar_sigmas = 2.0;   ///< epipolar band half-width, in keypoint sigmas (chi2-like)
  double min_parallax_deg = 1.0;  ///< less parallax: no depth (too uncertain)
  double full_confidence_parallax_deg = 6.0;  ///< parallax giving confidence 1
  double max_reprojection_sigmas = 2.5;       ///< reprojection error bound in both views, sigmas
  int max_level_difference = 1;               ///< pyramid levels a match may differ by
  double max_scale_inconsistency = 1.5;       ///< distance ratio vs keypoint scale ratio tolerance
  int min_views = 3;                          ///< views (with the keyframe) that must agree

  template <class V>
  void visit(V& v) {
    v.field("max_hamming", max_hamming, "largest descriptor distance of an epipolar match",
            options::Range<int>{0, 256});
    v.field("ratio", ratio, "best / second-best descriptor distance ratio",
            options::Range<double>{0.0, 1.0});
    v.field("epipolar_sigmas", epipolar_sigmas, "epipolar band half-width in keypoint sigmas",
            options::Range<double>{0.1, 20.0});
    v.field("min_parallax_deg", min_parallax_deg, "less parallax gives no depth, degrees",
            options::Range<double>{0.0, 90.0});
    v.field("full_confidence_parallax_deg", full_confidence_parallax_deg,
            "parallax giving confidence 1, degrees", options::Range<double>{0.01, 90.0});
    v.field("max_reprojection_sigmas", max_reprojection_sigmas,
            "reprojection error bound in both views, keypoint sigmas",
            options::Range<double>{0.1, 20.0});
    v.field("max_level_difference", max_level_difference,
            "pyramid levels an epipolar match may differ by", options::Range<int>{0, 16});
    v.field("max_scale_inconsistency", max_scale_inconsistency,
            "largest factor between the ratio of distances to the two cameras and the ratio "
            "of the keypoints' pyramid scales",
            options::Range<double>{1.0, 100.0});
    v.field("min_views", min_views,
            "views, the new keyframe included, whose matches must agree on a point before it "
            "gets a depth (2: one neighbour suffices)",
            options::Range<int>{2, 17});
  }
};

/// Options of the `rgbd` backend.
struct RgbdDepthOptions {
  double min_depth_m = 0.1;  ///< closer sensor readings are ignored, m
  double max_depth_m = 8.0;  ///< farther sensor readings are ignored, m

  template <class V>
  void visit(V& v) {
    v.field("min_depth_m", min_depth_m, "closer sensor readings are ignored, m",
            options::Range<double>{0.0, 1000.0});
    v.field("max_depth_m", max_depth_m, "farther sensor readings are ignored, m",
            options::Range<double>{0.0, 1000.0});
  }
};

/// Keyframe creation and depth inference.
struct DepthOptions {
  std::string backend = "auto";    ///< auto: rgbd in rgbd mode, else triangulation
  int neighbours = 5;              ///< keyframes depth inference looks at
  double min_confidence = 0.2;     ///< depth below this confidence makes no map-point
  int min_scale_samples = 20;      ///< 3D-2D matches needed to align a non-map-scale depth
  int fuse_keyframes = 10;         ///< keyframes whose map points are projected into a new one
  double fuse_radius_px = 3.0;     ///< search radius of that projection, level-0 px (x scale)
  int fuse_max_hamming = 50;       ///< largest descriptor distance of a projected match
  double fuse_min_view_cos = 0.5;  ///< cosine of the largest angle to a point's mean view ray
  TriangulationOptions triangulation;
  RgbdDepthOptions rgbd;
  PlaneSweepDepthOptions plane_sweep;

  template <class V>
  void visit(V& v) {
    v.field("backend", backend,
            "depth inference: auto (rgbd in rgbd mode, else triangulation), triangulation, "
            "rgbd, plane_sweep",
            options::OneOf{kDepthBackends});
    v.field("neighbours", neighbours, "neighbouring keyframes depth inference uses",
            options::Range<int>{1, 16});
    v.field("min_confidence", min_confidence,
            "keypoint depth below this confidence makes no map-point",
            options::Range<double>{0.0, 1.0});
    v.field("min_scale_samples", min_scale_samples,
            "3D-2D matches needed to scale-align a depth not in map units",
            options::Range<int>{1, 100000});
    v.field("fuse_keyframes", fuse_keyframes,
            "covisible keyframes whose map points are projected into a new keyframe and "
            "matched to its untracked keypoints (more observations per point; 0: off)",
            options::Range<int>{0, 64});
    v.field("fuse_radius_px", fuse_radius_px,
            "search radius of the projection into a new keyframe, level-0 px (scaled with the "
            "predicted pyramid level)",
            options::Range<double>{0.5, 100.0});
    v.field("fuse_max_hamming", fuse_max_hamming,
            "largest descriptor distance of a map point matched into a new keyframe",
            options::Range<int>{0, 256});
    v.field("fuse_min_view_cos", fuse_min_view_cos,
            "cosine of the largest angle between the new keyframe's view ray and a point's mean "
            "viewing direction for the point to be projected into it",
            options::Range<double>{-1.0, 1.0});
    v.section("triangulation", triangulation, "multi-view triangulation backend (monocular)");
    v.section("rgbd", rgbd, "RGB-D passthrough backend");
    v.section("plane_sweep", plane_sweep,
              "dense plane-sweep stereo backend (keyframe against recent tracked frames)");
  }
};

}  // namespace mer::depth
