// Fuzz target: the dataset text parsers (hal/replay/dataset_parsers.h). Every parser gets
// every input; besides not crashing, a successful parse must honour the documented
// contract (finite numbers, strictly increasing timestamps, non-empty results), otherwise
// the target aborts (a finding like a crash).
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <string>
#include <string_view>

#include "hal/replay/dataset_parsers.h"

namespace {

/// Longest token handed to parse_seconds_ns() (it parses one token, not a file).
constexpr std::size_t kMaxTokenLength = 64;
/// Largest |t| the parsers accept, s (the contract: within +-9.2e9 s).
constexpr double kMaxAbsSeconds = 9.2e9;
constexpr double kNsPerS = 1e9;

[[noreturn]] void fail(const char* parser, const char* what) {
  std::fprintf(stderr, "dataset_parsers_fuzz: %s: %s\n", parser, what);
  std::abort();
}

void check_list(const char* parser, const mer::Result<std::vector<mer::hal::TimedFile>>& r) {
  if (!r.is_ok()) return;
  const auto& v = r.value();
  if (v.empty()) fail(parser, "empty list accepted");
  for (std::size_t i = 1; i < v.size(); ++i) {
    if (v[i].t_ns <= v[i - 1].t_ns) fail(parser, "timestamps not strictly increasing");
  }
}

void check_trajectory(const char* parser, const mer::Result<mer::hal::Trajectory>& r) {
  if (!r.is_ok()) return;
  const auto& p = r.value().poses;
  if (p.empty()) fail(parser, "empty trajectory accepted");
  for (std::size_t i = 0; i < p.size(); ++i) {
    if (i > 0 && p[i].t_ns <= p[i - 1].t_ns) fail(parser, "timestamps not strictly increasing");
    if (!p[i].T_w_c.matrix().allFinite()) fail(parser, "non-finite pose accepted");
  }
}

bool is_finite(double v) {
  return std::isfinite(v);
}

}  // namespace

// NOLINTNEXTLINE(readability-identifier-naming): the name libFuzzer calls
extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  const std::string_view text(reinterpret_cast<const char*>(data), size);
  const std::string name = "fuzz.txt";

  std::int64_t t_ns = 0;
  if (mer::hal::parse_seconds_ns(text.substr(0, kMaxTokenLength), t_ns) &&
      std::abs(static_cast<double>(t_ns)) > kMaxAbsSeconds * kNsPerS) {
    fail("parse_seconds_ns", "time outside +-9.2e9 s accepted");
  }
  check_list("parse_tum_list", mer::hal::parse_tum_list(text, name));
  check_list("parse_euroc_csv", mer::hal::parse_euroc_csv(text, name));
  check_trajectory("parse_tum_trajectory", mer::hal::parse_tum_trajectory(text, name));
  check_trajectory("parse_euroc_groundtruth", mer::hal::parse_euroc_groundtruth(text, name));

  if (auto c = mer::hal::parse_kitti_calib(text, name); c.is_ok()) {
    const auto& k = c.value();
    if (!(k.fx > 0.0 && k.fy > 0.0 && is_finite(k.fx) && is_finite(k.fy) && is_finite(k.cx) &&
          is_finite(k.cy))) {
      fail("parse_kitti_calib", "non-positive or non-finite focal length accepted");
    }
  }
  if (auto t = mer::hal::parse_kitti_times(text, name); t.is_ok()) {
    const auto& v = t.value();
    if (v.empty()) fail("parse_kitti_times", "empty list accepted");
    for (std::size_t i = 0; i < v.size(); ++i) {
      if (!is_finite(v[i])) fail("parse_kitti_times", "non-finite time accepted");
      if (i > 0 && v[i] <= v[i - 1]) fail("parse_kitti_times", "times not strictly increasing");
    }
  }
  if (auto p = mer::hal::parse_kitti_poses(text, name); p.is_ok()) {
    for (const auto& T : p.value()) {
      if (!T.matrix().allFinite()) fail("parse_kitti_poses", "non-finite pose accepted");
    }
  }
  if (auto s = mer::hal::parse_euroc_sensor(text, name); s.is_ok()) {
    const auto& e = s.value();
    if (!(is_finite(e.fu) && is_finite(e.fv) && is_finite(e.cu) && is_finite(e.cv) &&
          is_finite(e.rate_hz) && e.T_b_s.matrix().allFinite())) {
      fail("parse_euroc_sensor", "non-finite value accepted");
    }
  }
  return 0;
}
