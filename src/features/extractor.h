#pragma once
/// @file extractor.h
/// Keypoint detection + binary description behind one interface, so the tracking thread
/// does not care which backend runs:
/// - `orb` (OrbExtractor, orb_extractor.h): this project's ORB — FAST-9 on an image
///   pyramid with grid bucketing, intensity-centroid orientation and steered rBRIEF-style
///   descriptors. No heap allocation per extract() after construction; uses no OpenCV
///   function (and so no OpenCV thread pool) at run time.
/// - `opencv_orb` (OpenCvOrbExtractor, opencv_orb_extractor.h): cv::ORB converted to our
///   types, for comparison. It allocates on every call and may use OpenCV's thread pool.
///
/// An extractor instance is not thread-safe: use one per thread.

#include <array>
#include <cstdint>
#include <memory>
#include <span>
#include <string>
#include <string_view>

#include <opencv2/core/mat.hpp>

#include "core/options.h"
#include "core/status.h"
#include "features/keypoint.h"

namespace mer::features {

/// Feature extractor implementation (ExtractorOptions::backend).
enum class ExtractorBackend : std::uint8_t {
  kOrb,        ///< allocation-free ORB of this project
  kOpenCvOrb,  ///< cv::ORB (allocates; for comparison)
};
/// Names of ExtractorBackend in config, by value.
inline constexpr std::array<std::string_view, 2> kExtractorBackendNames = {"orb", "opencv_orb"};

/// Options of the feature extractor (config section `tracking.extractor`).
struct ExtractorOptions {
  ExtractorBackend backend = ExtractorBackend::kOrb;
  int num_features = 1000;
  double scale_factor = 1.2;
  int num_levels = 8;
  int fast_threshold = 20;
  int min_fast_threshold = 7;
  int grid_cols = 8;
  int grid_rows = 6;
  int edge_threshold = 19;
  bool subpixel = false;

  template <class V>
  void visit(V& v) {
    v.field("backend", backend,
            "feature backend: orb (this project's, allocation-free) or opencv_orb (cv::ORB, "
            "allocates per frame; for comparison)",
            options::Names<ExtractorBackend>{kExtractorBackendNames});
    v.field("num_features", num_features, "features per frame, over all pyramid levels",
            options::Range<int>{1, 100000});
    v.field("scale_factor", scale_factor, "image pyramid scale between consecutive levels",
            options::Range<double>{1.01, 2.0});
    v.field("num_levels", num_levels, "image pyramid levels", options::Range<int>{1, 16});
    v.field("fast_threshold", fast_threshold, "FAST intensity threshold, grey levels",
            options::Range<int>{1, 254});
    v.field("min_fast_threshold", min_fast_threshold,
            "lower FAST threshold retried in grid cells where nothing was found "
            "(<= fast_threshold; equal: no retry)",
            options::Range<int>{1, 254});
    v.field("grid_cols", grid_cols,
            "bucketing grid columns at level 0 (fewer at coarser levels), spreads features",
            options::Range<int>{1, 64});
    v.field("grid_rows", grid_rows,
            "bucketing grid rows at level 0 (fewer at coarser levels), spreads features",
            options::Range<int>{1, 64});
    v.field("edge_threshold", edge_threshold,
            "image border without features, px (>= 16 so the radius-15 descriptor patch fits)",
            options::Range<int>{16, 128});
    v.field("subpixel", subpixel,
            "orb backend: place each keypoint at the peak of a parabola through the FAST scores "
            "of its row and column neighbours (within half a pixel of its level; opencv_orb "
            "ignores it)");
  }
};

/// Keypoint detector + descriptor for images of one fixed size.
class Extractor {
 public:
  virtual ~Extractor() = default;

  /// Detects keypoints and computes descriptors of `gray` (CV_8UC1 of the size given at
  /// construction). Results stay valid until the next call. Returns the number of keypoints.
  virtual int extract(const cv::Mat& gray) = 0;

  /// Keypoints of the last extract(), level-0 pixel coordinates.
  virtual std::span<const Keypoint> keypoints() const = 0;

  /// Descriptors of the last extract(), one per keypoint (same order).
  virtual std::span<const Descriptor> descriptors() const = 0;

  /// Backend name ("orb", "opencv_orb").
  virtual const char* name() const = 0;

  /// scale_factor^level, and its square (for per-level noise sigma of reprojection errors).
  virtual float level_scale(int level) const = 0;
  virtual float level_sigma2(int level) const = 0;

  /// Pyramid levels.
  virtual int num_levels() const = 0;
};

/// Checks `opts` (and that the pyramid fits a `width` x `height` image); the error names the
/// offending key (`tracking.extractor.<key>`).
Status validate_extractor_options(const ExtractorOptions& opts, int width, int height);

/// Builds the backend named in opts.backend for width x height images; error Status naming
/// the key on a bad option.
Result<std::unique_ptr<Extractor>> make_extractor(const ExtractorOptions& opts, int width,
                                                  int height);

}  // namespace mer::features
