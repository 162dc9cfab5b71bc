#include "features/opencv_orb_extractor.h"

#include <cmath>
#include <cstring>
#include <numbers>

#include "core/assert.h"

namespace mer::features {
namespace {
constexpr int kOrbWtaK = 2;        // binary tests compare 2 points (256-bit descriptors)
constexpr int kOrbPatchSize = 31;  // ORB's patch, px
constexpr int kOrbFirstLevel = 0;  // the input image is pyramid level 0
constexpr float kRadPerDeg = std::numbers::pi_v<float> / 180.0F;
}  // namespace

OpenCvOrbExtractor::OpenCvOrbExtractor(const ExtractorOptions& opts, int width, int height)
    : width_(width), height_(height) {
  MER_ASSERT(validate_extractor_options(opts, width, height).is_ok(),
             "OpenCvOrbExtractor: invalid options (call validate_extractor_options first)");
  orb_ = cv::ORB::create(opts.num_features, static_cast<float>(opts.scale_factor), opts.num_levels,
                         opts.edge_threshold, kOrbFirstLevel, kOrbWtaK, cv::ORB::HARRIS_SCORE,
                         kOrbPatchSize, opts.fast_threshold);
  for (int l = 0; l < opts.num_levels; ++l)
    scales_.push_back(static_cast<float>(std::pow(opts.scale_factor, l)));
  keypoints_.reserve(static_cast<std::size_t>(opts.num_features));
  descriptors_.reserve(static_cast<std::size_t>(opts.num_features));
}

float OpenCvOrbExtractor::level_scale(int level) const {
  MER_ASSERT(level >= 0 && level < num_levels(), "level out of range");
  return scales_[static_cast<std::size_t>(level)];
}

float OpenCvOrbExtractor::level_sigma2(int level) const {
  const float s = level_scale(level);
  return s * s;
}

int OpenCvOrbExtractor::extract(const cv::Mat& gray) {
  MER_ASSERT(gray.type() == CV_8UC1 && gray.cols == width_ && gray.rows == height_,
             "OpenCvOrbExtractor::extract: image type or size differs from construction");
  cv_keypoints_.clear();
  orb_->detectAndCompute(gray, cv::noArray(), cv_keypoints_, cv_descriptors_);
  keypoints_.clear();
  descriptors_.clear();
  MER_ASSERT(
      cv_descriptors_.empty() || (cv_descriptors_.type() == CV_8UC1 &&
                                  cv_descriptors_.cols == static_cast<int>(sizeof(Descriptor)) &&
                                  cv_descriptors_.rows == static_cast<int>(cv_keypoints_.size())),
      "cv::ORB returned unexpected descriptors");
  for (std::size_t i = 0; i < cv_keypoints_.size(); ++i) {
    const cv::KeyPoint& k = cv_keypoints_[i];
    Keypoint kp;
    kp.x = k.pt.x;
    kp.y = k.pt.y;
    kp.angle_rad = k.angle * kRadPerDeg;
    kp.response = k.response;
    kp.level = static_cast<std::int8_t>(k.octave);
    kp.scale = level_scale(k.octave);
    keypoints_.push_back(kp);
    Descriptor d{};
    std::memcpy(d.data(), cv_descriptors_.ptr<std::uint8_t>(static_cast<int>(i)), sizeof(d));
    descriptors_.push_back(d);
  }
  return static_cast<int>(keypoints_.size());
}

}  // namespace mer::features
