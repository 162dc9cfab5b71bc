#include "app/accuracy.h"

#include <filesystem>
#include <fstream>
#include <iomanip>
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
      {"1.0 - 0.5 0 0 0 0 0\n", ":1: expected 10 fields"},
      {"1.0 - x 0.5 0 0 0 0 0 1\n", ":1: bad segment"},
      {"1.0 - -1 0.5 0 0 0 0 0 1\n", ":1: bad segment"},
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

// A run whose segment 1 merged into segment 0 at scale 2 and whose segment 2 never merged:
// trajectory.txt holds the frames of 0 and 1. Segment 2's lines are skipped, segment 1's
// anchor is scaled into segment 0's units, and its frame without anchor (moved into
// trajectory.txt's frame by the merge) need not repeat its own-frame pose.
TEST(FrameAnchors, FramesOfJoinedSegmentsAreReadInTheMainSegmentsUnits) {
  std::vector<pipeline::AnchoredFrame> frames(3);
  frames[0].t_ns = 1'000'000'000;
  frames[1].t_ns = 2'000'000'000;
  frames[2].t_ns = 4'000'000'000;
  frames[2].T_w_c = make_se3(Eigen::Quaterniond::Identity(), Eigen::Vector3d(9.0, 0.0, 0.0));
  const char* const text =
      "1.0 0.5 0 0.1 0 0 0 0 0 1\n"
      "2.0 1.5 1 0.1 0.2 0 0 0 0 1\n"
      "3.0 2.5 2 0.1 0 0 0 0 0 1\n"
      "4.0 - 1 0.3 0 0 0 0 0 1\n";
  const std::vector<double> scales{1.0, 2.0, 0.0};
  const Status s = read_frame_anchors(write("mer_anchors_segments.txt", text), frames, scales, 0);
  ASSERT_TRUE(s.is_ok()) << s.message();
  ASSERT_TRUE(frames[0].has_anchor);
  EXPECT_NEAR(frames[0].T_kf_c.translation().x(), 0.1, 1e-12);
  ASSERT_TRUE(frames[1].has_anchor);
  EXPECT_EQ(frames[1].anchor_t_ns, 1'500'000'000);
  EXPECT_NEAR(frames[1].T_kf_c.translation().x(), 0.2, 1e-12);
  EXPECT_NEAR(frames[1].T_kf_c.translation().y(), 0.4, 1e-12);
  EXPECT_FALSE(frames[2].has_anchor);
  // The same file read as if every segment were trajectory.txt's: four lines, three frames.
  std::vector<pipeline::AnchoredFrame> all(3);
  all[0].t_ns = 1'000'000'000;
  all[1].t_ns = 2'000'000'000;
  all[2].t_ns = 4'000'000'000;
  EXPECT_FALSE(read_frame_anchors(write("mer_anchors_segments.txt", text), all).is_ok());
  // A frame without anchor of the main segment must repeat its trajectory.txt pose.
  EXPECT_FALSE(read_frame_anchors(write("mer_anchors_segments.txt", text), frames,
                                  std::vector<double>{1.0, 2.0, 0.0}, 1)
                   .is_ok());
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

TEST(EventAudit, ScoresRelocalizationsAndLoopsAgainstTheTruthInMetres) {
  const auto dir = std::filesystem::temp_directory_path() / "mer_event_audit_test";
  std::filesystem::create_directories(dir);
  // Truth: at the origin (t = 1 s), 1 m along x (t = 2 s), back at the origin turned 90 deg
  // about z (t = 3 s).
  std::ofstream(dir / "groundtruth.txt") << "1.0 0 0 0 0 0 0 1\n"
                                            "2.0 1 0 0 0 0 0 1\n"
                                            "3.0 0 0 0 0 0 0.7071067811865476 0.7071067811865476\n";
  pipeline::PipelineStats st;
  st.segments.resize(2);
  st.segments[0].id = 0;
  st.segments[1].id = 1;
  std::vector<AccuracyReport> seg(2);
  seg[0].available = true;
  seg[0].scale = 2.0;  // one map unit is 2 m
  // seg[1] has no alignment: its events cannot be scored.
  const SE3d half_x = make_se3(Eigen::Quaterniond::Identity(), Eigen::Vector3d(0.5, 0.0, 0.0));
  st.relocalization.events.push_back({10, 2'000'000'000, 1'000'000'000, 0, half_x});  // right
  st.relocalization.events.push_back({20, 3'000'000'000, 1'000'000'000, 0, half_x});  // wrong
  st.relocalization.events.push_back({30, 2'000'000'000, 1'000'000'000, 1, half_x});  // no scale
  loop::LoopClosureEvent l;
  l.seq = 40;
  l.t_ns = 3'000'000'000;
  l.loop_t_ns = 2'000'000'000;
  l.segment = 0;
  // The truth of the t = 3 s camera in the t = 2 s one: 1 m along -x, turned 90 deg. The loop
  // claims it 0.25 map units (0.5 m) along -x, not turned: 0.5 m and 90 deg off.
  l.sim_old_new.t = Eigen::Vector3d(-0.25, 0.0, 0.0);
  st.loop.closures.push_back(l);

  const EventAuditReport r = audit_events(dir.string(), st, seg);
  ASSERT_TRUE(r.available) << r.note;
  ASSERT_EQ(r.events.size(), 4U);
  EXPECT_EQ(r.relocalizations, 2);
  EXPECT_EQ(r.relocalizations_wrong, 1);
  EXPECT_EQ(r.loops, 1);
  EXPECT_EQ(r.loops_wrong, 0);  // 0.5 m is not more than kWrongLoopM
  EXPECT_TRUE(r.events[0].scored);
  EXPECT_NEAR(r.events[0].error_m, 0.0, 1e-9);
  EXPECT_NEAR(r.events[0].gt_distance_m, 1.0, 1e-9);
  EXPECT_FALSE(r.events[0].wrong);
  EXPECT_NEAR(r.events[1].error_m, 1.0, 1e-9);
  EXPECT_NEAR(r.events[1].error_deg, 90.0, 1e-6);
  EXPECT_TRUE(r.events[1].wrong);
  EXPECT_FALSE(r.events[2].scored);
  EXPECT_EQ(r.events[3].kind, "loop");
  EXPECT_NEAR(r.events[3].error_m, 0.5, 1e-9);
  EXPECT_NEAR(r.events[3].error_deg, 90.0, 1e-6);
  EXPECT_NEAR(r.events[3].gt_distance_m, 1.0, 1e-9);

  std::filesystem::remove(dir / "groundtruth.txt");
  EXPECT_FALSE(audit_events(dir.string(), st, seg).available);
  std::filesystem::remove_all(dir);
}

// A monocular run (map at half scale) exact for its first 5 s that then drifts sideways: the
// start's own ATE is zero, the run's is not. 10 s at 30 Hz along a circle of 1 m radius.
TEST(EvaluateRun, FirstSecondsAfterTheStartAreScoredOnTheirOwn) {
  const auto dir = std::filesystem::temp_directory_path() / "mer_start_ate_test";
  std::filesystem::create_directories(dir);
  std::ofstream gt(dir / "groundtruth.txt");
  std::ofstream est(dir / "trajectory.txt");
  constexpr int kFrames = 300;
  constexpr double kFps = 30.0;
  gt << std::setprecision(12);
  est << std::setprecision(12);
  for (int i = 0; i < kFrames; ++i) {
    const double t = 1.0 + i / kFps;
    const double a = 0.2 * i / kFps;
    const Eigen::Vector3d p(std::cos(a), std::sin(a), 0.1 * a);
    const double drift = t - 1.0 > kStartWindowS ? 0.05 * (t - 1.0 - kStartWindowS) : 0.0;
    const Eigen::Vector3d q = 0.5 * p + Eigen::Vector3d(0.0, 0.0, drift);
    gt << t << " " << p.x() << " " << p.y() << " " << p.z() << " 0 0 0 1\n";
    est << t << " " << q.x() << " " << q.y() << " " << q.z() << " 0 0 0 1\n";
  }
  gt.close();
  est.close();
  pipeline::PipelineStats st;
  st.frames_processed = kFrames;
  const AccuracyReport a = evaluate_run(dir.string(), SensorMode::kMono, st);
  ASSERT_TRUE(a.available) << a.note;
  EXPECT_EQ(a.pairs, static_cast<std::size_t>(kFrames));
  EXPECT_EQ(a.start_pairs, static_cast<std::size_t>(kStartWindowS * kFps) + 1);
  EXPECT_LT(a.start_ate_rmse_m, 1e-6);
  EXPECT_NEAR(a.start_path_length_m, 0.2 * kStartWindowS * std::sqrt(1.01), 1e-3);
  EXPECT_GT(a.ate_rmse_m, 0.01);
  std::filesystem::remove_all(dir);
}

}  // namespace
}  // namespace mer::app
