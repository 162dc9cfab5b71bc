#pragma once
/// @file opencv_orb_extractor.h
/// The `opencv_orb` backend: cv::ORB (features2d) converted to our types, kept for
/// comparison with the `orb` backend. It ALLOCATES on every extract() (cv::ORB builds its
/// pyramid, keypoint vectors and descriptor matrix per call) and may run parts of its work
/// on OpenCV's thread pool (cv::setNumThreads governs that; this class does not change it).
/// Not for the tracking thread's steady state.
///
/// Mapping of the options: num_features, scale_factor, num_levels, edge_threshold and
/// fast_threshold go to cv::ORB (patch size 31, Harris ranking, WTA_K 2); cv::ORB has no
/// bucketing grid nor retry threshold, so grid_cols, grid_rows and min_fast_threshold are
/// ignored. OpenCV's angle (degrees) is converted to radians, its octave to our level.

#include <vector>

#include <opencv2/features2d.hpp>

#include "features/extractor.h"

namespace mer::features {

/// cv::ORB behind the Extractor interface (allocates per call).
class OpenCvOrbExtractor final : public Extractor {
 public:
  /// `opts` must be valid (validate_extractor_options).
  OpenCvOrbExtractor(const ExtractorOptions& opts, int width, int height);

  int extract(const cv::Mat& gray) override;
  std::span<const Keypoint> keypoints() const override { return keypoints_; }
  std::span<const Descriptor> descriptors() const override { return descriptors_; }
  const char* name() const override { return "opencv_orb"; }
  float level_scale(int level) const override;
  float level_sigma2(int level) const override;
  int num_levels() const override { return static_cast<int>(scales_.size()); }

 private:
  int width_;
  int height_;
  cv::Ptr<cv::ORB> orb_;
  std::vector<float> scales_;
  std::vector<cv::KeyPoint> cv_keypoints_;
  cv::Mat cv_descriptors_;
  std::vector<Keypoint> keypoints_;
  std::vector<Descriptor> descriptors_;
};

}  // namespace mer::features
