// Reproduces the published ATE figures of ../shared/data/README.md (evo's test data).
#include <cstdio>
#include <string>

#include <gtest/gtest.h>

#include "eval/trajectory_eval.h"
#include "eval_fixtures.h"
#include "hal/ground_truth.h"
#include "support/required_data.h"

namespace mer::eval {
namespace {

hal::Trajectory load_tum(const std::string& name) {
  auto r = hal::load_tum_trajectory(test::trajectories_dir() + "/" + name);
  EXPECT_TRUE(r.is_ok()) << r.status().message();
  return r.is_ok() ? std::move(r).value() : hal::Trajectory{};
}

hal::Trajectory load_kitti(const std::string& name) {
  auto r = hal::load_kitti_trajectory(test::trajectories_dir() + "/" + name);
  EXPECT_TRUE(r.is_ok()) << r.status().message();
  return r.is_ok() ? std::move(r).value() : hal::Trajectory{};
}

#define SKIP_WITHOUT_DATA()                                                                 \
  MER_REQUIRE_DATA(!test::trajectories_dir().empty())                                       \
      << "reference trajectories not found ($MER_SOURCE_DIR/../shared/data/trajectories); " \
         "set MER_SOURCE_DIR to the checkout"

void check_tum(double max_dt_s, std::size_t pairs, double rmse) {
  const hal::Trajectory gt = load_tum("fr2_desk_groundtruth.txt");
  const hal::Trajectory est = load_tum("fr2_desk_ORB.txt");
  EXPECT_EQ(gt.duplicates_dropped, 1u);  // the repeated timestamp; first sample kept
  const auto p = associate(gt, est, static_cast<std::int64_t>(max_dt_s * 1e9 + 0.5));
  const EvalResult r = evaluate(gt, est, p, Alignment::kSe3);
  std::printf("fr2_desk ORB se3 max_dt %.2f: pairs %zu ATE RMSE %.9f m (published %zu, %.6f)\n",
              max_dt_s, r.pairs, r.ate_rmse_m, pairs, rmse);
  EXPECT_EQ(r.pairs, pairs);
  EXPECT_NEAR(r.ate_rmse_m, rmse, 5e-7);
  EXPECT_DOUBLE_EQ(r.scale, 1.0);
}

void check_kitti(const std::string& est_name, double rmse) {
  const hal::Trajectory gt = load_kitti("KITTI_00_gt.txt");
  const hal::Trajectory est = load_kitti(est_name);
  const auto p = associate_by_index(gt, est);
  const EvalResult r = evaluate(gt, est, p, Alignment::kSe3);
  std::printf("KITTI_00 %s se3: pairs %zu ATE RMSE %.9f m (published 4541, %.7f)\n",
              est_name.c_str(), r.pairs, r.ate_rmse_m, rmse);
  EXPECT_EQ(r.pairs, 4541u);
  EXPECT_NEAR(r.ate_rmse_m, rmse, 5e-8);
}

TEST(ReferenceFigures, Fr2DeskOrbSe3MaxDt002) {
  SKIP_WITHOUT_DATA();
  check_tum(0.02, 2223, 0.008144);
}

TEST(ReferenceFigures, Fr2DeskOrbSe3MaxDt001) {
  SKIP_WITHOUT_DATA();
  check_tum(0.01, 2174, 0.008119);
}

TEST(ReferenceFigures, Kitti00OrbSe3) {
  SKIP_WITHOUT_DATA();
  check_kitti("KITTI_00_ORB.txt", 1.3034497);
}

TEST(ReferenceFigures, Kitti00SptamSe3) {
  SKIP_WITHOUT_DATA();
  check_kitti("KITTI_00_SPTAM.txt", 3.7384879);
}

}  // namespace
}  // namespace mer::eval
