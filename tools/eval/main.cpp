// mer_eval: scores an estimated trajectory against ground truth (ATE with Umeyama alignment,
// RPE). Exit codes: 0 ok, 2 usage, 3 unreadable or malformed file, 4 no associated pairs.
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <optional>
#include <string>
#include <string_view>

#include "eval/trajectory_eval.h"
#include "hal/ground_truth.h"

namespace {

constexpr int kExitOk = 0;
constexpr int kExitUsage = 2;
constexpr int kExitInput = 3;
constexpr int kExitNoPairs = 4;

void print_usage(std::FILE* f) {
  std::fprintf(
      f,
      "usage: mer_eval --gt FILE --est FILE [--align sim3|se3|none|rotation] [--max-dt SEC]\n"
      "                [--format tum|kitti] [--rpe-delta-m M | --rpe-delta-frames N] [--json]\n"
      "  --align             alignment of the estimate to the ground truth (default se3);\n"
      "                      rotation: fitted to the orientations alone (orientation.txt)\n"
      "  --max-dt            TUM association: max |dt| in seconds (default 0.02)\n"
      "  --format            tum (timestamps, nearest-time association; default) or kitti\n"
      "                      (12 numbers per line, no timestamps, matched by index)\n"
      "  --rpe-delta-m       RPE segment length along the ground truth, metres (default 100)\n"
      "  --rpe-delta-frames  RPE segment length in associated pairs (overrides --rpe-delta-m)\n"
      "  --json              print one JSON object instead of the text summary\n");
}

std::optional<double> parse_double(const std::string& s) {
  char* end = nullptr;
  const double v = std::strtod(s.c_str(), &end);
  if (s.empty() || end != s.c_str() + s.size() || !std::isfinite(v)) return std::nullopt;
  return v;
}

int usage_error(const std::string& msg) {
  std::fprintf(stderr, "mer_eval: %s\n", msg.c_str());
  print_usage(stderr);
  return kExitUsage;
}

}  // namespace

int main(int argc, char** argv) {
  using namespace mer;
  std::string gt_path;
  std::string est_path;
  std::string format = "tum";
  eval::Alignment align = eval::Alignment::kSe3;
  double max_dt = 0.02;
  eval::RpeOptions rpe;
  bool json = false;

  for (int i = 1; i < argc; ++i) {
    const std::string_view a = argv[i];
    auto value = [&](std::string& out) -> bool {
      if (i + 1 >= argc) return false;
      out = argv[++i];
      return true;
    };
    std::string v;
    if (a == "--help" || a == "-h") {
      print_usage(stdout);
      return kExitOk;
    } else if (a == "--json") {
      json = true;
    } else if (a == "--gt") {
      if (!value(gt_path)) return usage_error("--gt needs a file");
    } else if (a == "--est") {
      if (!value(est_path)) return usage_error("--est needs a file");
    } else if (a == "--align") {
      if (!value(v)) return usage_error("--align needs sim3, se3, none or rotation");
      const auto p = eval::parse_alignment(v);
      if (!p) return usage_error("--align: unknown alignment '" + v + "'");
      align = *p;
    } else if (a == "--max-dt") {
      if (!value(v)) return usage_error("--max-dt needs seconds");
      const auto d = parse_double(v);
      if (!d || *d < 0.0) return usage_error("--max-dt: bad value '" + v + "'");
      max_dt = *d;
    } else if (a == "--format") {
      if (!value(format) || (format != "tum" && format != "kitti")) {
        return usage_error("--format needs tum or kitti");
      }
    } else if (a == "--rpe-delta-m") {
      if (!value(v)) return usage_error("--rpe-delta-m needs metres");
      const auto d = parse_double(v);
      if (!d || *d <= 0.0) return usage_error("--rpe-delta-m: bad value '" + v + "'");
      rpe.delta_m = *d;
    } else if (a == "--rpe-delta-frames") {
      if (!value(v)) return usage_error("--rpe-delta-frames needs a count");
      const auto d = parse_double(v);
      if (!d || *d < 1.0 || std::floor(*d) != *d) {
        return usage_error("--rpe-delta-frames: bad value '" + v + "'");
      }
      rpe.delta_frames = static_cast<std::size_t>(*d);
    } else {
      return usage_error("unknown argument '" + std::string(a) + "'");
    }
  }
  if (gt_path.empty() || est_path.empty()) return usage_error("--gt and --est are required");

  const bool kitti = format == "kitti";
  auto load = [&](const std::string& p) {
    return kitti ? hal::load_kitti_trajectory(p) : hal::load_tum_trajectory(p);
  };
  auto gt = load(gt_path);
  if (!gt.is_ok()) {
    std::fprintf(stderr, "mer_eval: %s\n", gt.status().message().c_str());
    return kExitInput;
  }
  auto est = load(est_path);
  if (!est.is_ok()) {
    std::fprintf(stderr, "mer_eval: %s\n", est.status().message().c_str());
    return kExitInput;
  }
  for (const hal::Trajectory* t : {&gt.value(), &est.value()}) {
    if (t->duplicates_dropped > 0 && !json) {
      std::fprintf(stderr, "mer_eval: %s: dropped %zu repeated timestamp(s), first at line %d\n",
                   t->source.c_str(), t->duplicates_dropped, t->first_duplicate_line);
    }
  }

  const auto pairs = kitti ? eval::associate_by_index(gt.value(), est.value())
                           : eval::associate(gt.value(), est.value(),
                                             static_cast<std::int64_t>(std::llround(max_dt * 1e9)));
  if (pairs.empty()) {
    std::fprintf(stderr, "mer_eval: no pose of %s associates with %s (max-dt %g s)\n",
                 est_path.c_str(), gt_path.c_str(), max_dt);
    return kExitNoPairs;
  }
  const eval::EvalResult r = eval::evaluate(gt.value(), est.value(), pairs, align, rpe);
  if (json) {
    std::printf("%s\n", eval::to_json(r).c_str());
  } else {
    std::printf("%s", eval::to_text(r).c_str());
  }
  return kExitOk;
}
