// Association, Umeyama alignment, ATE and RPE on synthetic trajectories.
#include "eval/trajectory_eval.h"

#include <cmath>
#include <numbers>

#include <gtest/gtest.h>

namespace mer::eval {
namespace {

/// A curvy 3D path of `n` poses at 30 Hz starting at t0, rotating about all axes.
hal::Trajectory curvy(std::size_t n, std::int64_t t0_ns = 1'000'000'000) {
  hal::Trajectory t;
  for (std::size_t i = 0; i < n; ++i) {
    const double s = static_cast<double>(i) * 0.05;
    const Eigen::Vector3d p(3.0 * std::cos(s), 2.0 * std::sin(1.3 * s), 0.5 * s);
    const Eigen::Quaterniond q = Eigen::AngleAxisd(s, Eigen::Vector3d::UnitZ()) *
                                 Eigen::AngleAxisd(0.3 * s, Eigen::Vector3d::UnitX());
    t.poses.push_back({t0_ns + static_cast<std::int64_t>(i) * 33'333'333, make_se3(q, p)});
  }
  return t;
}

hal::Trajectory transformed(const hal::Trajectory& in, const Sim3& s) {
  hal::Trajectory out = in;
  for (auto& p : out.poses) p.T_w_c = s.apply(p.T_w_c);
  return out;
}

RpeOptions by_frames(std::size_t n) {
  RpeOptions o;
  o.delta_frames = n;
  return o;
}

RpeOptions by_metres(double m) {
  RpeOptions o;
  o.delta_m = m;
  return o;
}

Sim3 known_sim3(double scale) {
  Sim3 s;
  s.R = Eigen::AngleAxisd(0.7, Eigen::Vector3d(1.0, -2.0, 0.5).normalized()).toRotationMatrix();
  s.t = Eigen::Vector3d(4.0, -1.5, 2.25);
  s.scale = scale;
  return s;
}

TEST(Alignment, ParseAndName) {
  EXPECT_EQ(parse_alignment("sim3"), Alignment::kSim3);
  EXPECT_EQ(parse_alignment("se3"), Alignment::kSe3);
  EXPECT_EQ(parse_alignment("none"), Alignment::kNone);
  EXPECT_EQ(parse_alignment("rotation"), Alignment::kRotation);
  EXPECT_STREQ(alignment_name(Alignment::kRotation), "rotation");
  EXPECT_FALSE(parse_alignment("SE3").has_value());
  EXPECT_STREQ(alignment_name(Alignment::kSim3), "sim3");
}

TEST(Ate, Sim3RecoversKnownTransformExactly) {
  const hal::Trajectory gt = curvy(300);
  // est = S^-1 * gt, so aligning est onto gt must recover S (scale 1/0.37 -> 2.7027...).
  const Sim3 s = known_sim3(0.37);
  const hal::Trajectory est = transformed(gt, s);
  const auto pairs = associate(gt, est, 1'000'000);
  ASSERT_EQ(pairs.size(), 300u);
  const EvalResult r = evaluate(gt, est, pairs, Alignment::kSim3);
  EXPECT_LT(r.ate_rmse_m, 1e-9);
  EXPECT_LT(r.ate_max_m, 1e-9);
  EXPECT_NEAR(r.scale, 1.0 / 0.37, 1e-9);
  // RPE of a perfectly aligned copy is zero too.
  const EvalResult rf = evaluate(gt, est, pairs, Alignment::kSim3, by_frames(10));
  EXPECT_GT(rf.rpe_segments, 0u);
  EXPECT_LT(rf.rpe_trans_pct, 1e-6);
  EXPECT_LT(rf.rpe_rot_deg_per_m, 1e-6);
}

TEST(Ate, Se3OfScaledCopyLeavesLargeError) {
  const hal::Trajectory gt = curvy(300);
  const hal::Trajectory est = transformed(gt, known_sim3(0.37));
  const auto pairs = associate(gt, est, 1'000'000);
  const EvalResult se3 = evaluate(gt, est, pairs, Alignment::kSe3);
  EXPECT_DOUBLE_EQ(se3.scale, 1.0);
  EXPECT_GT(se3.ate_rmse_m, 0.5);
  // Rigid copy: SE(3) is exact, no alignment is not.
  const hal::Trajectory rigid = transformed(gt, known_sim3(1.0));
  const EvalResult ok = evaluate(gt, rigid, pairs, Alignment::kSe3);
  EXPECT_LT(ok.ate_rmse_m, 1e-9);
  const EvalResult none = evaluate(gt, rigid, pairs, Alignment::kNone);
  EXPECT_GT(none.ate_rmse_m, 1.0);
}

TEST(Ate, StatisticsOfKnownOffsets) {
  // Errors 1, 2, 3, 4 (m) along x with no alignment.
  hal::Trajectory gt = curvy(4);
  hal::Trajectory est = gt;
  for (std::size_t i = 0; i < 4; ++i) {
    est.poses[i].T_w_c.translation().x() += static_cast<double>(i + 1);
  }
  const EvalResult r = evaluate(gt, est, associate_by_index(gt, est), Alignment::kNone);
  EXPECT_EQ(r.pairs, 4u);
  EXPECT_NEAR(r.ate_rmse_m, std::sqrt(30.0 / 4.0), 1e-12);
  EXPECT_NEAR(r.ate_mean_m, 2.5, 1e-12);
  EXPECT_NEAR(r.ate_median_m, 2.5, 1e-12);
  EXPECT_NEAR(r.ate_max_m, 4.0, 1e-12);
}

TEST(Are, RotationAlignmentRecoversTheOrientationsOfAPoseLessEstimate) {
  // Orientations only (positions zero), in a world rotated by a known R: the rotation
  // alignment must find R from the orientations and leave no rotation error; the known
  // per-frame errors added afterwards come back as RMS and max.
  const hal::Trajectory gt = curvy(120);
  const Sim3 s = known_sim3(1.0);
  hal::Trajectory est = gt;
  for (auto& p : est.poses) {
    p.T_w_c.linear() = s.R * p.T_w_c.linear();
    p.T_w_c.translation().setZero();
  }
  const auto pairs = associate_by_index(gt, est);
  EXPECT_TRUE(align_orientations(gt, est, pairs).isApprox(s.R.transpose(), 1e-12));
  const EvalResult r = evaluate(gt, est, pairs, Alignment::kRotation);
  EXPECT_LT(r.are_rmse_deg, 1e-6);
  EXPECT_LT(r.are_max_deg, 1e-6);
  EXPECT_DOUBLE_EQ(r.scale, 1.0);
  // Alternate +-0.5 deg about z on every frame: RMS and max are 0.5 deg (the mean rotation
  // stays the truth).
  for (std::size_t i = 0; i < est.poses.size(); ++i) {
    const double a = (i % 2 == 0 ? 0.5 : -0.5) * std::numbers::pi / 180.0;
    est.poses[i].T_w_c.linear() =
        est.poses[i].T_w_c.linear() * Eigen::AngleAxisd(a, Eigen::Vector3d::UnitZ()).matrix();
  }
  const EvalResult e = evaluate(gt, est, pairs, Alignment::kRotation);
  EXPECT_NEAR(e.are_rmse_deg, 0.5, 0.02);
  EXPECT_NEAR(e.are_max_deg, 0.5, 0.04);
  // The position-based alignments report the rotation error too: a perfect Sim(3) copy has
  // none.
  const hal::Trajectory copy = transformed(gt, known_sim3(0.37));
  const EvalResult c = evaluate(gt, copy, pairs, Alignment::kSim3);
  EXPECT_LT(c.are_rmse_deg, 1e-6);
}

TEST(Associate, NearestWithinMaxDtAndOffsets) {
  hal::Trajectory gt = curvy(100);  // 33.3 ms spacing
  hal::Trajectory est;
  // Offsets from gt samples: +5 ms (pairs), -12 ms (pairs at 20 ms), +25 ms (nearest is the
  // next sample, 8.3 ms away), +16.6 ms (outside 10 ms of either neighbour).
  const std::int64_t offsets[] = {5'000'000, -12'000'000, 25'000'000, 16'666'666};
  for (std::size_t k = 0; k < 4; ++k) {
    const std::size_t g = 10 + 20 * k;
    est.poses.push_back({gt.poses[g].t_ns + offsets[k], gt.poses[g].T_w_c});
  }
  const auto p20 = associate(gt, est, 20'000'000);
  ASSERT_EQ(p20.size(), 4u);
  EXPECT_EQ(p20[0].gt, 10u);
  EXPECT_EQ(p20[1].gt, 30u);
  EXPECT_EQ(p20[2].gt, 51u);  // nearest, not the one it was copied from
  EXPECT_EQ(p20[3].gt, 70u);
  for (std::size_t k = 0; k < 4; ++k) EXPECT_EQ(p20[k].est, k);

  const auto p10 = associate(gt, est, 10'000'000);
  ASSERT_EQ(p10.size(), 2u);
  EXPECT_EQ(p10[0].gt, 10u);
  EXPECT_EQ(p10[1].gt, 51u);

  // A whole-trajectory time offset beyond max-dt: nothing associates.
  hal::Trajectory late = gt;
  for (auto& p : late.poses) p.t_ns += 15'000'000;
  EXPECT_TRUE(associate(gt, late, 10'000'000).empty());
  EXPECT_EQ(associate(gt, late, 16'000'000).size(), 100u);
}

TEST(Associate, BoundaryInclusiveAndTieTakesEarlier) {
  hal::Trajectory gt;
  gt.poses.push_back({0, SE3d::Identity()});
  gt.poses.push_back({20'000'000, SE3d::Identity()});
  gt.poses.push_back({40'000'000, SE3d::Identity()});
  hal::Trajectory est;
  est.poses.push_back({10'000'000, SE3d::Identity()});  // tie between 0 and 20 ms
  est.poses.push_back({60'000'000, SE3d::Identity()});  // exactly 20 ms after the last
  const auto p = associate(gt, est, 20'000'000);
  ASSERT_EQ(p.size(), 2u);
  EXPECT_EQ(p[0].gt, 0u);
  EXPECT_EQ(p[1].gt, 2u);
  EXPECT_EQ(associate(gt, est, 19'999'999).size(), 1u);
}

TEST(Associate, OneToOneClosestWins) {
  // Two estimates nearest to the same ground-truth sample: the closer one takes it, the
  // other falls back to its next-nearest sample when that is within max-dt, else is dropped.
  hal::Trajectory gt;
  gt.poses.push_back({0, SE3d::Identity()});
  gt.poses.push_back({100'000'000, SE3d::Identity()});
  hal::Trajectory est;
  est.poses.push_back({96'000'000, SE3d::Identity()});   // 4 ms before gt[1]
  est.poses.push_back({103'000'000, SE3d::Identity()});  // 3 ms after gt[1]: wins it
  const auto p = associate(gt, est, 20'000'000);
  ASSERT_EQ(p.size(), 1u);
  EXPECT_EQ(p[0].est, 1u);
  EXPECT_EQ(p[0].gt, 1u);
  // With a wide window the loser pairs with gt[0] instead; pairs sorted by estimate.
  const auto w = associate(gt, est, 200'000'000);
  ASSERT_EQ(w.size(), 2u);
  EXPECT_EQ(w[0].est, 0u);
  EXPECT_EQ(w[0].gt, 0u);
  EXPECT_EQ(w[1].gt, 1u);
}

TEST(Associate, ByIndexUsesShorterLength) {
  const hal::Trajectory a = curvy(10);
  const hal::Trajectory b = curvy(7);
  const auto p = associate_by_index(a, b);
  ASSERT_EQ(p.size(), 7u);
  EXPECT_EQ(p[6].gt, 6u);
  EXPECT_EQ(p[6].est, 6u);
}

TEST(Rpe, KnownDriftPerMetre) {
  // Straight line along x, 1 m per frame; the estimate moves 1.02 m per frame (2 % drift).
  hal::Trajectory gt;
  hal::Trajectory est;
  for (int i = 0; i < 200; ++i) {
    gt.poses.push_back({i, make_se3(Eigen::Quaterniond::Identity(), {1.0 * i, 0, 0})});
    est.poses.push_back({i, make_se3(Eigen::Quaterniond::Identity(), {1.02 * i, 0, 0})});
  }
  const auto pairs = associate_by_index(gt, est);
  const EvalResult r = evaluate(gt, est, pairs, Alignment::kNone, by_metres(100.0));
  EXPECT_EQ(r.rpe_segments, 100u);  // starts 0..99 reach 100 m
  EXPECT_NEAR(r.rpe_trans_pct, 2.0, 1e-9);
  EXPECT_NEAR(r.rpe_rot_deg_per_m, 0.0, 1e-9);
  const EvalResult f = evaluate(gt, est, pairs, Alignment::kNone, by_frames(10));
  EXPECT_EQ(f.rpe_segments, 190u);
  EXPECT_NEAR(f.rpe_trans_pct, 2.0, 1e-9);
  // Too long a delta: no segment, reported as null in JSON.
  const EvalResult none = evaluate(gt, est, pairs, Alignment::kNone, by_metres(1000.0));
  EXPECT_EQ(none.rpe_segments, 0u);
  EXPECT_NE(to_json(none).find("\"rpe_trans_pct\": null"), std::string::npos);
}

TEST(Rpe, RotationDriftInDegreesPerMetre) {
  // Same positions, the estimate yaws 0.01 rad more per metre.
  hal::Trajectory gt;
  hal::Trajectory est;
  for (int i = 0; i < 50; ++i) {
    gt.poses.push_back({i, make_se3(Eigen::Quaterniond::Identity(), {1.0 * i, 0, 0})});
    const Eigen::Quaterniond q(Eigen::AngleAxisd(0.01 * i, Eigen::Vector3d::UnitZ()));
    est.poses.push_back({i, make_se3(q, {1.0 * i, 0, 0})});
  }
  const EvalResult r =
      evaluate(gt, est, associate_by_index(gt, est), Alignment::kNone, by_frames(5));
  EXPECT_NEAR(r.rpe_rot_deg_per_m, 0.01 * 180.0 / std::numbers::pi, 1e-9);
}

TEST(Json, HasAllKeys) {
  const hal::Trajectory gt = curvy(50);
  const EvalResult r = evaluate(gt, gt, associate_by_index(gt, gt), Alignment::kSim3);
  const std::string j = to_json(r);
  for (const char* k : {"\"pairs\": 50", "\"align\": \"sim3\"", "\"scale\"", "\"ate_rmse_m\"",
                        "\"ate_mean_m\"", "\"ate_median_m\"", "\"ate_max_m\"", "\"rpe_trans_pct\"",
                        "\"rpe_rot_deg_per_m\"", "\"are_rmse_deg\"", "\"are_max_deg\""}) {
    EXPECT_NE(j.find(k), std::string::npos) << k << " missing in " << j;
  }
}

}  // namespace
}  // namespace mer::eval
