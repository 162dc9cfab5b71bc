#pragma once
/// @file cli.h
/// Command line of mer_slam (a stable contract; later features add flags, never change them):
///
///   mer_slam [--config FILE] [--board FILE] [--input URI] [--output DIR] [--mode mono|rgbd]
///            [--lockstep] [--max-frames N] [--intrinsics fx,fy,cx,cy[,k1,k2,p1,p2]]
///            [--focal auto|fixed] [--final-ba] [--print-config] [--quiet] [--help] [--version]

#include <optional>
#include <string>
#include <vector>

#include "app/slam_config.h"
#include "core/status.h"

namespace mer::app {

/// The input used when --input is not given: the embedded synthetic camera.
inline constexpr const char* kDefaultInput = "synthetic:room_orbit";

/// Parsed command line (before it is applied to the configuration).
struct CliArgs {
  std::string config_file;                        ///< --config (empty: built-in defaults)
  std::string board_file;                         ///< --board (empty: none)
  std::string input = kDefaultInput;              ///< --input
  std::string output_dir;                         ///< --output (empty: no files)
  std::optional<std::string> mode;                ///< --mode
  bool lockstep = false;                          ///< --lockstep
  bool final_ba = false;                          ///< --final-ba
  bool gt_check = false;                          ///< --gt-check (needs --output)
  std::optional<int> max_frames;                  ///< --max-frames
  std::optional<std::vector<double>> intrinsics;  ///< --intrinsics (4 or 8 numbers)
  std::optional<std::string> focal;               ///< --focal
  bool print_config = false;                      ///< --print-config
  bool quiet = false;                             ///< --quiet: no human summary on stdout
  bool help = false;                              ///< --help
  bool version = false;                           ///< --version
};

/// Usage text.
std::string usage();

/// Parses argv. Errors name the flag and what was expected (exit code 2).
Result<CliArgs> parse_cli(int argc, const char* const* argv);

/// Builds the configuration: defaults, --config, --board, then flags; validates.
Status build_config(const CliArgs& args, SlamConfig& config);

/// Process exit code for a status: 0 ok, 2 usage/config, 3 input, 4 runtime.
int exit_code_for(const Status& s);

}  // namespace mer::app
