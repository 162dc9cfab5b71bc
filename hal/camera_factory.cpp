#include "hal/camera_factory.h"

#include <algorithm>
#include <array>

#include "hal/replay/rec_loader.h"
#include "hal/v4l2/v4l2_camera.h"

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

Result<std::unique_ptr<CameraSource>> make_camera(const InputUri& uri, const CameraOptions& opts,
                                                  bool paced, bool rgbd) {
  if (uri.scheme == "synthetic") {
    return std::unique_ptr<CameraSource>(
        std::make_unique<SyntheticCamera>(uri.path, opts.synthetic, paced));
  }
  if (uri.scheme == "tum" || uri.scheme == "euroc" || uri.scheme == "kitti") {
    return make_replay_camera(uri.scheme, uri.path, opts.replay, opts.calibration, rgbd, paced);
  }
  if (uri.scheme == "rec") {
    auto loader = make_rec_loader(uri.path);
    if (!loader.is_ok()) return loader.status();
    return std::unique_ptr<CameraSource>(
        std::make_unique<ReplayCamera>(std::move(loader).value(), opts.replay, paced));
  }
  if (uri.scheme == "v4l2") return make_v4l2_camera(uri.path, opts.v4l2);
  if (uri.scheme == "libcamera") return make_libcamera_camera(uri.path, opts.libcamera);
  return invalid_argument("--input '" + uri.scheme + ":" + uri.path + "': unknown scheme");
}

}  // namespace mer::hal
