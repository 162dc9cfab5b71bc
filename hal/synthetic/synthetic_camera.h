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

/// Options of the synthetic camera (config section `camera.synthetic`).
struct SyntheticOptions {
  int width = 640;                  ///< image width, px
  int height = 480;                 ///< image height, px
  double fov_x_deg = 70.0;          ///< horizontal field of view (sets fx = fy)
  double fps = 30.0;                ///< frame rate; timestamps advance by 1/fps
  int num_frames = 600;             ///< frames in the sequence (then end of stream)
  double noise_sigma = 2.0;         ///< additive Gaussian image noise, grey levels (0: none)
  double exposure_amplitude = 0.0;  ///< exposure gain varies as 1 + A sin(2 pi t / period)
  double exposure_period_s = 7.0;   ///< period of the exposure variation, s
  int seed = 1;                     ///< seed of textures, boxes and noise
  bool render_depth = true;         ///< also render per-pixel depth (for RGB-D mode)
  double room_size_x = 6.0;         ///< room extent along world x, m
  double room_size_y = 5.0;         ///< room extent along world y, m
  double room_height = 2.6;         ///< room height, m
  int num_boxes = 6;                ///< textured boxes standing in the room (0..16)
  int texture_size = 512;           ///< texels per wall side
  double kidnap_start_s = 8.0;      ///< room_kidnap: when the image goes black, s
  double kidnap_black_s = 1.0;      ///< room_kidnap: how long it stays black, s
  double kidnap_back_s = 6.0;       ///< room_kidnap: how far back in time the camera reappears, s
  double rotation_burst_s = 2.0;    ///< room_fast_rotation: duration of each 360 deg turn, s
  double hall_size_x = 80.0;        ///< hall_drive: hall extent along world x, m
  double hall_size_y = 50.0;        ///< hall_drive: hall extent along world y, m
  double hall_height = 10.0;        ///< hall_drive: hall height, m
  double drive_speed_mps = 5.6;     ///< hall_drive: driving speed, m/s

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
    v.field("exposure_amplitude", exposure_amplitude,
            "exposure gain amplitude A: gain = 1 + A sin(2 pi t / period)",
            options::Range<double>{0.0, 0.9});
    v.field("exposure_period_s", exposure_period_s, "period of the exposure variation, s",
            options::Range<double>{0.1, 1000.0});
    v.field("seed", seed, "random seed for textures, boxes and noise",
            options::Range<int>{0, 1 << 30});
    v.field("render_depth", render_depth, "render per-pixel depth (metres)");
    v.field("room_size_x", room_size_x, "room extent along world x, m",
            options::Range<double>{4.0, 100.0});
    v.field("room_size_y", room_size_y, "room extent along world y, m",
            options::Range<double>{3.5, 100.0});
    v.field("room_height", room_height, "room height, m", options::Range<double>{2.0, 50.0});
    v.field("num_boxes", num_boxes, "textured boxes standing in the room",
            options::Range<int>{0, 16});
    v.field("texture_size", texture_size, "texels per wall side", options::Range<int>{16, 4096});
    v.field("kidnap_start_s", kidnap_start_s, "room_kidnap: time the image goes black, s",
            options::Range<double>{0.0, 1e6});
    v.field("kidnap_black_s", kidnap_black_s, "room_kidnap: blackout duration, s",
            options::Range<double>{0.0, 1e6});
    v.field("kidnap_back_s", kidnap_back_s,
            "room_kidnap: the camera reappears where it was this long before, s",
            options::Range<double>{0.0, 1e6});
    v.field("rotation_burst_s", rotation_burst_s,
            "room_fast_rotation: duration of each 360 degree turn, s",
            options::Range<double>{0.2, 100.0});
    v.field("hall_size_x", hall_size_x, "hall_drive: hall extent along world x, m",
            options::Range<double>{20.0, 1000.0});
    v.field("hall_size_y", hall_size_y, "hall_drive: hall extent along world y, m",
            options::Range<double>{20.0, 1000.0});
    v.field("hall_height", hall_height, "hall_drive: hall height, m",
            options::Range<double>{3.0, 100.0});
    v.field("drive_speed_mps", drive_speed_mps, "hall_drive: driving speed, m/s",
            options::Range<double>{0.1, 50.0});
  }
};

/// An axis-aligned box standing in the room.
struct SceneBox {
  Eigen::Vector3f lo;  ///< minimum corner, world, m
  Eigen::Vector3f hi;  ///< maximum corner, world, m
  int texture = 0;     ///< texture index
};

/// Where the scripted camera is at one instant.
struct ScenarioSample {
  SE3d T_w_c = SE3d::Identity();  ///< camera-to-world pose
  bool visible = true;            ///< false while the image is blacked out (room_kidnap)
};

/// Names of the scripted trajectories:
/// - `room_orbit`: handheld-like orbit around the room centre, looking across the room.
/// - `room_loop`: walks an ellipse through the room looking ahead and outwards; returns to
///   its start pose every 20 s (a loop closure every 600 frames at 30 Hz).
/// - `room_kidnap`: room_orbit, then the image goes black for `kidnap_black_s` and the
///   camera reappears where it was `kidnap_back_s` earlier (ground truth absent while black).
/// - `room_fast_rotation`: room_orbit plus a full 360 degree yaw turn in `rotation_burst_s`
///   every 8 s (peak rate 1.5 x 360 / rotation_burst_s deg/s).
/// - `hall_drive`: a car-like drive (camera 1.65 m above the floor, looking ahead) at
///   `drive_speed_mps` round a rounded rectangle in a hall of `hall_size_x` x `hall_size_y` x
///   `hall_height` (the room_size_* options do not apply). The path spans 60 % of the hall;
///   its corners are 90 degree turns of 12 m radius in the default hall. Boxes are scaled up
///   (buildings and parked vehicles, 2-8 m) and walls carry 4x the texels and denser shapes.
///   A driving sequence like KITTI's: forward motion, a wide depth range and turns (use
///   `fps: 10` for KITTI's rate).
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

  /// The scripted camera at time `t_s` seconds from the start.
  ScenarioSample sample_at(double t_s) const;

  /// The boxes standing in the room (valid after open()).
  const std::vector<SceneBox>& boxes() const { return boxes_; }

  /// The room's (or hall's) minimum and maximum corners, world, m (valid after open()).
  Eigen::Vector3d room_lo() const { return {room_lo_[0], room_lo_[1], room_lo_[2]}; }
  Eigen::Vector3d room_hi() const { return {room_hi_[0], room_hi_[1], room_hi_[2]}; }

  /// Renders the view from `T_w_c` into `gray` (CV_8UC1) and optionally `depth` (CV_32FC1,
  /// may be empty), with exposure `gain`. `noise_offset` selects the noise pattern.
  /// No allocation.
  void render(const SE3d& T_w_c, cv::Mat& gray, cv::Mat* depth, std::uint64_t noise_offset,
              float gain = 1.0F) const;

 private:
  enum class Scenario { kOrbit, kLoop, kKidnap, kFastRotation, kHallDrive };
  SE3d orbit_pose(double t_s) const;
  SE3d drive_pose(double t_s) const;
  void place_boxes(std::uint32_t seed);
  void place_hall_boxes(std::uint32_t seed);
  // hall_drive: half extents of the path's rectangle and its corner radius, m.
  double drive_half_x() const;
  double drive_half_y() const;
  double drive_radius() const;

  std::string scenario_;
  Scenario kind_ = Scenario::kOrbit;
  SyntheticOptions opts_;
  bool paced_;
  CameraIntrinsics intrinsics_;
  std::unique_ptr<FramePool> pool_;
  std::vector<float> rays_;  // per pixel (x, y) of the ray at z = 1
  // One texture per wall (shared by boxes), as a mip pyramid: level l is (size >> l)^2.
  std::array<std::vector<std::vector<std::uint8_t>>, 6> textures_;
  int texture_size_ = 0;                      // texels per side of level 0
  bool use_mips_ = false;                     // pick a texture level per pixel (hall_drive only)
  std::array<float, 3> wall_texels_per_m_{};  // level-0 texels per metre along each world axis
  std::vector<SceneBox> boxes_;
  std::array<float, 3> room_lo_{};   // scene box minimum corner, world, m
  std::array<float, 3> room_hi_{};   // scene box maximum corner, world, m
  float box_texture_metres_ = 1.0F;  // one texture tile spans this many metres on a box face
  std::vector<std::int8_t> noise_;   // precomputed noise table
  std::uint64_t next_seq_ = 0;
  std::int64_t start_wall_ns_ = 0;
  bool started_ = false;
  Status last_error_;
};

}  // namespace mer::hal
