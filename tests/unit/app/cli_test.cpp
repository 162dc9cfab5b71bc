// The CLI contract: flags, exit codes and error messages, tested on the real binary.
#include "app/cli.h"

#include <cstdlib>
#include <filesystem>
#include <fstream>

#include <gtest/gtest.h>

#include "support/run_command.h"

namespace mer::app {
namespace {

using mer::testing::quote;
using mer::testing::run_command;

const std::string kExe = MER_SLAM_EXE;

std::filesystem::path temp_dir(const char* name) {
  auto d = std::filesystem::temp_directory_path() / name;
  std::filesystem::remove_all(d);
  std::filesystem::create_directories(d);
  return d;
}

std::string write_config(const std::filesystem::path& dir, const std::string& text) {
  const auto p = dir / "cfg.yaml";
  std::ofstream(p) << text;
  return p.string();
}

TEST(CliParse, ParsesTheContractFlags) {
  const char* argv[] = {"mer_slam",
                        "--config",
                        "c.yaml",
                        "--input",
                        "kitti:/d",
                        "--output",
                        "o",
                        "--mode",
                        "rgbd",
                        "--lockstep",
                        "--max-frames",
                        "12",
                        "--intrinsics",
                        "500,501,320,240",
                        "--focal",
                        "auto"};
  auto r = parse_cli(static_cast<int>(std::size(argv)), argv);
  ASSERT_TRUE(r.is_ok()) << r.status().message();
  const CliArgs& a = r.value();
  EXPECT_EQ(a.config_file, "c.yaml");
  EXPECT_EQ(a.input, "kitti:/d");
  EXPECT_EQ(a.output_dir, "o");
  EXPECT_EQ(*a.mode, "rgbd");
  EXPECT_TRUE(a.lockstep);
  EXPECT_EQ(*a.max_frames, 12);
  ASSERT_EQ(a.intrinsics->size(), 4U);
  EXPECT_DOUBLE_EQ((*a.intrinsics)[1], 501.0);
  EXPECT_EQ(*a.focal, "auto");
}

TEST(CliParse, DefaultInputIsTheSyntheticCamera) {
  const char* argv[] = {"mer_slam"};
  auto r = parse_cli(1, argv);
  ASSERT_TRUE(r.is_ok());
  EXPECT_EQ(r.value().input, "synthetic:room_orbit");
}

TEST(CliParse, FlagsOverrideTheConfig) {
  const char* argv[] = {"mer_slam", "--max-frames", "7", "--intrinsics", "1,2,3,4,0.1,0.2,0.3,0.4"};
  auto r = parse_cli(static_cast<int>(std::size(argv)), argv);
  ASSERT_TRUE(r.is_ok());
  SlamConfig c;
  ASSERT_TRUE(build_config(r.value(), c).is_ok());
  EXPECT_EQ(c.pipeline.max_frames, 7);
  EXPECT_DOUBLE_EQ(c.camera.calibration.fx, 1.0);
  EXPECT_DOUBLE_EQ(c.camera.calibration.p2, 0.4);
}

TEST(CliParse, BadValuesNameTheFlag) {
  for (std::vector<const char*> argv :
       std::vector<std::vector<const char*>>{{"mer_slam", "--max-frames", "ten"},
                                             {"mer_slam", "--max-frames"},
                                             {"mer_slam", "--intrinsics", "1,2,3"},
                                             {"mer_slam", "--intrinsics", "1,2,x,4"},
                                             {"mer_slam", "--output", "--lockstep"},
                                             {"mer_slam", "--gt-check"}}) {
    auto r = parse_cli(static_cast<int>(argv.size()), argv.data());
    ASSERT_FALSE(r.is_ok()) << argv[1];
    EXPECT_EQ(r.status().code(), StatusCode::kInvalidArgument);
    EXPECT_NE(r.status().message().find(argv[1]), std::string::npos) << r.status().message();
  }
}

TEST(CliBinary, UnknownFlagExits2AndNamesIt) {
  const auto r = run_command(quote(kExe) + " --frobnicate");
  EXPECT_EQ(r.exit_code, 2) << r.output;
  EXPECT_NE(r.output.find("--frobnicate"), std::string::npos) << r.output;
}

TEST(CliBinary, MissingConfigValueExits2AndNamesTheKey) {
  const auto dir = temp_dir("mer_cli_missing");
  const std::string cfg = write_config(dir, "tracking:\n  extractor:\n    fast_threshold:\n");
  const auto r = run_command(quote(kExe) + " --config " + quote(cfg) + " --max-frames 1");
  EXPECT_EQ(r.exit_code, 2) << r.output;
  EXPECT_NE(r.output.find("tracking.extractor.fast_threshold"), std::string::npos) << r.output;
  EXPECT_NE(r.output.find(cfg), std::string::npos) << r.output;
  EXPECT_NE(r.output.find("found nothing"), std::string::npos) << r.output;
}

TEST(CliBinary, MalformedValueExits2AndNamesTheKey) {
  const auto dir = temp_dir("mer_cli_malformed");
  const std::string cfg = write_config(dir, "pipeline:\n  acquire_timeout_ms: soon\n");
  const auto r = run_command(quote(kExe) + " --config " + quote(cfg));
  EXPECT_EQ(r.exit_code, 2) << r.output;
  EXPECT_NE(r.output.find("pipeline.acquire_timeout_ms"), std::string::npos) << r.output;
  EXPECT_NE(r.output.find("expected an integer"), std::string::npos) << r.output;
  EXPECT_NE(r.output.find("'soon'"), std::string::npos) << r.output;
}

TEST(CliBinary, MapTableSizeMustBeAPowerOfTwo) {
  const auto dir = temp_dir("mer_cli_map_table");
  const std::string cfg = write_config(dir, "map:\n  cell_table_size: 1000\n");
  const auto r = run_command(quote(kExe) + " --config " + quote(cfg) + " --max-frames 1");
  EXPECT_EQ(r.exit_code, 2) << r.output;
  EXPECT_NE(r.output.find("map.cell_table_size"), std::string::npos) << r.output;
  EXPECT_NE(r.output.find("power of two"), std::string::npos) << r.output;
}

TEST(CliBinary, UnknownKeyAndOutOfRangeExit2) {
  const auto dir = temp_dir("mer_cli_unknown");
  std::string cfg = write_config(dir, "board:\n  capture_cores: 2\n");
  auto r = run_command(quote(kExe) + " --config " + quote(cfg));
  EXPECT_EQ(r.exit_code, 2) << r.output;
  EXPECT_NE(r.output.find("board.capture_cores"), std::string::npos) << r.output;
  cfg = write_config(dir, "camera:\n  pool_size: 1\n");
  r = run_command(quote(kExe) + " --config " + quote(cfg));
  EXPECT_EQ(r.exit_code, 2) << r.output;
  EXPECT_NE(r.output.find("camera.pool_size"), std::string::npos) << r.output;
}

TEST(CliBinary, MissingConfigFileExits2) {
  const auto r = run_command(quote(kExe) + " --config /nonexistent/mer.yaml");
  EXPECT_EQ(r.exit_code, 2) << r.output;
  EXPECT_NE(r.output.find("/nonexistent/mer.yaml"), std::string::npos) << r.output;
}

TEST(CliBinary, BadModeFlagExits2) {
  const auto r = run_command(quote(kExe) + " --mode stereo");
  EXPECT_EQ(r.exit_code, 2) << r.output;
  EXPECT_NE(r.output.find("pipeline.mode"), std::string::npos) << r.output;
}

TEST(CliBinary, InputErrorsExit2Or3) {
  auto r = run_command(quote(kExe) + " --input nosuch:thing");
  EXPECT_EQ(r.exit_code, 2) << r.output;
  r = run_command(quote(kExe) + " --input synthetic:no_such_scene");
  EXPECT_EQ(r.exit_code, 3) << r.output;
  EXPECT_NE(r.output.find("no_such_scene"), std::string::npos) << r.output;
}

TEST(CliBinary, PrintConfigLoadsBack) {
  const auto dir = temp_dir("mer_cli_print");
  const auto r = run_command(quote(kExe) + " --print-config --max-frames 5");
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_NE(r.output.find("max_frames: 5"), std::string::npos);
  const std::string cfg = write_config(dir, r.output);
  const auto r2 = run_command(quote(kExe) + " --config " + quote(cfg) + " --print-config");
  ASSERT_EQ(r2.exit_code, 0) << r2.output;
  EXPECT_EQ(r.output, r2.output);
}

TEST(CliBinary, ShippedConfigsLoad) {
  const char* src = std::getenv("MER_SOURCE_DIR");
  ASSERT_NE(src, nullptr);
  int n = 0;
  for (const auto& e :
       std::filesystem::recursive_directory_iterator(std::filesystem::path(src) / "configs")) {
    if (e.path().extension() != ".yaml") continue;
    const bool board = e.path().parent_path().filename() == "boards";
    const auto r = run_command(quote(kExe) + (board ? " --board " : " --config ") +
                               quote(e.path().string()) + " --print-config");
    EXPECT_EQ(r.exit_code, 0) << e.path() << "\n" << r.output;
    ++n;
  }
  EXPECT_GE(n, 2);
}

TEST(CliBinary, HelpAndVersion) {
  auto r = run_command(quote(kExe) + " --help");
  EXPECT_EQ(r.exit_code, 0);
  EXPECT_NE(r.output.find("--intrinsics"), std::string::npos);
  r = run_command(quote(kExe) + " --version");
  EXPECT_EQ(r.exit_code, 0);
  EXPECT_NE(r.output.find("mer_slam "), std::string::npos);
}

}  // namespace
}  // namespace mer::app

namespace mer::app {
namespace {
// configs/slam/default.yaml is the option reference: it must match the built-in defaults.
TEST(CliBinary, ShippedDefaultConfigMatchesBuiltInDefaults) {
  const char* src = std::getenv("MER_SOURCE_DIR");
  ASSERT_NE(src, nullptr);
  const auto r = run_command(quote(kExe) + " --print-config");
  ASSERT_EQ(r.exit_code, 0);
  const std::string shipped =
      mer::testing::read_text((std::filesystem::path(src) / "configs/slam/default.yaml").string());
  EXPECT_EQ(r.output, shipped)
      << "regenerate with: mer_slam --print-config > configs/slam/default.yaml";
}
}  // namespace
}  // namespace mer::app
