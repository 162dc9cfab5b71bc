// Dataset text parsers: exact values on good input, errors naming file:line on bad input,
// and no crash/hang on arbitrary bytes (what the fuzz harness relies on).
#include "hal/replay/dataset_parsers.h"

#include <random>

#include <gtest/gtest.h>

namespace mer::hal {
namespace {

bool has(const std::string& text, const std::string& part) {
  return text.find(part) != std::string::npos;
}

TEST(ParseSeconds, DecimalIsExactAndExponentIsRounded) {
  std::int64_t t = 0;
  ASSERT_TRUE(parse_seconds_ns("1305031102.175304", t));
  EXPECT_EQ(t, 1305031102175304000LL);
  ASSERT_TRUE(parse_seconds_ns("1.000000e-01", t));
  EXPECT_EQ(t, 100000000LL);
  ASSERT_TRUE(parse_seconds_ns("-0.5", t));
  EXPECT_EQ(t, -500000000LL);
  ASSERT_TRUE(parse_seconds_ns("+2", t));
  EXPECT_EQ(t, 2000000000LL);
  ASSERT_TRUE(parse_seconds_ns(".25", t));
  EXPECT_EQ(t, 250000000LL);
  ASSERT_TRUE(parse_seconds_ns("1.1234567899", t));
  EXPECT_EQ(t, 1123456789LL) << "digits past ns are truncated";
  for (const char* bad : {"", ".", "-", "abc", "1.2.3", "nan", "inf", "1e300", "99999999999", "1,5",
                          "0x10", "1e", "--1"}) {
    EXPECT_FALSE(parse_seconds_ns(bad, t)) << bad;
  }
}

TEST(ParseTumList, CommentsBlankLinesAndCrlf) {
  auto r = parse_tum_list(
      "# color images\r\n# file: 'x.bag'\r\n\r\n1305031102.175304 rgb/1305031102.175304.png\r\n"
      "  1305031102.211214   rgb/b.png  \n1305031102.243211 rgb/c.png",
      "rgb.txt");
  ASSERT_TRUE(r.is_ok()) << r.status().message();
  ASSERT_EQ(r.value().size(), 3U);
  EXPECT_EQ(r.value()[0].t_ns, 1305031102175304000LL);
  EXPECT_EQ(r.value()[0].file, "rgb/1305031102.175304.png");
  EXPECT_EQ(r.value()[0].line, 4);
  EXPECT_EQ(r.value()[1].file, "rgb/b.png");
  EXPECT_EQ(r.value()[2].line, 6);
}

TEST(ParseTumList, MalformedLineNamesFileAndLine) {
  auto r = parse_tum_list("1.0 a.png\n2.0 b.png extra\n", "/d/rgb.txt");
  ASSERT_FALSE(r.is_ok());
  EXPECT_EQ(r.status().code(), StatusCode::kInputError);
  EXPECT_TRUE(has(r.status().message(), "/d/rgb.txt:2:")) << r.status().message();
  auto bad_t = parse_tum_list("1.0 a.png\nxyz b.png\n", "rgb.txt");
  ASSERT_FALSE(bad_t.is_ok());
  EXPECT_TRUE(has(bad_t.status().message(), "rgb.txt:2: bad timestamp 'xyz'"))
      << bad_t.status().message();
}

TEST(ParseTumList, DuplicateAndNonMonotonicTimestampsAreErrors) {
  auto dup = parse_tum_list("1.0 a.png\n1.0 b.png\n", "rgb.txt");
  ASSERT_FALSE(dup.is_ok());
  EXPECT_TRUE(has(dup.status().message(), "rgb.txt:2: duplicate timestamp"))
      << dup.status().message();
  auto back = parse_tum_list("1.0 a.png\n# c\n3.0 b.png\n2.0 c.png\n", "rgb.txt");
  ASSERT_FALSE(back.is_ok());
  EXPECT_TRUE(has(back.status().message(), "rgb.txt:4: non-monotonic timestamp"))
      << back.status().message();
  EXPECT_TRUE(has(back.status().message(), "line 3")) << back.status().message();
}

TEST(ParseTumList, EmptyFileIsAnError) {
  for (const char* text : {"", "# only a comment\n", "\n\n  \n"}) {
    auto r = parse_tum_list(text, "depth.txt");
    ASSERT_FALSE(r.is_ok());
    EXPECT_TRUE(has(r.status().message(), "depth.txt: no entries")) << r.status().message();
  }
}

TEST(ParseEurocCsv, ReadsNanosecondsAndNames) {
  auto r = parse_euroc_csv(
      "#timestamp [ns],filename\r\n1403636579763555584,1403636579763555584.png\r\n"
      "1403636579813555456, 1403636579813555456.png\r\n",
      "data.csv");
  ASSERT_TRUE(r.is_ok()) << r.status().message();
  ASSERT_EQ(r.value().size(), 2U);
  EXPECT_EQ(r.value()[0].t_ns, 1403636579763555584LL);
  EXPECT_EQ(r.value()[1].file, "1403636579813555456.png");
  EXPECT_EQ(r.value()[1].line, 3);
}

TEST(ParseEurocCsv, BadLinesNameFileAndLine) {
  for (const char* text : {"1,a.png\n2\n", "1,a.png\n-5,b.png\n", "1,a.png\n1.5,b.png\n",
                           "1,a.png\n2,\n", "1,a.png\n2,b.png,c\n"}) {
    auto r = parse_euroc_csv(text, "cam0/data.csv");
    ASSERT_FALSE(r.is_ok()) << text;
    EXPECT_TRUE(has(r.status().message(), "cam0/data.csv:2:")) << r.status().message();
  }
  auto back = parse_euroc_csv("5,a.png\n4,b.png\n", "data.csv");
  ASSERT_FALSE(back.is_ok());
  EXPECT_TRUE(has(back.status().message(), "data.csv:2: non-monotonic")) << back.status().message();
}

TEST(ParseKittiCalib, ReadsP0) {
  auto r = parse_kitti_calib(
      "P0: 7.070912e+02 0 6.018873e+02 0 0 7.070912e+02 1.831104e+02 0 0 0 1 0\n"
      "P1: 7.070912e+02 0 6.018873e+02 -3.798145e+02 0 7.070912e+02 1.831104e+02 0 0 0 1 0\n",
      "calib.txt");
  ASSERT_TRUE(r.is_ok()) << r.status().message();
  EXPECT_DOUBLE_EQ(r.value().fx, 707.0912);
  EXPECT_DOUBLE_EQ(r.value().fy, 707.0912);
  EXPECT_DOUBLE_EQ(r.value().cx, 601.8873);
  EXPECT_DOUBLE_EQ(r.value().cy, 183.1104);
}

TEST(ParseKittiCalib, Errors) {
  auto none = parse_kitti_calib("P1: 1 0 0 0 0 1 0 0 0 0 1 0\n", "calib.txt");
  ASSERT_FALSE(none.is_ok());
  EXPECT_TRUE(has(none.status().message(), "calib.txt: no 'P0:'")) << none.status().message();
  auto short_line = parse_kitti_calib("P0: 1 0 0 0 0 1 0 0 0 0 1\n", "calib.txt");
  ASSERT_FALSE(short_line.is_ok());
  EXPECT_TRUE(has(short_line.status().message(), "calib.txt:1:"));
  auto bad_num = parse_kitti_calib("\nP0: 1 0 0 0 0 x 0 0 0 0 1 0\n", "calib.txt");
  ASSERT_FALSE(bad_num.is_ok());
  EXPECT_TRUE(has(bad_num.status().message(), "calib.txt:2: P0: bad number 'x'"))
      << bad_num.status().message();
  auto zero_f = parse_kitti_calib("P0: 0 0 0 0 0 1 0 0 0 0 1 0\n", "calib.txt");
  ASSERT_FALSE(zero_f.is_ok());
}

TEST(ParseKittiTimes, ReadsAndChecksOrder) {
  auto r = parse_kitti_times("0.000000e+00\n1.000000e-01\n2.000000e-01\n", "times.txt");
  ASSERT_TRUE(r.is_ok());
  ASSERT_EQ(r.value().size(), 3U);
  EXPECT_DOUBLE_EQ(r.value()[1], 0.1);
  auto dup = parse_kitti_times("0.0\n0.1\n0.1\n", "times.txt");
  ASSERT_FALSE(dup.is_ok());
  EXPECT_TRUE(has(dup.status().message(), "times.txt:3: duplicate")) << dup.status().message();
  auto bad = parse_kitti_times("0.0\n0.1 0.2\n", "times.txt");
  ASSERT_FALSE(bad.is_ok());
  EXPECT_TRUE(has(bad.status().message(), "times.txt:2:"));
  EXPECT_FALSE(parse_kitti_times("", "times.txt").is_ok());
}

TEST(ParseKittiPoses, ReadsRowMajor3x4) {
  auto r =
      parse_kitti_poses("1 0 0 1.5 0 1 0 -2 0 0 1 3.25\n0 -1 0 0 1 0 0 0 0 0 1 0\n", "poses.txt");
  ASSERT_TRUE(r.is_ok()) << r.status().message();
  ASSERT_EQ(r.value().size(), 2U);
  EXPECT_EQ(r.value()[0].translation(), Eigen::Vector3d(1.5, -2, 3.25));
  EXPECT_DOUBLE_EQ(r.value()[1].linear()(0, 1), -1.0);
  EXPECT_DOUBLE_EQ(r.value()[1].linear()(1, 0), 1.0);
}

TEST(ParseKittiPoses, Errors) {
  auto short_line =
      parse_kitti_poses("1 0 0 0 0 1 0 0 0 0 1 0\n1 0 0 0 0 1 0 0 0 0 1\n", "poses.txt");
  ASSERT_FALSE(short_line.is_ok());
  EXPECT_TRUE(has(short_line.status().message(), "poses.txt:2: expected 12 numbers"))
      << short_line.status().message();
  auto not_rot = parse_kitti_poses("2 0 0 0 0 1 0 0 0 0 1 0\n", "poses.txt");
  ASSERT_FALSE(not_rot.is_ok());
  EXPECT_TRUE(has(not_rot.status().message(), "poses.txt:1: the 3x3 block is not a rotation"));
  auto reflection = parse_kitti_poses("-1 0 0 0 0 1 0 0 0 0 1 0\n", "poses.txt");
  EXPECT_FALSE(reflection.is_ok());
  auto nan = parse_kitti_poses("1 0 0 nan 0 1 0 0 0 0 1 0\n", "poses.txt");
  EXPECT_FALSE(nan.is_ok());
}

TEST(ParseTumTrajectory, ReadsPosesAndChecksQuaternions) {
  auto r = parse_tum_trajectory(
      "# timestamp tx ty tz qx qy qz qw\n1.0 1 2 3 0 0 0 1\n1.5 0 0 0 0 0 0.7071067811865476 "
      "0.7071067811865476\n",
      "gt.txt");
  ASSERT_TRUE(r.is_ok()) << r.status().message();
  ASSERT_EQ(r.value().poses.size(), 2U);
  EXPECT_EQ(r.value().source, "gt.txt");
  EXPECT_EQ(r.value().poses[1].t_ns, 1500000000LL);
  EXPECT_EQ(r.value().poses[0].T_w_c.translation(), Eigen::Vector3d(1, 2, 3));
  EXPECT_NEAR(r.value().poses[1].T_w_c.linear()(1, 0), 1.0, 1e-12);  // 90 deg about z
  auto bad_q = parse_tum_trajectory("1.0 1 2 3 0 0 0 1\n2.0 1 2 3 0 0 0 0\n", "gt.txt");
  ASSERT_FALSE(bad_q.is_ok());
  EXPECT_TRUE(has(bad_q.status().message(), "gt.txt:2: quaternion")) << bad_q.status().message();
  auto few = parse_tum_trajectory("1.0 1 2 3 0 0 1\n", "gt.txt");
  ASSERT_FALSE(few.is_ok());
  EXPECT_TRUE(has(few.status().message(), "gt.txt:1: expected 't tx ty tz qx qy qz qw'"));
  auto back = parse_tum_trajectory("2.0 0 0 0 0 0 0 1\n1.0 0 0 0 0 0 0 1\n", "gt.txt");
  ASSERT_FALSE(back.is_ok());
  EXPECT_TRUE(has(back.status().message(), "gt.txt:2: non-monotonic"));
}

TEST(ParseTumTrajectory, RepeatedTimestampsAreDroppedAndCounted) {
  auto r = parse_tum_trajectory(
      "1.0 1 0 0 0 0 0 1\n2.0 2 0 0 0 0 0 1\n2.0 9 0 0 0 0 0 1\n2.0 9 0 0 0 0 0 1\n"
      "3.0 3 0 0 0 0 0 1\n",
      "gt.txt");
  ASSERT_TRUE(r.is_ok()) << r.status().message();
  ASSERT_EQ(r.value().poses.size(), 3U);
  EXPECT_EQ(r.value().poses[1].T_w_c.translation().x(), 2.0) << "the first sample is kept";
  EXPECT_EQ(r.value().duplicates_dropped, 2U);
  EXPECT_EQ(r.value().first_duplicate_line, 3);
  auto back = parse_tum_trajectory(
      "1.0 0 0 0 0 0 0 1\n2.0 0 0 0 0 0 0 1\n2.0 0 0 0 0 0 0 1\n"
      "1.5 0 0 0 0 0 0 1\n",
      "gt.txt");
  ASSERT_FALSE(back.is_ok());
  EXPECT_TRUE(has(back.status().message(), "gt.txt:4: non-monotonic")) << back.status().message();
}

TEST(ParseEurocGroundTruth, ReadsBodyPoses) {
  auto r = parse_euroc_groundtruth(
      "#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], "
      "q_RS_z [], v_RS_R_x [m s^-1]\n"
      "1403636580838555648,4.688319,-1.786938,0.783338,0.534108,-0.153029,-0.827383,-0.082152,"
      "-0.027876\n",
      "gt.csv");
  ASSERT_TRUE(r.is_ok()) << r.status().message();
  ASSERT_EQ(r.value().poses.size(), 1U);
  EXPECT_EQ(r.value().poses[0].t_ns, 1403636580838555648LL);
  const Eigen::Quaterniond q(r.value().poses[0].T_w_c.linear());
  const Eigen::Quaterniond e =
      Eigen::Quaterniond(0.534108, -0.153029, -0.827383, -0.082152).normalized();
  EXPECT_NEAR(std::abs(q.dot(e)), 1.0, 1e-12);
  auto short_line = parse_euroc_groundtruth("1,2,3\n", "gt.csv");
  ASSERT_FALSE(short_line.is_ok());
  EXPECT_TRUE(has(short_line.status().message(), "gt.csv:1:"));
}

constexpr const char* kEurocSensorYaml = R"(%YAML:1.0
# General sensor definitions.
sensor_type: camera
comment: VI-Sensor cam0 (MT9M034)

# Sensor extrinsics wrt. the body-frame.
T_BS:
  cols: 4
  rows: 4
  data: [0.0148655429818, -0.999880929698, 0.00414029679422, -0.0216401454975,
         0.999557249008, 0.0149672133247, 0.025715529948, -0.064676986768,
        -0.0257744366974, 0.00375618835797, 0.999660727178, 0.00981073058949,
         0.0, 0.0, 0.0, 1.0]

# Camera specific definitions.
rate_hz: 20
resolution: [752, 480]
camera_model: pinhole
intrinsics: [458.654, 457.296, 367.215, 248.375] #fu, fv, cu, cv
distortion_model: radial-tangential
distortion_coefficients: [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05]
)";

TEST(ParseEurocSensor, ReadsTheRealFileLayout) {
  auto r = parse_euroc_sensor(kEurocSensorYaml, "sensor.yaml");
  ASSERT_TRUE(r.is_ok()) << r.status().message();
  const EurocSensor& s = r.value();
  EXPECT_EQ(s.width, 752);
  EXPECT_EQ(s.height, 480);
  EXPECT_DOUBLE_EQ(s.fu, 458.654);
  EXPECT_DOUBLE_EQ(s.fv, 457.296);
  EXPECT_DOUBLE_EQ(s.cu, 367.215);
  EXPECT_DOUBLE_EQ(s.cv, 248.375);
  EXPECT_DOUBLE_EQ(s.dist[0], -0.28340811);
  EXPECT_DOUBLE_EQ(s.dist[3], 1.76187114e-05);
  EXPECT_DOUBLE_EQ(s.rate_hz, 20.0);
  EXPECT_DOUBLE_EQ(s.T_b_s.linear()(0, 1), -0.999880929698);
  EXPECT_DOUBLE_EQ(s.T_b_s.translation().z(), 0.00981073058949);
}

TEST(ParseEurocSensor, MissingOrMalformedKeysNameTheKey) {
  std::string text = kEurocSensorYaml;
  auto no_intr = parse_euroc_sensor(
      std::string(text).replace(text.find("intrinsics:"), 11, "intrinsicz:"), "sensor.yaml");
  ASSERT_FALSE(no_intr.is_ok());
  EXPECT_TRUE(has(no_intr.status().message(), "sensor.yaml: missing key 'intrinsics'"));
  auto short_list =
      parse_euroc_sensor(std::string(text).replace(text.find("458.654, "), 9, ""), "sensor.yaml");
  ASSERT_FALSE(short_list.is_ok());
  EXPECT_TRUE(has(short_list.status().message(), "sensor.yaml:19: key 'intrinsics': expected 4"))
      << short_list.status().message();
  auto model = parse_euroc_sensor(
      std::string(text).replace(text.find("radial-tangential"), 17, "equidistant"), "sensor.yaml");
  ASSERT_FALSE(model.is_ok());
  EXPECT_TRUE(has(model.status().message(), "distortion_model")) << model.status().message();
  auto open_list =
      parse_euroc_sensor(std::string(text).substr(0, text.find("0.0, 1.0]")), "sensor.yaml");
  ASSERT_FALSE(open_list.is_ok());
}

// Arbitrary bytes and mutations of valid files: every parser returns, nothing crashes
// (run under ASan in the asan preset). A small in-test stand-in for the fuzz harness.
TEST(DatasetParsers, SurviveRandomAndMutatedInput) {
  const std::vector<std::string> seeds = {"1.0 a.png\n2.0 b.png\n",
                                          "1,a.png\n2,b.png\n",
                                          "P0: 1 0 0 0 0 1 0 0 0 0 1 0\n",
                                          "0.0\n0.1\n",
                                          "1 0 0 0 0 1 0 0 0 0 1 0\n",
                                          "1.0 1 2 3 0 0 0 1\n",
                                          "1,1,2,3,1,0,0,0\n",
                                          kEurocSensorYaml};
  std::mt19937 rng(7);
  const std::string alphabet = "0123456789.,:-+eE []#\n\r\tabcP_xyz/";
  std::size_t ok_count = 0;
  for (int iter = 0; iter < 3000; ++iter) {
    std::string s = seeds[static_cast<std::size_t>(iter) % seeds.size()];
    const int edits = 1 + static_cast<int>(rng() % 8);
    for (int e = 0; e < edits; ++e) {
      const std::size_t pos = s.empty() ? 0 : rng() % (s.size() + 1);
      switch (rng() % 3) {
        case 0:
          s.insert(pos, 1, alphabet[rng() % alphabet.size()]);
          break;
        case 1:
          if (pos < s.size()) s.erase(pos, 1 + rng() % 4);
          break;
        default:
          if (pos < s.size()) s[pos] = static_cast<char>(rng() & 0xff);
      }
    }
    if (iter % 10 == 0) {  // pure random bytes
      s.assign(rng() % 200, '\0');
      for (char& c : s) c = static_cast<char>(rng() & 0xff);
    }
    ok_count += parse_tum_list(s, "f").is_ok() ? 1 : 0;
    ok_count += parse_euroc_csv(s, "f").is_ok() ? 1 : 0;
    ok_count += parse_kitti_calib(s, "f").is_ok() ? 1 : 0;
    ok_count += parse_kitti_times(s, "f").is_ok() ? 1 : 0;
    ok_count += parse_kitti_poses(s, "f").is_ok() ? 1 : 0;
    ok_count += parse_tum_trajectory(s, "f").is_ok() ? 1 : 0;
    ok_count += parse_euroc_groundtruth(s, "f").is_ok() ? 1 : 0;
    ok_count += parse_euroc_sensor(s, "f").is_ok() ? 1 : 0;
  }
  EXPECT_GT(ok_count, 0U) << "some mutations keep the input valid";
}

}  // namespace
}  // namespace mer::hal
