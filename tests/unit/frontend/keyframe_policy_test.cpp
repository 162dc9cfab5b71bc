#include "frontend/keyframe_policy.h"

#include <vector>

#include <gtest/gtest.h>

namespace mer::frontend {
namespace {

constexpr int kWidth = 640;
constexpr int kHeight = 480;

// Inliers spread evenly over the image.
struct Spread {
  std::vector<float> x;
  std::vector<float> y;
  explicit Spread(int n, float x_max = kWidth, float y_max = kHeight) {
    for (int i = 0; i < n; ++i) {
      x.push_back(static_cast<float>((i * 37) % 100) / 100.0F * x_max);
      y.push_back(static_cast<float>((i * 53) % 100) / 100.0F * y_max);
    }
  }
};

constexpr std::int64_t kFrameNs = 33'333'333;  // 30 Hz

KeyframeEvidence evidence(const Spread& s, const KeyframeHistogram* h, int frame = 10) {
  KeyframeEvidence e;
  e.t_ns = frame * kFrameNs;
  e.inliers = static_cast<int>(s.x.size());
  e.inlier_x = s.x;
  e.inlier_y = s.y;
  e.histogram = h;
  return e;
}

TEST(KeyframeHistogram, KlIsZeroForIdenticalAndGrowsWithChange) {
  KeyframeHistogram a;
  KeyframeHistogram b;
  for (int i = 0; i < 60; ++i) a.add(5);
  for (int i = 0; i < 40; ++i) a.add(6);
  b = a;
  EXPECT_NEAR(KeyframeHistogram::kl_divergence(a, b, 1e-3), 0.0, 1e-12);
  // A small drift (new keyframe takes a few points): small divergence.
  KeyframeHistogram drift;
  for (int i = 0; i < 55; ++i) drift.add(5);
  for (int i = 0; i < 40; ++i) drift.add(6);
  for (int i = 0; i < 5; ++i) drift.add(7);
  const double small = KeyframeHistogram::kl_divergence(drift, a, 1e-3);
  // A revisit: the tracked points now belong to old keyframes 0 and 1.
  KeyframeHistogram revisit;
  for (int i = 0; i < 70; ++i) revisit.add(0);
  for (int i = 0; i < 30; ++i) revisit.add(1);
  const double big = KeyframeHistogram::kl_divergence(revisit, a, 1e-3);
  EXPECT_GT(small, 0.0);
  EXPECT_LT(small, 0.5);
  EXPECT_GT(big, 3.0);
  EXPECT_GT(big, 20.0 * small);
}

TEST(KeyframeHistogram, OverflowBinKeepsTotals) {
  KeyframeHistogram h;
  for (std::uint32_t k = 0; k < KeyframeHistogram::kBins + 10; ++k) h.add(k);
  EXPECT_EQ(h.size(), KeyframeHistogram::kBins);
  EXPECT_EQ(h.overflow(), 10);
  EXPECT_EQ(h.total(), KeyframeHistogram::kBins + 10);
  EXPECT_EQ(h.count_of(3), 1);
  EXPECT_EQ(h.count_of(1000), 0);
}

// A constructed revisit: frames track points of recent keyframes 8 and 9 with slow drift,
// then the camera comes back to where keyframes 0 and 1 were. Only the revisit fires KL.
TEST(KeyframePolicy, KlFiresOnConstructedRevisitOnly) {
  KeyframePolicyOptions o;
  o.min_inliers = 10;
  o.min_inlier_ratio = 0.0;
  o.min_spread = 0.0;
  o.max_spacing_s = 1000.0;
  o.min_spacing_s = 0.1;
  KeyframePolicy policy(o, kWidth, kHeight);
  policy.reset(200, 0);
  const Spread s(200);
  KeyframeHistogram h;
  for (int f = 0; f < 20; ++f) {
    h.clear();
    const int from_new = 5 * f;  // keyframe 9 gradually takes over from keyframe 8
    for (int i = 0; i < 200 - from_new; ++i) h.add(8);
    for (int i = 0; i < from_new; ++i) h.add(9);
    const KeyframeEvidence e = evidence(s, &h, f + 1);
    const KeyframeReason r = policy.decide(e);
    EXPECT_EQ(r, KeyframeReason::kNone) << "frame " << f << " kl " << policy.last_kl();
    policy.on_frame(e, false);
  }
  h.clear();
  for (int i = 0; i < 150; ++i) h.add(0);
  for (int i = 0; i < 50; ++i) h.add(1);
  const KeyframeEvidence e = evidence(s, &h, 21);
  EXPECT_EQ(policy.decide(e), KeyframeReason::kKlJump);
  EXPECT_GT(policy.last_kl(), o.kl_threshold);
}

TEST(KeyframePolicy, KlWaitsForMinimumSpacing) {
  KeyframePolicyOptions o;
  o.min_inliers = 0;
  o.min_inlier_ratio = 0.0;
  o.min_spread = 0.0;
  o.min_spacing_s = 5 * kFrameNs * 1e-9;
  KeyframePolicy policy(o, kWidth, kHeight);
  policy.reset(100, 0);
  const Spread s(100);
  KeyframeHistogram a;
  for (int i = 0; i < 100; ++i) a.add(3);
  KeyframeHistogram b;
  for (int i = 0; i < 100; ++i) b.add(0);
  policy.on_frame(evidence(s, &a, 1), false);  // frame 1 after the keyframe
  EXPECT_EQ(policy.decide(evidence(s, &b, 2)), KeyframeReason::kNone);    // frame 2 < spacing
  EXPECT_EQ(policy.decide(evidence(s, &b, 6)), KeyframeReason::kKlJump);  // past min spacing
}

TEST(KeyframePolicy, TooFewInliersAndRatio) {
  KeyframePolicyOptions o;
  o.min_inliers = 50;
  o.min_inlier_ratio = 0.5;
  o.min_spread = 0.0;
  o.min_spacing_s = 0.0;
  KeyframePolicy policy(o, kWidth, kHeight);
  policy.reset(300, 0);
  EXPECT_EQ(policy.decide(evidence(Spread(40), nullptr)), KeyframeReason::kTooFewInliers);
  EXPECT_EQ(policy.decide(evidence(Spread(140), nullptr)), KeyframeReason::kTooFewInliers);
  EXPECT_EQ(policy.decide(evidence(Spread(160), nullptr)), KeyframeReason::kNone);
}

TEST(KeyframePolicy, PoorSpreadFiresWhenInliersBunchUp) {
  KeyframePolicyOptions o;
  o.min_inliers = 0;
  o.min_inlier_ratio = 0.0;
  o.min_spacing_s = 0.0;
  o.min_spread = 0.4;
  KeyframePolicy policy(o, kWidth, kHeight);
  policy.reset(100, 0);
  // All inliers in the left quarter of the image: at most 2 of 8 columns occupied.
  EXPECT_EQ(policy.decide(evidence(Spread(200, kWidth / 4.0F, kHeight), nullptr)),
            KeyframeReason::kPoorSpread);
  EXPECT_LT(policy.last_spread(), 0.26);
  EXPECT_EQ(policy.decide(evidence(Spread(200), nullptr)), KeyframeReason::kNone);
  EXPECT_GT(policy.last_spread(), 0.9);
}

TEST(KeyframePolicy, MaxSpacingForcesAKeyframe) {
  KeyframePolicyOptions o;
  o.min_inliers = 0;
  o.min_inlier_ratio = 0.0;
  o.min_spread = 0.0;
  o.max_spacing_s = 10.5 * kFrameNs * 1e-9;
  KeyframePolicy policy(o, kWidth, kHeight);
  policy.reset(100, 0);
  const Spread s(100);
  for (int f = 1; f <= 10; ++f) {
    EXPECT_EQ(policy.decide(evidence(s, nullptr, f)), KeyframeReason::kNone) << f;
    policy.on_frame(evidence(s, nullptr, f), false);
  }
  EXPECT_EQ(policy.decide(evidence(s, nullptr, 11)), KeyframeReason::kMaxSpacing);
}

TEST(KeyframePolicy, ParallaxGateHoldsAllButTheCountUntilTheCameraHasMoved) {
  KeyframePolicyOptions o;
  o.min_inliers = 50;
  o.min_inlier_ratio = 0.6;
  o.min_spread = 0.4;
  o.min_spacing_s = 0.0;
  o.min_baseline_ratio = 0.03;
  KeyframePolicy policy(o, kWidth, kHeight);
  const Eigen::Vector3d start(1.0, 2.0, 0.5);
  policy.reset(300, 0, start);
  // Bunched-up inliers, fewer than 0.6 of the keyframe's: spread and ratio would both fire.
  // (The spreads outlive the evidence that points into them.)
  const Spread bunched(120, kWidth / 4.0F, kHeight);
  KeyframeEvidence e = evidence(bunched, nullptr);
  e.median_depth = 2.0;
  e.centre_w = start + Eigen::Vector3d(0.05, 0.0, 0.0);  // 0.05 / 2 = 0.025 < 0.03
  EXPECT_EQ(policy.decide(e), KeyframeReason::kNone);
  EXPECT_NEAR(policy.last_baseline_ratio(), 0.025, 1e-12);
  e.centre_w = start + Eigen::Vector3d(0.0, 0.0, 0.07);  // 0.035: the gate opens
  EXPECT_EQ(policy.decide(e), KeyframeReason::kTooFewInliers);
  // The absolute count is not gated: losing the map must still make a keyframe.
  const Spread forty(40);
  KeyframeEvidence few = evidence(forty, nullptr);
  few.median_depth = 2.0;
  few.centre_w = start;
  EXPECT_EQ(policy.decide(few), KeyframeReason::kTooFewInliers);
  // Unknown depth (<= 0) means no gate.
  e.centre_w = start;
  e.median_depth = 0.0;
  EXPECT_EQ(policy.decide(e), KeyframeReason::kTooFewInliers);
  // The gate measures from the newest keyframe's centre.
  e.median_depth = 2.0;
  e.centre_w = start + Eigen::Vector3d(0.1, 0.0, 0.0);
  policy.on_frame(e, true);
  e.inliers = 120;
  EXPECT_EQ(policy.decide(e), KeyframeReason::kNone);  // 0 baseline from the new keyframe
  e.centre_w = start + Eigen::Vector3d(0.1, 0.08, 0.0);
  EXPECT_EQ(policy.decide(e), KeyframeReason::kPoorSpread);
}

TEST(KeyframePolicy, RgbdTakesItsOwnMaxSpacingAndNoParallaxGate) {
  KeyframePolicyOptions o;
  o.max_spacing_s = 1.5;
  o.rgbd_max_spacing_s = 0.5;
  o.min_baseline_ratio = 0.03;
  const KeyframePolicyOptions mono = o.for_mode(SensorMode::kMono);
  EXPECT_EQ(mono.max_spacing_s, 1.5);
  EXPECT_EQ(mono.min_baseline_ratio, 0.03);
  const KeyframePolicyOptions rgbd = o.for_mode(SensorMode::kRgbd);
  EXPECT_EQ(rgbd.max_spacing_s, 0.5);
  EXPECT_EQ(rgbd.min_baseline_ratio, 0.0);
  // In effect: 16 frames at 30 Hz (0.53 s) without any other criterion make a keyframe.
  KeyframePolicyOptions quiet = o;
  quiet.min_inliers = 0;
  quiet.min_inlier_ratio = 0.0;
  quiet.min_spread = 0.0;
  KeyframePolicy policy(quiet.for_mode(SensorMode::kRgbd), kWidth, kHeight);
  policy.reset(100, 0);
  EXPECT_EQ(policy.decide(evidence(Spread(100), nullptr, 15)), KeyframeReason::kNone);
  EXPECT_EQ(policy.decide(evidence(Spread(100), nullptr, 16)), KeyframeReason::kMaxSpacing);
}

}  // namespace
}  // namespace mer::frontend
