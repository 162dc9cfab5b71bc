#pragma once
/// @file synthetic_camera.h
/// `synthetic:NAME` — a camera that renders a textured room along a scripted trajectory,
/// with exact ground-truth poses and per-pixel depth. Deterministic for a given seed.
///
/// Rendering is ray casting against the room's six walls (axis-aligned box, world z up),
/// each wall carrying a procedural texture generated at open() from the seed (random
/// rectangles and discs over a gradient: plenty of corners for feature detectors, no
/// downloaded images). Per-pixel ray directions and textures are precomputed at open(), so
/// acquire() does no allocation.

#include <array>
#include <cstdint>
#include <string>
#include <string_view>
#include <vector>

#include "core/options.h"
#include "hal/camera.h"

namespace mer::hal {

/// Options of the synthetic camera (config section `synthetic`).
struct SyntheticOptions {
  int width = 640;           ///< image width, px
  int height = 480;          ///< image height, px
  double fov_x_deg = 70.0;   ///< horizontal field of view (sets fx = fy)
  double fps = 30.0;         ///< frame rate; timestamps advance by 1/fps
  int num_frames = 600;      ///< frames in the sequence (then end of stream)
  double noise_sigma = 2.0;  ///< additive Gaussian image noise, grey levels (0: none)
  int seed = 1;              ///< seed of textures and noise
  bool render_depth = true;  ///< also render per-pixel depth (for RGB-D mode)
  double room_size_x = 6.0;  ///< room extent along world x, m
  double room_size_y = 5.0;  ///< room extent along world y, m
  double room_height = 2.6;  ///< room height, m
  int texture_size = 512;    ///< texels per wall side (power of two)

  template <class V>
  void visit(V& v) {
    v.field("width", width, "image width, px", options::Range<int>{32, 4096});
    v.field("height", height, "image height, px", options::Range<int>{32, 4096});
    v.field("fov_x_deg", fov_x_deg, "horizontal field of view, degrees",
            options::Range<double>{10.0, 150.0});
    v.field("fps", fps, "frame rate, Hz", options::Range<double>{1.0, 1000.0});
    v.field("num_frames", num_frames, "frames in the sequence", options::Range<int>{1, 10000000});
    v.field("noise_sigma", noise_sigma, "Gaussian image noise, grey levels",
            options::Range<double>{0.0, 50.0});
    v.field("seed", seed, "random seed for textures and noise", options::Range<int>{0, 1 << 30});
    v.field("render_depth", render_depth, "render per-pixel depth (metres)");
    v.field("room_size_x", room_size_x, "room extent along world x, m",
            options::Range<double>{1.0, 100.0});
    v.field("room_size_y", room_size_y, "room extent along world y, m",
            options::Range<double>{1.0, 100.0});
    v.field("room_height", room_height, "room height, m", options::Range<double>{1.0, 50.0});
    v.field("texture_size", texture_size, "texels per wall side", options::Range<int>{16, 4096});
  }
};

/// Names of the scripted trajectories.
std::span<const std::string_view> synthetic_scenarios();

/// The synthetic camera. `paced` = true makes acquire() wait for each frame's due time
/// (a live camera at `fps`); false renders as fast as asked (lockstep replay).
class SyntheticCamera final : public CameraSource {
 public:
  SyntheticCamera(std::string scenario, const SyntheticOptions& opts, bool paced);

  Status open(std::size_t pool_size) override;
  Status start() override;
  AcquireStatus acquire(FrameHandle& out, std::int64_t timeout_ns) override;
  void stop() override;
  const CameraIntrinsics& intrinsics() const override { return intrinsics_; }
  CameraCapabilities capabilities() const override;
  std::string describe() const override;
  const Status& last_error() const override { return last_error_; }
  FramePool& pool() override { return *pool_; }

  /// Ground-truth camera-to-world pose at time `t_s` seconds from the start.
  SE3d pose_at(double t_s) const;

  /// Renders the view from `T_w_c` into `gray` (CV_8UC1) and optionally `depth` (CV_32FC1,
  /// may be empty). `noise_offset` selects the noise pattern. No allocation.
  void render(const SE3d& T_w_c, cv::Mat& gray, cv::Mat* depth, std::uint64_t noise_offset) const;

 private:
  std::string scenario_;
  SyntheticOptions opts_;
  bool paced_;
  CameraIntrinsics intrinsics_;
  std::unique_ptr<FramePool> pool_;
  std::vector<float> rays_;                            // per pixel (x, y) of the ray at z = 1
  std::array<std::vector<std::uint8_t>, 6> textures_;  // one per wall
  std::vector<std::int8_t> noise_;                     // precomputed noise table
  std::uint64_t next_seq_ = 0;
  std::int64_t start_wall_ns_ = 0;
  bool started_ = false;
  Status last_error_;
};

}  // namespace mer::hal
