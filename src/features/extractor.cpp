#include "features/extractor.h"

#include <cmath>
#include <string>

#include "features/opencv_orb_extractor.h"
#include "features/orb_extractor.h"

namespace mer::features {
namespace {
constexpr const char* kPrefix = "tracking.extractor.";
// Smallest detection region (level size minus both borders) of the coarsest level, px:
// a few FAST corners must fit.
constexpr int kMinLevelRegion = 8;
// Largest image side: keypoint coordinates are stored in 16 bits inside the extractor.
constexpr int kMaxImageSide = 16384;
}  // namespace

Status validate_extractor_options(const ExtractorOptions& opts, int width, int height) {
  ExtractorOptions copy = opts;
  options::Validator v(kPrefix);
  copy.visit(v);
  if (!v.status().is_ok()) return v.status();
  if (opts.min_fast_threshold > opts.fast_threshold) {
    return invalid_argument(std::string("key '") + kPrefix + "min_fast_threshold': expected <= " +
                            "fast_threshold (" + std::to_string(opts.fast_threshold) + "), found " +
                            std::to_string(opts.min_fast_threshold));
  }
  if (width <= 0 || height <= 0 || width > kMaxImageSide || height > kMaxImageSide) {
    return invalid_argument("feature extractor: image size " + std::to_string(width) + "x" +
                            std::to_string(height) + " outside 1.." +
                            std::to_string(kMaxImageSide) + " px per side");
  }
  const double coarsest = std::pow(opts.scale_factor, opts.num_levels - 1);
  const int cw = static_cast<int>(std::lround(width / coarsest));
  const int ch = static_cast<int>(std::lround(height / coarsest));
  const int need = 2 * opts.edge_threshold + kMinLevelRegion;
  if (cw < need || ch < need) {
    return invalid_argument(
        std::string("key '") + kPrefix + "num_levels': " + std::to_string(opts.num_levels) +
        " levels at scale_factor " + options::format_value(opts.scale_factor) +
        " make the coarsest level of the " + std::to_string(width) + "x" + std::to_string(height) +
        " image " + std::to_string(cw) + "x" + std::to_string(ch) + " px; with edge_threshold " +
        std::to_string(opts.edge_threshold) + " every level needs at least " +
        std::to_string(need) + " px per side");
  }
  return Status::ok();
}

Result<std::unique_ptr<Extractor>> make_extractor(const ExtractorOptions& opts, int width,
                                                  int height) {
  if (Status s = validate_extractor_options(opts, width, height); !s.is_ok()) return s;
  std::unique_ptr<Extractor> e;
  if (opts.backend == ExtractorBackend::kOrb) {
    e = std::make_unique<OrbExtractor>(opts, width, height);
  } else {
    e = std::make_unique<OpenCvOrbExtractor>(opts, width, height);
  }
  return e;
}

}  // namespace mer::features
