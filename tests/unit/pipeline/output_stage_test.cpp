#include "pipeline/output_stage.h"

#include <filesystem>
#include <fstream>
#include <sstream>

#include <gtest/gtest.h>

namespace mer::pipeline {
namespace {

TEST(OutputStage, TumLineRoundTripsThePose) {
  const Eigen::Quaterniond q =
      Eigen::Quaterniond(Eigen::AngleAxisd(0.3, Eigen::Vector3d(1, 2, 3).normalized()));
  const SE3d T = make_se3(q, Eigen::Vector3d(1.5, -2.25, 0.125));
  char buf[256];
  const int n = format_tum_line(buf, sizeof buf, 1'234'567'891'000LL, T);
  ASSERT_GT(n, 0);
  std::istringstream is(std::string(buf, static_cast<std::size_t>(n)));
  double t, x, y, z, qx, qy, qz, qw;
  is >> t >> x >> y >> z >> qx >> qy >> qz >> qw;
  EXPECT_NEAR(t, 1234.567891, 1e-9);
  EXPECT_NEAR(x, 1.5, 1e-9);
  EXPECT_NEAR(y, -2.25, 1e-9);
  EXPECT_NEAR(z, 0.125, 1e-9);
  const Eigen::Quaterniond r(qw, qx, qy, qz);
  EXPECT_LT(r.angularDistance(q), 1e-8);
}

TEST(OutputStage, WritesTrackedFramesAndKeyframesOnly) {
  const auto dir = std::filesystem::temp_directory_path() / "mer_output_stage_test";
  std::filesystem::create_directories(dir);
  OutputStage out;
  ASSERT_TRUE(out.open(dir.string(), OutputOptions{}).is_ok());
  frontend::TrackingResult r;
  for (int i = 0; i < 5; ++i) {
    r.seq = static_cast<std::uint64_t>(i);
    r.t_ns = i * 100'000'000LL;
    r.state = (i == 2) ? frontend::TrackState::kLost : frontend::TrackState::kTracked;
    r.is_keyframe = (i == 0 || i == 3);
    (void)out.spin_once(r, 1000);
  }
  ASSERT_TRUE(out.close().is_ok());
  auto lines = [&](const char* name) {
    std::ifstream f(dir / name);
    int n = 0;
    for (std::string l; std::getline(f, l);) ++n;
    return n;
  };
  EXPECT_EQ(lines("trajectory.txt"), 4);
  EXPECT_EQ(lines("keyframes.txt"), 2);
  EXPECT_EQ(lines("frames.csv"), 6);   // header + 5
  EXPECT_EQ(lines("latency.csv"), 6);  // header + 5
  std::filesystem::remove_all(dir);
}

TEST(OutputStage, UnwritableDirectoryIsAnError) {
  OutputStage out;
  const Status s = out.open("/nonexistent/dir", OutputOptions{});
  ASSERT_FALSE(s.is_ok());
  EXPECT_NE(s.message().find("/nonexistent/dir"), std::string::npos);
}

}  // namespace
}  // namespace mer::pipeline

namespace mer::pipeline {
namespace {
// Epoch timestamps (TUM/EuRoC, ~1.4e9 s) keep every nanosecond digit.
TEST(OutputStage, TumTimestampsAreExactAtEpochTimes) {
  char buf[256];
  format_tum_line(buf, sizeof buf, 1'403'636'579'763'555'584LL, SE3d::Identity());
  EXPECT_EQ(std::string(buf).substr(0, 20), "1403636579.763555584");
  format_tum_line(buf, sizeof buf, 5, SE3d::Identity());
  EXPECT_EQ(std::string(buf).substr(0, 11), "0.000000005");
}
}  // namespace
}  // namespace mer::pipeline
