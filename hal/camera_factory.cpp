#include "hal/camera_factory.h"

#include <algorithm>
#include <array>

namespace mer::hal {
namespace {
constexpr std::array<std::string_view, 7> kSchemes{"synthetic", "tum",  "euroc",    "kitti",
                                                   "rec",       "v4l2", "libcamera"};
}  // namespace

std::span<const std::string_view> input_schemes() {
  return kSchemes;
}

Result<InputUri> parse_input_uri(std::string_view uri) {
  const auto colon = uri.find(':');
  std::string known;
  for (auto s : kSchemes) known += (known.empty() ? "" : ", ") + std::string(s) + ":";
  if (colon == std::string_view::npos) {
    return invalid_argument("--input '" + std::string(uri) +
                            "': expected SCHEME:PATH with one of " + known);
  }
  InputUri out{std::string(uri.substr(0, colon)), std::string(uri.substr(colon + 1))};
  if (std::find(kSchemes.begin(), kSchemes.end(), out.scheme) == kSchemes.end()) {
    return invalid_argument("--input '" + std::string(uri) + "': unknown scheme '" + out.scheme +
                            "' (expected one of " + known + ")");
  }
  if (out.path.empty()) {
    return invalid_argument("--input '" + std::string(uri) + "': empty path after '" + out.scheme +
                            ":'");
  }
  return out;
}

CameraIntrinsics effective_intrinsics(const CameraIntrinsics& source,
                                      const CalibrationOptions& calib) {
  if (!calib.is_set()) return source;
  CameraIntrinsics k = source;
  k.fx = calib.fx;
  k.fy = calib.fy > 0.0 ? calib.fy : calib.fx;
  k.cx = calib.cx;
  k.cy = calib.cy;
  k.dist = {calib.k1, calib.k2, calib.p1, calib.p2};
  k.focal_known = true;
  return k;
}

Result<std::unique_ptr<CameraSource>> make_camera(const InputUri& uri, const CameraOptions& opts,
                                                  bool paced) {
  if (uri.scheme == "synthetic") {
    return std::unique_ptr<CameraSource>(
        std::make_unique<SyntheticCamera>(uri.path, opts.synthetic, paced));
  }
  return Status(StatusCode::kUnavailable,
                "--input '" + uri.scheme + ":" + uri.path + "': the '" + uri.scheme +
                    "' reader is not available in this build (available: synthetic:)");
}

}  // namespace mer::hal
