#pragma once
// Test helpers: temporary folders, file writers, dataset fixtures and the shared data path.

#include <cstdint>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <string>
#include <vector>

#include <gtest/gtest.h>
#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>

#include "core/pose.h"

namespace mer::hal::test {

/// A fresh folder under the system temp dir, removed at destruction.
class TempDir {
 public:
  TempDir() {
    std::string tmpl = (std::filesystem::temp_directory_path() / "mer_replay_XXXXXX").string();
    char* p = ::mkdtemp(tmpl.data());
    EXPECT_NE(p, nullptr);
    path_ = tmpl;
  }
  ~TempDir() {
    std::error_code ec;
    std::filesystem::remove_all(path_, ec);
  }
  TempDir(const TempDir&) = delete;
  TempDir& operator=(const TempDir&) = delete;
  /// The folder.
  const std::string& path() const { return path_; }
  /// path() + "/" + rel.
  std::string operator/(const std::string& rel) const { return path_ + "/" + rel; }

 private:
  std::string path_;
};

/// Writes `text` to `path`, creating parent folders.
inline void write_file(const std::string& path, const std::string& text) {
  std::filesystem::create_directories(std::filesystem::path(path).parent_path());
  std::ofstream out(path, std::ios::binary);
  out << text;
}

/// Writes an image (PNG) to `path`, creating parent folders.
inline void write_png(const std::string& path, const cv::Mat& img) {
  std::filesystem::create_directories(std::filesystem::path(path).parent_path());
  ASSERT_TRUE(cv::imwrite(path, img)) << path;
}

/// A deterministic random image.
inline cv::Mat random_image(int w, int h, int type, std::uint64_t seed) {
  cv::Mat m(h, w, type);
  cv::RNG rng(seed);
  rng.fill(m, cv::RNG::UNIFORM, 0, CV_MAT_DEPTH(type) == CV_16U ? 60000 : 256);
  return m;
}

/// The folder holding kitti_clip1/ etc.: $MER_SHARED_DIR (or its data/), else
/// $MER_SOURCE_DIR/../shared/data. Empty when not found.
inline std::string shared_data_dir() {
  namespace fs = std::filesystem;
  if (const char* s = std::getenv("MER_SHARED_DIR"); s != nullptr && *s != '\0') {
    if (fs::is_directory(fs::path(s) / "data" / "kitti_clip1"))
      return (fs::path(s) / "data").string();
    if (fs::is_directory(fs::path(s) / "kitti_clip1")) return s;
  }
  if (const char* s = std::getenv("MER_SOURCE_DIR"); s != nullptr && *s != '\0') {
    const fs::path d = fs::path(s) / ".." / "shared" / "data";
    if (fs::is_directory(d)) return d.lexically_normal().string();
  }
  return {};
}

/// Rotation about z by `a` radians plus a translation.
inline SE3d pose_z(double a, double x, double y, double z) {
  SE3d T = SE3d::Identity();
  T.linear() = Eigen::AngleAxisd(a, Eigen::Vector3d::UnitZ()).toRotationMatrix();
  T.translation() = Eigen::Vector3d(x, y, z);
  return T;
}

/// Writes a KITTI folder with `n` frames (w x h gray), times at 10 Hz, `n_poses` poses
/// (pose i: rotation 0.01 i about z, translation (i, 0, 2 i)).
inline void make_kitti(const std::string& dir, int n, int w, int h, int n_poses) {
  write_file(dir + "/calib.txt",
             "P0: 500.0 0 320.5 0 0 510.0 240.25 0 0 0 1 0\n"
             "P1: 500.0 0 320.5 -100 0 510.0 240.25 0 0 0 1 0\n");
  std::string times;
  std::string poses;
  char buf[64];
  for (int i = 0; i < n; ++i) {
    std::snprintf(buf, sizeof buf, "%06d.png", i);
    write_png(dir + "/image_0/" + buf,
              random_image(w, h, CV_8UC1, static_cast<std::uint64_t>(i) + 1));
    times += std::to_string(0.1 * i) + "\n";
  }
  for (int i = 0; i < n_poses; ++i) {
    const SE3d T = pose_z(0.01 * i, i, 0.0, 2.0 * i);
    const auto& r = T.linear();
    const auto& t = T.translation();
    for (int row = 0; row < 3; ++row) {
      for (int c = 0; c < 3; ++c) poses += std::to_string(r(row, c)) + " ";
      poses += std::to_string(t(row)) + (row == 2 ? "\n" : " ");
    }
  }
  write_file(dir + "/times.txt", times);
  if (n_poses > 0) write_file(dir + "/poses.txt", poses);
}

}  // namespace mer::hal::test
