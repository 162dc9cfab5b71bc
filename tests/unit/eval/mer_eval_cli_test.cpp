// The mer_eval executable: output, exit codes, errors naming file and line.
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <string>

#include <gtest/gtest.h>

#include "eval_fixtures.h"
#include "support/required_data.h"
#include "support/run_command.h"

namespace mer::eval {
namespace {

using mer::testing::quote;
using mer::testing::run_command;

std::string exe() {
  return MER_EVAL_EXE;
}

std::string tmp_file(const std::string& name, const std::string& content) {
  const auto dir = std::filesystem::temp_directory_path() / "mer_eval_cli_test";
  std::filesystem::create_directories(dir);
  const auto p = dir / name;
  std::ofstream(p) << content;
  return p.string();
}

TEST(MerEvalCli, UsageErrorsExit2) {
  EXPECT_EQ(run_command(exe()).exit_code, 2);
  EXPECT_EQ(run_command(exe() + " --gt a --est b --align foo").exit_code, 2);
  EXPECT_EQ(run_command(exe() + " --gt a --est b --format csv").exit_code, 2);
  EXPECT_EQ(run_command(exe() + " --gt a --est b --max-dt x").exit_code, 2);
  EXPECT_EQ(run_command(exe() + " --bogus").exit_code, 2);
  EXPECT_EQ(run_command(exe() + " --help").exit_code, 0);
}

TEST(MerEvalCli, MalformedFileExit3NamesFileAndLine) {
  const std::string gt = tmp_file("gt.txt", "1.0 0 0 0 0 0 0 1\n2.0 0 0 0 0 0 0 1\n");
  const std::string bad = tmp_file("bad.txt", "1.0 0 0 0 0 0 0 1\n2.0 0 0 zz 0 0 0 1\n");
  const auto r = run_command(exe() + " --gt " + quote(gt) + " --est " + quote(bad));
  EXPECT_EQ(r.exit_code, 3) << r.output;
  EXPECT_NE(r.output.find("bad.txt"), std::string::npos) << r.output;
  EXPECT_NE(r.output.find('2'), std::string::npos) << r.output;
  const auto missing = run_command(exe() + " --gt /nonexistent/gt.txt --est " + quote(gt));
  EXPECT_EQ(missing.exit_code, 3) << missing.output;
  EXPECT_NE(missing.output.find("/nonexistent/gt.txt"), std::string::npos) << missing.output;
}

TEST(MerEvalCli, NoPairsExit4) {
  const std::string gt = tmp_file("gt4.txt", "1.0 0 0 0 0 0 0 1\n2.0 1 0 0 0 0 0 1\n");
  const std::string est = tmp_file("est4.txt", "5.0 0 0 0 0 0 0 1\n6.0 1 0 0 0 0 0 1\n");
  const auto r = run_command(exe() + " --gt " + quote(gt) + " --est " + quote(est));
  EXPECT_EQ(r.exit_code, 4) << r.output;
}

TEST(MerEvalCli, JsonOnReferenceData) {
  const std::string dir = test::trajectories_dir();
  MER_REQUIRE_DATA(!dir.empty()) << "reference trajectories not found (set MER_SOURCE_DIR)";
  const auto r =
      run_command(exe() + " --gt " + quote(dir + "/fr2_desk_groundtruth.txt") + " --est " +
                  quote(dir + "/fr2_desk_ORB.txt") + " --align se3 --max-dt 0.02 --json");
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_NE(r.output.find("\"pairs\": 2223"), std::string::npos) << r.output;
  EXPECT_NE(r.output.find("\"ate_rmse_m\": 0.00814"), std::string::npos) << r.output;
  const auto k = run_command(exe() + " --gt " + quote(dir + "/KITTI_00_gt.txt") + " --est " +
                             quote(dir + "/KITTI_00_ORB.txt") + " --format kitti");
  ASSERT_EQ(k.exit_code, 0) << k.output;
  EXPECT_NE(k.output.find("pairs:      4541"), std::string::npos) << k.output;
  EXPECT_NE(k.output.find("1.3034497"), std::string::npos) << k.output;
}

}  // namespace
}  // namespace mer::eval
