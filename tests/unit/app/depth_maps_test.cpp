// The depth maps of depth.backend: external, from real files: the folder is opened and
// checked at start (errors name depth.external.folder), and the external backend samples
// the right file at the keypoints (16-bit PNG and PFM, nanosecond and second names, a map at
// half the image resolution, a keyframe without a map).
#include "app/depth_maps.h"

#include <unistd.h>

#include <filesystem>
#include <fstream>
#include <string>
#include <vector>

#include <gtest/gtest.h>
#include <opencv2/imgcodecs.hpp>

#include "depth/external_depth.h"
#include "hal/replay/pfm.h"
#include "support/run_command.h"

namespace mer::app {
namespace {

namespace fs = std::filesystem;

constexpr int kWidth = 80;
constexpr int kHeight = 60;
constexpr double kMmPerM = 1000.0;

class TempFolder {
 public:
  TempFolder() {
    std::string tmpl = (fs::temp_directory_path() / "mer_depth_maps_XXXXXX").string();
    EXPECT_NE(::mkdtemp(tmpl.data()), nullptr);
    path_ = tmpl;
  }
  ~TempFolder() {
    std::error_code ec;
    fs::remove_all(path_, ec);
  }
  TempFolder(const TempFolder&) = delete;
  TempFolder& operator=(const TempFolder&) = delete;
  std::string operator/(const std::string& rel) const { return (fs::path(path_) / rel).string(); }
  const std::string& path() const { return path_; }

 private:
  std::string path_;
};

/// Depth of the test scene at image pixel (x, y), m: a gentle slope.
double scene_depth(double x, double y) {
  return 1.5 + 0.004 * x + 0.002 * y;
}

/// The scene's depth map at `w` x `h` (a plain resize of the kWidth x kHeight image), plus
/// `offset` metres.
cv::Mat scene_map(int w, int h, double offset) {
  cv::Mat m(h, w, CV_32FC1);
  const double sx = static_cast<double>(kWidth) / w;
  const double sy = static_cast<double>(kHeight) / h;
  for (int v = 0; v < h; ++v) {
    for (int u = 0; u < w; ++u) {
      m.at<float>(v, u) =
          static_cast<float>(scene_depth((u + 0.5) * sx - 0.5, (v + 0.5) * sy - 0.5) + offset);
    }
  }
  return m;
}

void write_pfm(const std::string& path, const cv::Mat& m) {
  std::ofstream out(path, std::ios::binary);
  out << hal::encode_pfm(m);
}

void write_png_mm(const std::string& path, const cv::Mat& m) {
  cv::Mat mm;
  m.convertTo(mm, CV_16UC1, kMmPerM);
  ASSERT_TRUE(cv::imwrite(path, mm)) << path;
}

depth::DepthOptions external(const std::string& folder) {
  depth::DepthOptions o;
  o.backend = depth::DepthBackend::kExternal;
  o.external.folder = folder;
  o.external.depth_scale = kMmPerM;
  return o;
}

TEST(DepthMaps, OtherBackendsNeedNone) {
  depth::DepthOptions o;
  for (const char* b : {"auto", "triangulation", "rgbd", "plane_sweep"}) {
    ASSERT_TRUE(options::parse_name(b, depth::kDepthBackendNames, o.backend)) << b;
    auto r = open_depth_maps(o);
    ASSERT_TRUE(r.is_ok()) << b;
    EXPECT_EQ(r.value(), nullptr) << b;
  }
}

TEST(DepthMaps, AMissingEmptyOrBadFolderIsAConfigErrorNamingTheKey) {
  TempFolder d;
  std::vector<depth::DepthOptions> bad{external(""), external(d / "missing"), external(d.path())};
  fs::create_directories(d / "eight_bit");
  ASSERT_TRUE(cv::imwrite(d / "eight_bit/1.png", cv::Mat(4, 4, CV_8UC1, cv::Scalar(9))));
  bad.push_back(external(d / "eight_bit"));
  for (const auto& o : bad) {
    auto r = open_depth_maps(o);
    ASSERT_FALSE(r.is_ok()) << o.external.folder;
    EXPECT_EQ(r.status().code(), StatusCode::kInvalidArgument);
    EXPECT_NE(r.status().message().find("depth.external.folder"), std::string::npos)
        << r.status().message();
  }
}

TEST(DepthMaps, KeypointDepthFromRealFiles) {
  TempFolder d;
  // Nanosecond names: a PFM at 0.1 s, a half-resolution PNG (mm) at 0.2 s, each offset by
  // its time so the map used is visible.
  write_pfm(d / "100000000.pfm", scene_map(kWidth, kHeight, 0.1));
  write_png_mm(d / "200000000.png", scene_map(kWidth / 2, kHeight / 2, 0.2));
  auto maps = open_depth_maps(external(d.path()));
  ASSERT_TRUE(maps.is_ok()) << maps.status().message();
  ASSERT_NE(maps.value(), nullptr);
  EXPECT_EQ(maps.value()->timestamps().size(), 2U);

  depth::ExternalDepthOptions eo = external(d.path()).external;
  depth::ExternalDepth backend(eo, *maps.value());
  const cv::Mat gray(kHeight, kWidth, CV_8UC1, cv::Scalar(100));
  std::vector<features::Keypoint> kps;
  for (const auto& [x, y] : {std::pair{12.0F, 9.0F}, {40.5F, 30.25F}, {70.2F, 50.9F}}) {
    features::Keypoint kp;
    kp.x = x;
    kp.y = y;
    kps.push_back(kp);
  }
  const std::size_t n = kps.size();
  std::vector<float> depth(n), conf(n);
  std::vector<std::uint32_t> sv(n), sk(n);
  depth::DepthRequest req;
  req.keypoints = kps;
  req.gray = &gray;
  for (const auto& [t_ns, offset, tol] :
       {std::tuple{105'000'000LL, 0.1, 1e-5}, {190'000'000LL, 0.2, 1e-3}}) {
    req.t_ns = t_ns;
    depth::DepthResult out{depth, conf, sv, sk, 0, {}, false, {}};
    ASSERT_TRUE(backend.infer(req, out).is_ok()) << t_ns;
    ASSERT_EQ(out.num_valid, static_cast<int>(n)) << t_ns;
    for (std::size_t i = 0; i < n; ++i) {
      // PNG: millimetre quantization.
      EXPECT_NEAR(depth[i], scene_depth(kps[i].x, kps[i].y) + offset, tol) << t_ns << " " << i;
    }
  }
  req.t_ns = 500'000'000;  // 0.3 s from the last map
  depth::DepthResult out{depth, conf, sv, sk, 0, {}, false, {}};
  const Status s = backend.infer(req, out);
  EXPECT_FALSE(s.is_ok());
  EXPECT_TRUE(out.input_missing);
  EXPECT_NE(s.message().find(d.path()), std::string::npos) << s.message();
}

TEST(DepthMaps, MerSlamRefusesAMissingFolderAtStart) {
  TempFolder d;
  const std::string cfg = d / "external.yaml";
  {
    std::ofstream f(cfg);
    f << "depth:\n  backend: external\n  external:\n    folder: \"" << (d / "none") << "\"\n";
  }
  const auto r = mer::testing::run_command(mer::testing::quote(MER_SLAM_EXE) +
                                           " --lockstep --max-frames 5 --quiet --config " +
                                           mer::testing::quote(cfg));
  EXPECT_EQ(r.exit_code, 2) << r.output;
  EXPECT_NE(r.output.find("depth.external.folder"), std::string::npos) << r.output;
  EXPECT_NE(r.output.find(d / "none"), std::string::npos) << r.output;
}

}  // namespace
}  // namespace mer::app
