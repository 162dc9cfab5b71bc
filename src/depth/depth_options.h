#pragma once
/// @file depth_options.h
/// Options of keyframe creation and depth inference (config section `depth`).

#include <array>
#include <cstdint>
#include <string>
#include <string_view>

#include "core/options.h"
#include "depth/plane_sweep_depth.h"

namespace mer::depth {

/// Depth inference backend (`depth.backend`).
enum class DepthBackend : std::uint8_t {
  kAuto,           ///< rgbd in rgbd mode, else triangulation
  kTriangulation,  ///< epipolar matching and triangulation against neighbour keyframes
  kRgbd,           ///< the sensor's depth image
  kPlaneSweep,     ///< dense plane-sweep stereo against recent frames
  kExternal,       ///< depth maps from files (depth.external)
};
/// Names of DepthBackend in config, by value.
inline constexpr std::array<std::string_view, 5> kDepthBackendNames{"auto", "triangulation", "rgbd",
                                                                    "plane_sweep", "external"};

/// File formats of the `external` backend's depth maps.
inline constexpr std::array<std::string_view, 3> kExternalDepthFormats{"auto", "png16", "float32"};
/// How the `external` backend's file names give a timestamp.
inline constexpr std::array<std::string_view, 3> kExternalDepthTimeUnits{"auto", "s", "ns"};
/// Units of the `external` backend's depth (`depth.external.scale`).
enum class ExternalDepthScale : std::uint8_t {
  kUnknown,  ///< up to an unknown scale, aligned to the map
  kMetric,   ///< metres
};
/// Names of ExternalDepthScale in config, by value.
inline constexpr std::array<std::string_view, 2> kExternalDepthScaleNames{"unknown", "metric"};
/// Whether duplicate points are merged (`depth.fuse_merge_duplicates`).
enum class MergeMode : std::uint8_t {
  kAuto,  ///< in rgbd mode only
  kOn,    ///< always
  kOff,   ///< never
};
/// Names of MergeMode in config, by value.
inline constexpr std::array<std::string_view, 3> kMergeModeNames{"auto", "on", "off"};

/// Options of the `triangulation` backend.
struct TriangulationOptions {
  int max_hamming = 50;
  double ratio = 0.7;
  double epipolar_sigmas = 2.0;
  double min_parallax_deg = 1.0;
  double full_confidence_parallax_deg = 6.0;
  double max_reprojection_sigmas = 2.5;
  int max_level_difference = 1;
  double max_scale_inconsistency = 1.5;
  int min_views = 3;

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
  double min_depth_m = 0.1;
  double max_depth_m = 8.0;

  template <class V>
  void visit(V& v) {
    v.field("min_depth_m", min_depth_m, "closer sensor readings are ignored, m",
            options::Range<double>{0.0, 1000.0});
    v.field("max_depth_m", max_depth_m, "farther sensor readings are ignored, m",
            options::Range<double>{0.0, 1000.0});
  }
};

/// Options of the `external` backend: depth maps read from a folder, one per frame, named by
/// capture time (e.g. a learned model's output recorded offline).
struct ExternalDepthOptions {
  std::string folder;
  std::string format = "auto";
  std::string time_unit = "auto";
  double depth_scale = 5000.0;
  double max_time_diff_s = 0.02;
  ExternalDepthScale scale = ExternalDepthScale::kUnknown;
  double confidence = 1.0;
  double min_depth = 0.0;
  double max_depth = 1.0e6;
  double max_depth_step = 0.03;

  template <class V>
  void visit(V& v) {
    v.field("folder", folder,
            "folder of depth maps, one per frame, named by capture time (<t>.png / <t>.pfm); "
            "indexed once at start; required with depth.backend external");
    v.field("format", format,
            "auto (by extension: .png 16-bit, .pfm float), png16 (16-bit PNG, value / "
            "depth_scale), float32 (single-channel PFM, 'Pf', either byte order)",
            options::OneOf{kExternalDepthFormats});
    v.field("time_unit", time_unit,
            "file names are timestamps: s (decimal seconds, e.g. 1305031102.175304.png, as in "
            "TUM), ns (integer nanoseconds, e.g. 1403636579763555584.png), auto (a name with a "
            "decimal point is seconds, digits only are nanoseconds)",
            options::OneOf{kExternalDepthTimeUnits});
    v.field("depth_scale", depth_scale,
            "png16: stored value per depth unit (TUM 5000 per metre, 1000 for millimetres)",
            options::Range<double>{1e-6, 1e9});
    v.field("max_time_diff_s", max_time_diff_s,
            "a keyframe takes the map with the nearest timestamp within this, s; none: the "
            "keyframe gets no depth (warned, counted in map.depth_missing)",
            options::Range<double>{0.0, 10.0});
    v.field("scale", scale,
            "unknown: depth up to an unknown scale (a monocular network), aligned to the map "
            "with the keyframe's 3D-2D matches; metric: metres (used as is in rgbd mode)",
            options::Names<ExternalDepthScale>{kExternalDepthScaleNames});
    v.field("confidence", confidence,
            "confidence of every depth read from a map (depth.min_confidence gates new points)",
            options::Range<double>{0.0, 1.0});
    v.field("min_depth", min_depth, "closer readings are ignored, in the maps' unit",
            options::Range<double>{0.0, 1e9});
    v.field("max_depth", max_depth, "farther readings are ignored, in the maps' unit",
            options::Range<double>{0.0, 1e9});
    v.field("max_depth_step", max_depth_step,
            "depth is interpolated over the keypoint's 2x2 map pixels; a relative depth step "
            "among them above this marks a depth edge and the reading is refused",
            options::Range<double>{0.0, 100.0});
  }
};

/// Keyframe creation and depth inference.
struct DepthOptions {
  DepthBackend backend = DepthBackend::kAuto;
  int neighbours = 5;
  double min_confidence = 0.2;
  int min_scale_samples = 20;
  int fuse_keyframes = 10;
  double fuse_radius_px = 3.0;
  int fuse_max_hamming = 50;
  double fuse_min_view_cos = 0.5;
  MergeMode fuse_merge_duplicates = MergeMode::kAuto;
  bool align_keypoints = true;
  double align_max_shift_px = 1.5;
  int align_keyframe_images = 8;
  double align_max_rms = 6.0;
  double align_max_anisotropy = 1.3;
  TriangulationOptions triangulation;
  RgbdDepthOptions rgbd;
  PlaneSweepDepthOptions plane_sweep;
  ExternalDepthOptions external;

  template <class V>
  void visit(V& v) {
    v.field("backend", backend,
            "depth inference: auto (rgbd in rgbd mode, else triangulation), triangulation, "
            "rgbd, plane_sweep, external (depth maps from files, depth.external)",
            options::Names<DepthBackend>{kDepthBackendNames});
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
    v.field("fuse_merge_duplicates", fuse_merge_duplicates,
            "a covisible point projected onto a keypoint that already tracks another point, "
            "and matching it, is the same point: merge the two (the one with more observations "
            "stays, if its position reprojects onto every observation of the other), tying the "
            "old and new points of a revisited place together: auto (on in rgbd mode, off "
            "in mono, where the map's scale drifts between them), on, off",
            options::Names<MergeMode>{kMergeModeNames});
    v.field("align_keypoints", align_keypoints,
            "move the keypoint of each map point seen by a new keyframe to where the point's "
            "anchor patch (its appearance in the first keyframe that observed it, warped by the "
            "views' relative pose) aligns best, and a new point's keypoints in older keyframes "
            "likewise, so every keyframe measures the same surface point rather than each its "
            "own detection (map.max_points anchor patches of about 300 bytes are allocated "
            "when on; see docs/keypoint-alignment.md)");
    v.field("align_max_shift_px", align_max_shift_px,
            "an alignment that moves a keypoint farther than this (px of its pyramid level) is "
            "refused and the detection kept",
            options::Range<double>{0.1, 10.0});
    v.field("align_keyframe_images", align_keyframe_images,
            "image pyramids of the most recent keyframes kept (align_keypoints): a new point's "
            "keypoints in older keyframes are aligned to its anchor when their keyframe's image is "
            "still kept (about 0.45 MB each at 640x480)",
            options::Range<int>{1, 64});
    v.field("align_max_rms", align_max_rms,
            "an alignment whose RMS intensity residual (grey levels, brightness offset removed) "
            "stays above this did not find the anchor's surface point: refused, detection kept",
            options::Range<double>{0.0, 255.0});
    v.field("align_max_anisotropy", align_max_anisotropy,
            "an alignment whose predicted warp stretches one direction more than this times "
            "the other (the views see the surface at very different angles, where the anchor's "
            "fronto-parallel model is least right) is refused, detection kept",
            options::Range<double>{1.0, 100.0});
    v.section("triangulation", triangulation, "multi-view triangulation backend (monocular)");
    v.section("rgbd", rgbd, "RGB-D passthrough backend");
    v.section("plane_sweep", plane_sweep,
              "dense plane-sweep stereo backend (keyframe against recent tracked frames)");
    v.section("external", external,
              "external backend: depth maps read from a folder (e.g. a learned model's output "
              "recorded offline), sampled at the keypoints");
  }
};

}  // namespace mer::depth
