// Dataset folder loaders on generated fixtures: exact values (gray conversion, depth in
// metres, interpolated ground truth, calibration) and every bad-input case (error at open
// naming file:line, or a counted skip naming the image).
#include <cmath>
#include <cstdio>
#include <numbers>

#include <gtest/gtest.h>
#include <opencv2/imgproc.hpp>

#include "hal/replay/euroc_loader.h"
#include "hal/replay/kitti_loader.h"
#include "hal/replay/tum_loader.h"
#include "replay_fixtures.h"

namespace mer::hal {
namespace {

using test::pose_z;
using test::random_image;
using test::TempDir;
using test::write_file;
using test::write_png;

constexpr int kW = 64;
constexpr int kH = 48;
constexpr std::int64_t kMaxDt = 20'000'000;  // 0.02 s
constexpr double kDepthScale = 5000.0;

bool has(const std::string& text, const std::string& part) {
  return text.find(part) != std::string::npos;
}

double yaw(const SE3d& T) {
  return std::atan2(T.linear()(1, 0), T.linear()(0, 0));
}

std::string fmt(const char* f, double v) {
  char buf[64];
  std::snprintf(buf, sizeof buf, f, v);
  return buf;
}

std::string tum_pose_line(double t, const SE3d& T) {
  const Eigen::Quaterniond q(T.linear());
  std::string s = fmt("%.6f", t);
  for (double v : {T.translation().x(), T.translation().y(), T.translation().z(), q.x(), q.y(),
                   q.z(), q.w()}) {
    s += " " + fmt("%.12f", v);
  }
  return s + "\n";
}

CalibrationOptions calib() {
  CalibrationOptions c;
  c.fx = 50.0;
  c.fy = 51.0;
  c.cx = 31.5;
  c.cy = 23.5;
  c.k1 = 0.01;
  return c;
}

Frame make_frame(bool depth) {
  Frame f;
  f.gray = cv::Mat(kH, kW, CV_8UC1);
  if (depth) f.depth = cv::Mat(kH, kW, CV_32FC1);
  return f;
}

double frame_time(int i) {
  return 100.0 + 0.05 * i;
}

// TUM folder: color PNGs (even frames) and gray PNGs (odd), 16-bit depth 5 ms after each
// frame, ground truth at t - 10 ms (yaw 0.1 i, x = i) and t + 10 ms (yaw 0.1 i + 0.02,
// x = i + 0.2), so the pose at t is yaw 0.1 i + 0.01, x = i + 0.1.
void make_tum(const std::string& dir, int n) {
  std::string rgb = "# color images\n# timestamp filename\n";
  std::string depth = "# depth maps\n";
  std::string gt = "# ground truth trajectory\n# timestamp tx ty tz qx qy qz qw\n";
  for (int i = 0; i < n; ++i) {
    const double t = frame_time(i);
    const std::string name = fmt("%.6f", t) + ".png";
    const int type = i % 2 == 0 ? CV_8UC3 : CV_8UC1;
    write_png(dir + "/rgb/" + name, random_image(kW, kH, type, static_cast<std::uint64_t>(i) + 10));
    write_png(dir + "/depth/" + name,
              random_image(kW, kH, CV_16UC1, static_cast<std::uint64_t>(i) + 100));
    rgb += fmt("%.6f", t) + " rgb/" + name + "\n";
    depth += fmt("%.6f", t + 0.005) + " depth/" + name + "\n";
    gt += tum_pose_line(t - 0.01, pose_z(0.1 * i, i, 0.0, 1.0));
    gt += tum_pose_line(t + 0.01, pose_z(0.1 * i + 0.02, i + 0.2, 0.0, 1.0));
  }
  write_file(dir + "/rgb.txt", rgb);
  write_file(dir + "/depth.txt", depth);
  write_file(dir + "/groundtruth.txt", gt);
}

// ---- TUM ------------------------------------------------------------------------------

TEST(TumLoader, DecodesGrayDepthAndInterpolatedGroundTruthExactly) {
  TempDir dir;
  make_tum(dir.path(), 4);
  TumLoader loader(dir.path(), calib(), true, kDepthScale, kMaxDt);
  ASSERT_TRUE(loader.open().is_ok());
  ASSERT_EQ(loader.size(), 4U);
  EXPECT_TRUE(loader.has_depth());
  EXPECT_TRUE(loader.has_ground_truth());
  EXPECT_EQ(loader.ground_truth().poses.size(), 8U);
  const CameraIntrinsics& k = loader.intrinsics();
  EXPECT_EQ(k.width, kW);
  EXPECT_EQ(k.height, kH);
  EXPECT_EQ(k.fx, 50.0);
  EXPECT_EQ(k.fy, 51.0);
  EXPECT_EQ(k.cx, 31.5);
  EXPECT_EQ(k.dist[0], 0.01);
  EXPECT_NEAR(loader.nominal_fps(), 20.0, 1e-9);
  EXPECT_TRUE(has(loader.describe(), "tum:" + dir.path()));

  Frame f = make_frame(true);
  const uchar* gray_buffer = f.gray.data;
  for (int i = 0; i < 4; ++i) {
    Status st;
    ASSERT_EQ(loader.load(static_cast<std::size_t>(i), f, st), LoadStatus::kOk) << st.message();
    EXPECT_EQ(f.gray.data, gray_buffer) << "decoded in place, no reallocation";
    EXPECT_EQ(f.seq, static_cast<std::uint64_t>(i));
    EXPECT_EQ(f.t_ns, 100'000'000'000LL + 50'000'000LL * i);
    cv::Mat expected_gray =
        random_image(kW, kH, i % 2 == 0 ? CV_8UC3 : CV_8UC1, static_cast<std::uint64_t>(i) + 10);
    if (i % 2 == 0) cv::cvtColor(expected_gray, expected_gray, cv::COLOR_BGR2GRAY);
    EXPECT_EQ(cv::norm(f.gray, expected_gray, cv::NORM_INF), 0.0);
    const cv::Mat raw = random_image(kW, kH, CV_16UC1, static_cast<std::uint64_t>(i) + 100);
    for (int v = 0; v < kH; v += 7) {
      for (int u = 0; u < kW; u += 5) {
        EXPECT_NEAR(f.depth.at<float>(v, u), raw.at<std::uint16_t>(v, u) / 5000.0, 1e-6);
      }
    }
    ASSERT_TRUE(f.has_ground_truth);
    EXPECT_NEAR(yaw(f.T_w_c_gt), 0.1 * i + 0.01, 1e-9);
    EXPECT_NEAR(f.T_w_c_gt.translation().x(), i + 0.1, 1e-9);
  }
  Status st;
  EXPECT_EQ(loader.load(4, f, st), LoadStatus::kEndOfStream);
}

TEST(TumLoader, MonoModeIgnoresDepthAndGroundTruthIsOptional) {
  TempDir dir;
  make_tum(dir.path(), 3);
  std::filesystem::remove(dir / "depth.txt");
  std::filesystem::remove(dir / "groundtruth.txt");
  TumLoader loader(dir.path(), calib(), false, kDepthScale, kMaxDt);
  ASSERT_TRUE(loader.open().is_ok());
  EXPECT_FALSE(loader.has_depth());
  EXPECT_FALSE(loader.has_ground_truth());
  Frame f = make_frame(false);
  Status st;
  ASSERT_EQ(loader.load(0, f, st), LoadStatus::kOk) << st.message();
  EXPECT_FALSE(f.has_ground_truth);
}

TEST(TumLoader, FramesOutsideTheGroundTruthHaveNone) {
  TempDir dir;
  make_tum(dir.path(), 3);
  // Only the first frame's bracket: later frames get no pose (no extrapolation).
  write_file(dir / "groundtruth.txt",
             tum_pose_line(99.99, pose_z(0, 0, 0, 0)) + tum_pose_line(100.01, pose_z(0, 0, 0, 0)));
  TumLoader loader(dir.path(), calib(), false, kDepthScale, kMaxDt);
  ASSERT_TRUE(loader.open().is_ok());
  EXPECT_TRUE(loader.frames()[0].has_ground_truth);
  EXPECT_FALSE(loader.frames()[1].has_ground_truth);
  EXPECT_FALSE(loader.frames()[2].has_ground_truth);
}

TEST(TumLoader, NoIntrinsicsIsAClearError) {
  TempDir dir;
  make_tum(dir.path(), 2);
  TumLoader loader(dir.path(), CalibrationOptions{}, false, kDepthScale, kMaxDt);
  const Status s = loader.open();
  ASSERT_EQ(s.code(), StatusCode::kInvalidArgument);
  EXPECT_TRUE(has(s.message(), "--intrinsics")) << s.message();
  EXPECT_TRUE(has(s.message(), "camera.calibration")) << s.message();
}

TEST(TumLoader, RgbdFrameWithoutDepthIsASkip) {
  TempDir dir;
  make_tum(dir.path(), 3);
  // Frame 1's depth is 30 ms away: beyond the 20 ms association bound.
  write_file(dir / "depth.txt",
             "100.005 depth/100.000000.png\n100.080 depth/100.050000.png\n"
             "100.105 depth/100.100000.png\n");
  TumLoader loader(dir.path(), calib(), true, kDepthScale, kMaxDt);
  ASSERT_TRUE(loader.open().is_ok());
  Frame f = make_frame(true);
  Status st;
  EXPECT_EQ(loader.load(0, f, st), LoadStatus::kOk) << st.message();
  EXPECT_EQ(loader.load(1, f, st), LoadStatus::kSkip);
  EXPECT_TRUE(has(st.message(), "no depth image")) << st.message();
  EXPECT_TRUE(has(st.message(), "rgb.txt:4")) << st.message();
  EXPECT_EQ(loader.load(2, f, st), LoadStatus::kOk) << st.message();
}

TEST(TumLoader, RgbdWithoutDepthListIsAnError) {
  TempDir dir;
  make_tum(dir.path(), 2);
  std::filesystem::remove(dir / "depth.txt");
  TumLoader loader(dir.path(), calib(), true, kDepthScale, kMaxDt);
  const Status s = loader.open();
  ASSERT_EQ(s.code(), StatusCode::kInputError);
  EXPECT_TRUE(has(s.message(), "depth.txt")) << s.message();
}

TEST(TumLoader, BadDepthImageIsASkipNamingIt) {
  TempDir dir;
  make_tum(dir.path(), 2);
  write_png(dir / "depth/100.050000.png", random_image(kW, kH, CV_8UC1, 3));  // 8-bit
  TumLoader loader(dir.path(), calib(), true, kDepthScale, kMaxDt);
  ASSERT_TRUE(loader.open().is_ok());
  Frame f = make_frame(true);
  Status st;
  EXPECT_EQ(loader.load(1, f, st), LoadStatus::kSkip);
  EXPECT_TRUE(has(st.message(), "depth/100.050000.png")) << st.message();
  EXPECT_TRUE(has(st.message(), "16-bit")) << st.message();
}

// ---- bad input shared by the folder loaders --------------------------------------------

TEST(FolderLoaders, MissingFolderIsAnErrorNamingIt) {
  const std::string missing = "/no/such/dataset";
  TumLoader tum(missing, calib(), false, kDepthScale, kMaxDt);
  EurocLoader euroc(missing, {}, kMaxDt);
  KittiLoader kitti(missing, {});
  for (FrameLoader* l : std::initializer_list<FrameLoader*>{&tum, &euroc, &kitti}) {
    const Status s = l->open();
    ASSERT_EQ(s.code(), StatusCode::kInputError);
    EXPECT_TRUE(has(s.message(), missing)) << s.message();
    EXPECT_TRUE(has(s.message(), "not found")) << s.message();
  }
}

TEST(FolderLoaders, MissingIndexFilesAreErrorsNamingThem) {
  {
    TempDir dir;
    make_tum(dir.path(), 2);
    std::filesystem::remove(dir / "rgb.txt");
    const Status s = TumLoader(dir.path(), calib(), false, kDepthScale, kMaxDt).open();
    EXPECT_TRUE(has(s.message(), dir / "rgb.txt")) << s.message();
  }
  for (const char* file : {"times.txt", "calib.txt"}) {
    TempDir dir;
    test::make_kitti(dir.path(), 2, kW, kH, 2);
    std::filesystem::remove(dir / file);
    const Status s = KittiLoader(dir.path(), {}).open();
    ASSERT_EQ(s.code(), StatusCode::kInputError);
    EXPECT_TRUE(has(s.message(), dir / file)) << s.message();
  }
}

TEST(FolderLoaders, MissingCorruptTruncatedAndWrongSizeImagesAreSkips) {
  TempDir dir;
  test::make_kitti(dir.path(), 6, kW, kH, 0);
  std::filesystem::remove(dir / "image_0/000001.png");
  write_file(dir / "image_0/000002.png", "this is not a PNG file");
  {
    std::ifstream in(dir / "image_0/000003.png", std::ios::binary);
    std::string bytes((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
    write_file(dir / "image_0/000003.png", bytes.substr(0, bytes.size() / 2));
  }
  write_png(dir / "image_0/000004.png", random_image(kW + 2, kH, CV_8UC1, 9));
  KittiLoader loader(dir.path(), {});
  ASSERT_TRUE(loader.open().is_ok());
  Frame f = make_frame(false);
  Status st;
  EXPECT_EQ(loader.load(0, f, st), LoadStatus::kOk);
  const std::pair<int, const char*> cases[] = {{1, "missing"},
                                               {2, "unreadable"},
                                               {3, "unreadable"},
                                               {4, "image is 66x48, the sequence is 64x48"}};
  for (const auto& [i, why] : cases) {
    char name[32];
    std::snprintf(name, sizeof name, "image_0/%06d.png", i);
    EXPECT_EQ(loader.load(static_cast<std::size_t>(i), f, st), LoadStatus::kSkip) << name;
    EXPECT_TRUE(has(st.message(), dir / name)) << st.message();
    EXPECT_TRUE(has(st.message(), why)) << st.message();
    EXPECT_TRUE(has(st.message(), "times.txt:" + std::to_string(i + 1))) << st.message();
  }
  EXPECT_EQ(loader.load(5, f, st), LoadStatus::kOk) << "the stream goes on after skips";
  EXPECT_EQ(f.seq, 5U);
}

TEST(FolderLoaders, ImageSizeComesFromTheFirstReadableImage) {
  TempDir dir;
  test::make_kitti(dir.path(), 3, kW, kH, 0);
  std::filesystem::remove(dir / "image_0/000000.png");
  KittiLoader ok(dir.path(), {});
  ASSERT_TRUE(ok.open().is_ok());
  EXPECT_EQ(ok.intrinsics().width, kW);
  for (int i = 1; i < 3; ++i) {
    char name[32];
    std::snprintf(name, sizeof name, "image_0/%06d.png", i);
    std::filesystem::remove(dir / name);
  }
  const Status s = KittiLoader(dir.path(), {}).open();
  ASSERT_EQ(s.code(), StatusCode::kInputError);
  EXPECT_TRUE(has(s.message(), "image size is unknown")) << s.message();
  EXPECT_TRUE(has(s.message(), dir / "image_0/000000.png")) << s.message();
}

TEST(FolderLoaders, IndexProblemsAreErrorsNamingFileAndLine) {
  struct Case {
    const char* file;
    const char* text;
    const char* expect;
  };
  const Case tum_cases[] = {
      {"rgb.txt", "100.0 rgb/100.000000.png\n100.1 rgb/a.png\n100.05 rgb/b.png\n",
       "rgb.txt:3: non-monotonic"},
      {"rgb.txt", "100.0 rgb/100.000000.png\n100.0 rgb/a.png\n", "rgb.txt:2: duplicate"},
      {"rgb.txt", "", "rgb.txt: no entries"},
      {"rgb.txt", "100.0 rgb/100.000000.png\n100.1\n", "rgb.txt:2: expected 'timestamp filename'"},
      {"groundtruth.txt", "100.0 0 0 0 0 0 0 1\n100.1 0 0 0 0 0 1\n", "groundtruth.txt:2:"},
      {"groundtruth.txt", "", "groundtruth.txt: no entries"},
  };
  for (const Case& c : tum_cases) {
    TempDir dir;
    make_tum(dir.path(), 2);
    write_file(dir / c.file, c.text);
    const Status s = TumLoader(dir.path(), calib(), false, kDepthScale, kMaxDt).open();
    ASSERT_EQ(s.code(), StatusCode::kInputError) << c.expect;
    EXPECT_TRUE(has(s.message(), dir.path() + "/" + c.expect)) << s.message();
  }
  const Case kitti_cases[] = {
      {"times.txt", "0.0\n0.2\n0.1\n", "times.txt:3: non-monotonic"},
      {"times.txt", "", "times.txt: no entries"},
      {"calib.txt", "", "calib.txt: no 'P0:'"},
      {"poses.txt", "1 0 0 0 0 1 0 0 0 0 1 0\n1 0 0 0 0 1 0 0 0 0 1\n", "poses.txt:2:"},
      {"poses.txt", "", "poses.txt: no entries"},
      {"poses.txt",
       "1 0 0 0 0 1 0 0 0 0 1 0\n1 0 0 0 0 1 0 0 0 0 1 0\n1 0 0 0 0 1 0 0 0 0 1 0\n"
       "1 0 0 0 0 1 0 0 0 0 1 0\n",
       "poses.txt: 4 poses for 3 frames"},
  };
  for (const Case& c : kitti_cases) {
    TempDir dir;
    test::make_kitti(dir.path(), 3, kW, kH, 3);
    write_file(dir / c.file, c.text);
    const Status s = KittiLoader(dir.path(), {}).open();
    ASSERT_EQ(s.code(), StatusCode::kInputError) << c.expect;
    EXPECT_TRUE(has(s.message(), dir.path() + "/" + c.expect)) << s.message();
  }
}

// ---- KITTI ------------------------------------------------------------------------------

TEST(KittiLoader, CalibrationTimesAndFewerPosesThanImages) {
  TempDir dir;
  test::make_kitti(dir.path(), 4, kW, kH, 3);
  KittiLoader loader(dir.path(), {});
  ASSERT_TRUE(loader.open().is_ok());
  const CameraIntrinsics& k = loader.intrinsics();
  EXPECT_EQ(k.fx, 500.0);
  EXPECT_EQ(k.fy, 510.0);
  EXPECT_EQ(k.cx, 320.5);
  EXPECT_EQ(k.cy, 240.25);
  EXPECT_EQ(k.dist, (std::array<double, 4>{}));
  EXPECT_EQ(loader.ground_truth().poses.size(), 3U);
  Frame f = make_frame(false);
  Status st;
  for (int i = 0; i < 4; ++i) {
    ASSERT_EQ(loader.load(static_cast<std::size_t>(i), f, st), LoadStatus::kOk) << st.message();
    EXPECT_EQ(f.t_ns, 100'000'000LL * i);
    EXPECT_EQ(cv::norm(f.gray, random_image(kW, kH, CV_8UC1, static_cast<std::uint64_t>(i) + 1),
                       cv::NORM_INF),
              0.0);
    EXPECT_EQ(f.has_ground_truth, i < 3) << i;
    if (i < 3) {
      EXPECT_NEAR(f.T_w_c_gt.translation().z(), 2.0 * i, 1e-6);
    }
  }
}

TEST(KittiLoader, CalibrationOverrideWins) {
  TempDir dir;
  test::make_kitti(dir.path(), 2, kW, kH, 0);
  KittiLoader loader(dir.path(), calib());
  ASSERT_TRUE(loader.open().is_ok());
  EXPECT_EQ(loader.intrinsics().fx, 50.0);
  EXPECT_EQ(loader.intrinsics().width, kW) << "image size is kept";
}

// ---- EuRoC ------------------------------------------------------------------------------

const SE3d kTbs = pose_z(std::numbers::pi / 2, 0.1, 0.2, 0.3);

std::string euroc_sensor_yaml(int w, int h) {
  std::string data;
  for (int r = 0; r < 4; ++r) {
    for (int c = 0; c < 4; ++c)
      data += fmt("%.17g", kTbs.matrix()(r, c)) + (r * 4 + c < 15 ? ", " : "");
    if (r < 3) data += "\n         ";
  }
  return "%YAML:1.0\nsensor_type: camera\nT_BS:\n  cols: 4\n  rows: 4\n  data: [" + data +
         "]\nrate_hz: 20\nresolution: [" + std::to_string(w) + ", " + std::to_string(h) +
         "]\ncamera_model: pinhole\nintrinsics: [458.654, 457.296, 367.215, 248.375] #fu, fv, "
         "cu, cv\ndistortion_model: radial-tangential\ndistortion_coefficients: [-0.28340811, "
         "0.07395907, 0.00019359, 1.76187114e-05]\n";
}

std::int64_t euroc_t(int i) {
  return 1403636579763555584LL + 50'000'000LL * i;
}

// Frame 0: ground truth sample exactly at its time; frame 1: samples 5 ms either side with
// the same rotation; frame 2: none within 20 ms.
void make_euroc(const std::string& root, int w, int h) {
  const std::string cam = root + "/mav0/cam0";
  std::string csv = "#timestamp [ns],filename\n";
  for (int i = 0; i < 3; ++i) {
    const std::string name = std::to_string(euroc_t(i)) + ".png";
    write_png(cam + "/data/" + name,
              random_image(w, h, CV_8UC1, static_cast<std::uint64_t>(i) + 40));
    csv += std::to_string(euroc_t(i)) + "," + name + "\n";
  }
  write_file(cam + "/data.csv", csv);
  write_file(cam + "/sensor.yaml", euroc_sensor_yaml(w, h));
  const auto row = [](std::int64_t t, const SE3d& T) {
    const Eigen::Quaterniond q(T.linear());
    std::string s = std::to_string(t);
    for (double v : {T.translation().x(), T.translation().y(), T.translation().z(), q.w(), q.x(),
                     q.y(), q.z(), 0.1, 0.2, 0.3}) {
      s += "," + fmt("%.15g", v);
    }
    return s + "\n";
  };
  std::string gt =
      "#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], "
      "q_RS_z [], v_RS_R_x [m s^-1], v_RS_R_y [m s^-1], v_RS_R_z [m s^-1]\n";
  gt += row(euroc_t(0), pose_z(0.3, 1.0, 2.0, 3.0));
  gt += row(euroc_t(1) - 5'000'000, pose_z(0.5, 4.0, 0.0, 0.0));
  gt += row(euroc_t(1) + 5'000'000, pose_z(0.5, 5.0, 1.0, 0.0));
  write_file(root + "/mav0/state_groundtruth_estimate0/data.csv", gt);
}

TEST(EurocLoader, IntrinsicsDistortionAndCameraGroundTruth) {
  TempDir dir;
  make_euroc(dir.path(), kW, kH);
  EurocLoader loader(dir.path(), {}, kMaxDt);
  ASSERT_TRUE(loader.open().is_ok());
  const CameraIntrinsics& k = loader.intrinsics();
  EXPECT_EQ(k.width, kW);
  EXPECT_EQ(k.fx, 458.654);
  EXPECT_EQ(k.fy, 457.296);
  EXPECT_EQ(k.cx, 367.215);
  EXPECT_EQ(k.cy, 248.375);
  EXPECT_EQ(k.dist, (std::array<double, 4>{-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05}));
  EXPECT_NEAR((loader.T_b_c().matrix() - kTbs.matrix()).norm(), 0.0, 1e-12);
  EXPECT_NEAR(loader.nominal_fps(), 20.0, 1e-9);

  Frame f = make_frame(false);
  Status st;
  ASSERT_EQ(loader.load(0, f, st), LoadStatus::kOk) << st.message();
  EXPECT_EQ(f.t_ns, euroc_t(0));
  EXPECT_EQ(cv::norm(f.gray, random_image(kW, kH, CV_8UC1, 40), cv::NORM_INF), 0.0);
  ASSERT_TRUE(f.has_ground_truth);
  const SE3d expect0 = pose_z(0.3, 1.0, 2.0, 3.0) * kTbs;  // T_w_c = T_w_b * T_b_s
  EXPECT_NEAR((f.T_w_c_gt.matrix() - expect0.matrix()).norm(), 0.0, 1e-9);

  ASSERT_EQ(loader.load(1, f, st), LoadStatus::kOk) << st.message();
  ASSERT_TRUE(f.has_ground_truth);
  const SE3d expect1 = pose_z(0.5, 4.5, 0.5, 0.0) * kTbs;  // midpoint of the two samples
  EXPECT_NEAR((f.T_w_c_gt.matrix() - expect1.matrix()).norm(), 0.0, 1e-9);

  ASSERT_EQ(loader.load(2, f, st), LoadStatus::kOk) << st.message();
  EXPECT_FALSE(f.has_ground_truth);
}

TEST(EurocLoader, AcceptsTheMav0FolderItself) {
  TempDir dir;
  make_euroc(dir.path(), kW, kH);
  EurocLoader loader(dir / "mav0", {}, kMaxDt);
  EXPECT_TRUE(loader.open().is_ok());
  EXPECT_EQ(loader.size(), 3U);
}

TEST(EurocLoader, ErrorsNameTheFile) {
  {
    TempDir dir;
    make_euroc(dir.path(), kW, kH);
    write_file(dir / "mav0/cam0/sensor.yaml", euroc_sensor_yaml(kW + 1, kH));
    const Status s = EurocLoader(dir.path(), {}, kMaxDt).open();
    ASSERT_EQ(s.code(), StatusCode::kInputError);
    EXPECT_TRUE(has(s.message(), "sensor.yaml: resolution 65x48 does not match")) << s.message();
  }
  for (const char* file : {"mav0/cam0/data.csv", "mav0/cam0/sensor.yaml"}) {
    TempDir dir;
    make_euroc(dir.path(), kW, kH);
    std::filesystem::remove(dir / file);
    const Status s = EurocLoader(dir.path(), {}, kMaxDt).open();
    ASSERT_EQ(s.code(), StatusCode::kInputError);
    EXPECT_TRUE(has(s.message(), dir / file)) << s.message();
  }
  {
    TempDir dir;
    make_euroc(dir.path(), kW, kH);
    write_file(dir / "mav0/cam0/data.csv", "#timestamp [ns],filename\n5,a.png\n5,b.png\n");
    const Status s = EurocLoader(dir.path(), {}, kMaxDt).open();
    EXPECT_TRUE(has(s.message(), "mav0/cam0/data.csv:3: duplicate timestamp")) << s.message();
  }
  {
    TempDir dir;
    make_euroc(dir.path(), kW, kH);
    write_file(dir / "mav0/state_groundtruth_estimate0/data.csv", "1,2,3\n");
    const Status s = EurocLoader(dir.path(), {}, kMaxDt).open();
    EXPECT_TRUE(has(s.message(), "state_groundtruth_estimate0/data.csv:1:")) << s.message();
  }
}

}  // namespace
}  // namespace mer::hal
