#include "app/cli.h"

#include <charconv>
#include <cstring>
#include <sstream>

#include "core/config_io.h"

namespace mer::app {
namespace {

bool parse_int(const std::string& s, int& out) {
  const char* end = s.data() + s.size();
  auto [p, ec] = std::from_chars(s.data(), end, out);
  return ec == std::errc() && p == end;
}

bool parse_double_list(const std::string& s, std::vector<double>& out) {
  std::stringstream ss(s);
  std::string item;
  while (std::getline(ss, item, ',')) {
    char* end = nullptr;
    const double v = std::strtod(item.c_str(), &end);
    if (item.empty() || end != item.c_str() + item.size()) return false;
    out.push_back(v);
  }
  return !s.empty() && s.back() != ',';
}

}  // namespace

std::string usage() {
  return R"(usage: mer_slam [options]

  --config FILE      YAML configuration (default: built-in; see --print-config)
  --board FILE       board profile YAML: thread cores/priorities, budgets (configs/boards/)
  --input URI        frame source (default: synthetic:room_orbit):
                       synthetic:NAME  tum:DIR  euroc:DIR  kitti:DIR  rec:FILE
                       v4l2:/dev/videoN  libcamera:ID
  --output DIR       write trajectory.txt, keyframes.txt, keyframes_final.txt,
                     frames.csv, latency.csv, summary.json into DIR (created if
                     missing)
  --mode mono|rgbd   sensor mode (rgbd needs a source with depth)
  --lockstep         deterministic sequential replay: no drops, as fast as possible
  --max-frames N     stop after N frames from the source
  --intrinsics fx,fy,cx,cy[,k1,k2,p1,p2]
                     calibration override (pixels; radtan distortion)
  --focal auto|fixed estimate the focal length (auto) or trust the calibration
  --final-ba         after the stream, optimize the whole graph (trajectory_final.txt
                     and keyframes_final.txt then carry its result)
  --gt-check         after the outputs are written, check the final map's observations
                     against the ground truth (needs --output and a source with ground
                     truth; keyframes_gt_converged.txt, keyframes_gt_shuffled.txt)
  --print-config     print the effective configuration as YAML and exit
  --quiet            no human-readable summary on stdout
  --help, --version

exit codes: 0 success, 2 usage or configuration error, 3 input error, 4 runtime failure
)";
}

Result<CliArgs> parse_cli(int argc, const char* const* argv) {
  CliArgs a;
  for (int i = 1; i < argc; ++i) {
    const std::string flag = argv[i];
    auto value = [&](std::string& out) -> Status {
      if (i + 1 >= argc || std::strncmp(argv[i + 1], "--", 2) == 0) {
        return invalid_argument("flag '" + flag + "': expected a value, found nothing");
      }
      out = argv[++i];
      return Status::ok();
    };
    std::string v;
    Status s;
    if (flag == "--help" || flag == "-h") {
      a.help = true;
    } else if (flag == "--version") {
      a.version = true;
    } else if (flag == "--lockstep") {
      a.lockstep = true;
    } else if (flag == "--print-config") {
      a.print_config = true;
    } else if (flag == "--quiet") {
      a.quiet = true;
    } else if (flag == "--config") {
      s = value(a.config_file);
    } else if (flag == "--board") {
      s = value(a.board_file);
    } else if (flag == "--input") {
      s = value(a.input);
    } else if (flag == "--output") {
      s = value(a.output_dir);
    } else if (flag == "--mode") {
      if (s = value(v); s.is_ok()) a.mode = v;
    } else if (flag == "--final-ba") {
      a.final_ba = true;
    } else if (flag == "--gt-check") {
      a.gt_check = true;
    } else if (flag == "--focal") {
      if (s = value(v); s.is_ok()) a.focal = v;
    } else if (flag == "--max-frames") {
      if (s = value(v); s.is_ok()) {
        int n = 0;
        if (!parse_int(v, n) || n < 0) {
          return invalid_argument("flag '--max-frames': expected a non-negative integer, found '" +
                                  v + "'");
        }
        a.max_frames = n;
      }
    } else if (flag == "--intrinsics") {
      if (s = value(v); s.is_ok()) {
        std::vector<double> k;
        if (!parse_double_list(v, k) || (k.size() != 4 && k.size() != 8)) {
          return invalid_argument(
              "flag '--intrinsics': expected fx,fy,cx,cy or fx,fy,cx,cy,k1,k2,p1,p2, found '" + v +
              "'");
        }
        a.intrinsics = k;
      }
    } else {
      return invalid_argument("unknown flag '" + flag + "' (see --help)");
    }
    if (!s.is_ok()) return s;
  }
  if (a.gt_check && a.output_dir.empty() && !a.help && !a.version && !a.print_config) {
    return invalid_argument("flag '--gt-check' needs --output DIR (it scores files written there)");
  }
  return a;
}

Status build_config(const CliArgs& args, SlamConfig& config) {
  if (!args.config_file.empty()) {
    if (Status s = options::load_yaml_file(args.config_file, config); !s.is_ok()) return s;
  }
  if (!args.board_file.empty()) {
    if (Status s = options::load_yaml_file(args.board_file, config.board); !s.is_ok()) return s;
  }
  if (args.mode) {
    const Status s =
        options::set_by_name("pipeline.mode", *args.mode,
                             options::Names<SensorMode>{kSensorModeNames}, config.pipeline.mode);
    if (!s.is_ok()) return Status(s.code(), "command line: " + s.message());
  }
  if (args.lockstep) config.pipeline.lockstep = true;
  if (args.max_frames) config.pipeline.max_frames = *args.max_frames;
  if (args.focal) {
    const Status s = options::set_by_name(
        "pipeline.focal", *args.focal,
        options::Names<pipeline::FocalMode>{pipeline::kFocalModeNames}, config.pipeline.focal);
    if (!s.is_ok()) return Status(s.code(), "command line: " + s.message());
  }
  if (args.final_ba) config.pipeline.final_ba = true;
  if (args.intrinsics) {
    const auto& k = *args.intrinsics;
    auto& c = config.camera.calibration;
    c.fx = k[0];
    c.fy = k[1];
    c.cx = k[2];
    c.cy = k[3];
    if (k.size() == 8) {
      c.k1 = k[4];
      c.k2 = k[5];
      c.p1 = k[6];
      c.p2 = k[7];
    }
  }
  Status s = options::validate(config);
  if (!s.is_ok()) return Status(s.code(), "command line: " + s.message());
  return Status::ok();
}

int exit_code_for(const Status& s) {
  switch (s.code()) {
    case StatusCode::kOk:
    case StatusCode::kEndOfStream:
      return 0;
    case StatusCode::kInvalidArgument:
      return 2;
    case StatusCode::kInputError:
    case StatusCode::kUnavailable:
      return 3;
    default:
      return 4;
  }
}

}  // namespace mer::app
