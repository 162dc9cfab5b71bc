#include "app/accuracy.h"

#include <filesystem>
#include <fstream>
#include <random>
#include <string>
#include <vector>

#include <gtest/gtest.h>

namespace mer::app {
namespace {

std::string write(const std::string& name, const std::string& text) {
  const auto path = (std::filesystem::temp_directory_path() / name).string();
  std::ofstream(path) << text;
  return path;
}

std::vector<pipeline::AnchoredFrame> two_frames() {
  std::vector<pipeline::AnchoredFrame> f(2);
  f[0].t_ns = 1'000'000'000;
  f[0].T_w_c = make_se3(Eigen::Quaterniond::Identity(), Eigen::Vector3d(0.5, 0.0, 0.0));
  f[1].t_ns = 1'033'333'333;
  return f;
}

const char* const kGood =
    "1.000000000 - 0.500000000 0.000000000 0.000000000 0 0 0 1\n"
    "1.033333333 0.900000000 0.100000000 0.200000000 0.300000000 0 0 0.7071067811865476 "
    "0.7071067811865476\n";

TEST(FrameAnchors, ReadsAnchoredAndUnanchoredFrames) {
  auto frames = two_frames();
  const Status s = read_frame_anchors(write("mer_anchors_good.txt", kGood), frames);
  ASSERT_TRUE(s.is_ok()) << s.message();
  EXPECT_FALSE(frames[0].has_anchor);
  ASSERT_TRUE(frames[1].has_anchor);
  EXPECT_EQ(frames[1].anchor_t_ns, 900'000'000);
  EXPECT_NEAR(frames[1].T_kf_c.translation().x(), 0.1, 1e-12);
  EXPECT_NEAR(frames[1].T_kf_c.translation().z(), 0.3, 1e-12);
  EXPECT_NEAR(Eigen::AngleAxisd(frames[1].T_kf_c.linear()).angle(), M_PI / 2, 1e-9);
}

// Each defect is an error naming the file and the line.
TEST(FrameAnchors, BadLinesNameFileAndLine) {
  const std::vector<std::pair<std::string, std::string>> cases{
      {"1.0 - 0.5 0 0 0 0 0\n", ":1: expected 9 fields"},
      {"x - 0.5 0 0 0 0 0 1\n", ":1: bad timestamp"},
      {"1.0 - 0.5 0 0 0 0 0 1\n2.0 - 0 0 0 0 0 0 1\n", ":2: timestamp 2.0"},
      {"1.0 y 0.5 0 0 0 0 0 1\n", ":1: bad keyframe timestamp"},
      {"1.0 - 0.5 0 nan 0 0 0 1\n", ":1: bad number"},
      {"1.0 - 0.5 0 0 0 0 0 2\n", ":1: quaternion not unit"},
      {"1.0 - 0.7 0 0 0 0 0 1\n", ":1: frame without keyframe"},
      {"1.0 - 0.5 0 0 0 0 0 1\n", "1 frames, trajectory.txt has 2"},
      {std::string(kGood) + "1.1 - 0 0 0 0 0 0 1\n", ":3: more frames"},
  };
  for (const auto& [text, what] : cases) {
    auto frames = two_frames();
    const std::string path = write("mer_anchors_bad.txt", text);
    const Status s = read_frame_anchors(path, frames);
    ASSERT_FALSE(s.is_ok()) << text;
    EXPECT_NE(s.message().find(path), std::string::npos) << s.message();
    EXPECT_NE(s.message().find(what), std::string::npos) << s.message();
  }
  auto frames = two_frames();
  EXPECT_FALSE(read_frame_anchors("/nonexistent/frame_anchors.txt", frames).is_ok());
}

// Random byte edits of a good file: parsed or refused, never a crash or a hang (run under
// ASan in the asan preset).
TEST(FrameAnchors, FuzzedFilesAreParsedOrRefused) {
  std::mt19937 rng(7);
  const std::string good = kGood;
  const std::string alphabet = "0123456789.-+e \n#xnan";
  for (int i = 0; i < 500; ++i) {
    std::string text = good;
    const int edits = 1 + static_cast<int>(rng() % 4);
    for (int e = 0; e < edits; ++e) {
      const std::size_t at = rng() % text.size();
      switch (rng() % 3) {
        case 0:
          text[at] = alphabet[rng() % alphabet.size()];
          break;
        case 1:
          text.erase(at, 1);
          break;
        default:
          text.insert(at, 1, alphabet[rng() % alphabet.size()]);
      }
    }
    auto frames = two_frames();
    const Status s = read_frame_anchors(write("mer_anchors_fuzz.txt", text), frames);
    if (s.is_ok()) {
      for (const auto& f : frames) EXPECT_TRUE(f.T_kf_c.matrix().allFinite());
    }
  }
}

}  // namespace
}  // namespace mer::app
