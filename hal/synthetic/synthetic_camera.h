#pragma once
/// @file synthetic_camera.h
/// `synthetic:NAME` — a camera that renders a textured room along a scripted trajectory,
/// with exact ground-truth poses and per-pixel depth. Deterministic for a given seed.
///
/// Rendering is ray casting against the room's six walls (axis-aligned box, world z up),
/// each wall carrying a texture made at open() from the seed: procedural (random rectangles
/// and discs over a gradient: plenty of corners for feature detectors) or photographs from a
/// folder (`texture: photo`, default the Debian package mate-backgrounds), grey, cropped and
/// resized, one photo per wall picked by the seed. Look-alike places (`repeat_texture`): one
/// framed photo panel repeated on several walls (and boxes). Camera effects: additive noise, a
/// sinusoidal and a stepped exposure gain, and motion blur (the mean of several renders
/// spread over the exposure time along the trajectory). Per-pixel ray directions, textures
/// and the blur accumulator are made at open(), so acquire() does no allocation.

#include <array>
#include <cstdint>
#include <random>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "core/options.h"
#include "hal/camera.h"

namespace mer::hal {

/// Values of `camera.synthetic.texture`: auto is photo for the reproduction scenarios
/// (hall_turn, room_explore, room_rotation, corridor, room_kidnap_unknown, room_repeated,
/// hall_repeated) and procedural for the others.
inline constexpr std::array<std::string_view, 3> kSyntheticTextures{"auto", "procedural", "photo"};
/// Values of `camera.synthetic.photo_set`: every photo, or one of two disjoint halves of the
/// name-sorted list (dev: even positions, heldout: odd ones).
inline constexpr std::array<std::string_view, 3> kSyntheticPhotoSets{"all", "dev", "heldout"};
/// Default `camera.synthetic.photo_dir`, and the Debian package that fills it.
inline constexpr std::string_view kDefaultPhotoDir = "/usr/share/backgrounds/mate";
inline constexpr std::string_view kPhotoPackage = "mate-backgrounds";

/// Options of the synthetic camera (config section `camera.synthetic`).
struct SyntheticOptions {
  int width = 640;
  int height = 480;
  double fov_x_deg = 70.0;
  double fps = 30.0;
  int num_frames = 600;
  double noise_sigma = 2.0;
  double exposure_amplitude = 0.0;
  double exposure_period_s = 7.0;
  int seed = 1;
  bool render_depth = true;
  double room_size_x = 6.0;
  double room_size_y = 5.0;
  double room_height = 2.6;
  int num_boxes = 6;
  int texture_size = 512;
  double kidnap_start_s = 8.0;
  double kidnap_black_s = 1.0;
  double kidnap_back_s = 6.0;
  double rotation_burst_s = 2.0;
  double hall_size_x = 80.0;
  double hall_size_y = 50.0;
  double hall_height = 10.0;
  double drive_speed_mps = 5.6;
  std::string texture = "auto";
  std::string photo_dir{kDefaultPhotoDir};
  std::string photo_set = "all";
  double exposure_time_s = 0.0;
  int blur_samples = 5;
  double exposure_step_every_s = 0.0;
  double exposure_step_size = 0.25;
  double turn_angle_deg = 95.0;
  double turn_duration_s = 4.0;
  double turn_speed_mps = 3.5;
  double walk_speed_mps = 0.25;
  double sweep_yaw_deg = 40.0;
  double sweep_pitch_deg = 15.0;
  double sweep_period_s = 6.0;
  double sweep_translation_m = 0.03;
  double corridor_length = 24.0;
  double corridor_width = 2.0;
  double corridor_height = 2.5;
  double corridor_speed_mps = 1.0;
  double corridor_contrast = 0.12;
  double kidnap_return_s = 6.0;
  int repeat_texture = 0;

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
    v.field("kidnap_start_s", kidnap_start_s,
            "room_kidnap, room_repeated: time the image goes black, s (room_repeated: its "
            "mapping lap ends 1 s before; at least 6 s)",
            options::Range<double>{0.0, 1e6});
    v.field("kidnap_black_s", kidnap_black_s, "room_kidnap, room_repeated: blackout duration, s",
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
    v.field("drive_speed_mps", drive_speed_mps,
            "hall_drive, hall_repeated: driving speed, m/s (hall_turn: speed on its straights)",
            options::Range<double>{0.1, 50.0});
    v.field("texture", texture,
            "wall textures: procedural, photo (from photo_dir), or auto (photo for hall_turn, "
            "room_explore, room_rotation, corridor, room_kidnap_unknown, room_repeated, "
            "hall_repeated; procedural otherwise)",
            options::OneOf{kSyntheticTextures});
    v.field("photo_dir", photo_dir,
            "photo textures: folder searched (recursively) for *.jpg; default from the Debian "
            "package mate-backgrounds");
    v.field("photo_set", photo_set,
            "photo textures: all photos, or one half of the name-sorted list (dev: even "
            "positions, heldout: odd), to choose settings on one half and check on the other",
            options::OneOf{kSyntheticPhotoSets});
    v.field("exposure_time_s", exposure_time_s,
            "motion blur: exposure time centred on the frame time, s (0: no blur)",
            options::Range<double>{0.0, 0.5});
    v.field("blur_samples", blur_samples, "motion blur: renders averaged over the exposure",
            options::Range<int>{2, 32});
    v.field("exposure_step_every_s", exposure_step_every_s,
            "exposure steps (auto-exposure jumps): one sudden gain change every this many s "
            "(0: none)",
            options::Range<double>{0.0, 1e6});
    v.field("exposure_step_size", exposure_step_size,
            "exposure steps: each jump multiplies or divides the gain by 1 + this",
            options::Range<double>{0.0, 2.0});
    v.field("turn_angle_deg", turn_angle_deg, "hall_turn: angle of the first (left) turn, deg",
            options::Range<double>{10.0, 180.0});
    v.field("turn_duration_s", turn_duration_s, "hall_turn: duration of each turn, s",
            options::Range<double>{1.0, 30.0});
    v.field("turn_speed_mps", turn_speed_mps, "hall_turn: speed through the turns, m/s",
            options::Range<double>{0.5, 20.0});
    v.field("walk_speed_mps", walk_speed_mps, "room_explore: walking speed, m/s",
            options::Range<double>{0.05, 3.0});
    v.field("sweep_yaw_deg", sweep_yaw_deg, "room_rotation: yaw sweep amplitude, deg",
            options::Range<double>{0.0, 90.0});
    v.field("sweep_pitch_deg", sweep_pitch_deg, "room_rotation: pitch sweep amplitude, deg",
            options::Range<double>{0.0, 60.0});
    v.field("sweep_period_s", sweep_period_s,
            "room_rotation: period of the yaw sweep, s (pitch: 0.68 of it)",
            options::Range<double>{0.5, 100.0});
    v.field("sweep_translation_m", sweep_translation_m,
            "room_rotation: amplitude of the hand's translation, m",
            options::Range<double>{0.0, 0.5});
    v.field("corridor_length", corridor_length, "corridor: length, m",
            options::Range<double>{8.0, 200.0});
    v.field("corridor_width", corridor_width, "corridor: width, m",
            options::Range<double>{1.2, 10.0});
    v.field("corridor_height", corridor_height, "corridor: height, m",
            options::Range<double>{2.0, 10.0});
    v.field("corridor_speed_mps", corridor_speed_mps, "corridor: walking speed, m/s",
            options::Range<double>{0.1, 5.0});
    v.field("corridor_contrast", corridor_contrast,
            "corridor: contrast of the photo kept on the white walls (0: flat white)",
            options::Range<double>{0.0, 1.0});
    v.field("kidnap_return_s", kidnap_return_s,
            "room_kidnap_unknown: after reappearing, time to walk and turn back to the mapped "
            "part, s",
            options::Range<double>{1.0, 1e6});
    v.field("repeat_texture", repeat_texture,
            "look-alike places: this many copies of one framed panel (a crop of the first "
            "wall's photo or texture, the same texels in each copy) hang on the walls: in rooms "
            "centred on the -x, +x, -y, +y walls in turn (more copies share a wall evenly), in "
            "halls and the corridor evenly along the two long walls; every other box wears the "
            "same photo (0: off, every scene as without it)",
            options::Range<int>{0, 64});
  }
};

/// An axis-aligned box standing in the room.
struct SceneBox {
  Eigen::Vector3f lo;  ///< minimum corner, world, m
  Eigen::Vector3f hi;  ///< maximum corner, world, m
  int texture = 0;     ///< texture index (0-5: a wall's; kPanelTexture: the repeated panel)
};

/// SceneBox::texture of a box wearing the repeated panel's photo (`repeat_texture`).
inline constexpr int kPanelTexture = 6;

/// One copy of the repeated panel (`repeat_texture`), on a vertical wall.
struct WallPanel {
  int wall = 0;     ///< wall index: axis * 2 + side (0: -x, 1: +x, 2: -y, 3: +y)
  float u0 = 0.0F;  ///< extent along the wall's horizontal axis (y for x walls, else x), m
  float u1 = 0.0F;
  float v0 = 0.0F;  ///< extent in height (world z), m
  float v1 = 0.0F;
  bool mirror = false;  ///< texture columns run towards -u (so copies read the same from inside)
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
///
/// Reproductions of held-out failures (photo textures by default; their camera settings and
/// effects are in `configs/scenarios/NAME.yaml`, passed with `--config`):
/// - `hall_turn`: KITTI-like drive in the hall that starts inside a sharp low-speed left turn
///   (`turn_angle_deg` in `turn_duration_s` at `turn_speed_mps`, yaw rate nonzero from the
///   first frame), then a straight at up to 5 m/s, a second 90 degree left turn, a straight
///   at `drive_speed_mps`, and stops 21.5 s in (then parked).
/// - `room_explore`: handheld walk at `walk_speed_mps` round a 1.7 x 1.1 m rounded rectangle,
///   looking ahead and 40 degrees outwards, with hand sway: new walls and boxes come into view
///   all the time; passes through its start after one lap (about 20 s at 0.25 m/s). Meant
///   for a bigger room (10 x 8 m, 16 boxes in its config).
/// - `room_rotation`: rotation-dominant handheld motion from the first frame: yaw sweeps of
///   +-`sweep_yaw_deg`, pitch sweeps of +-`sweep_pitch_deg`, a hand translation of
///   +-`sweep_translation_m` (all zero: a static camera).
/// - `corridor`: a `corridor_length` x `corridor_width` x `corridor_height` corridor with
///   mostly white walls (the photos flattened to `corridor_contrast`), doors, posters,
///   skirting and ceiling lights; walks along it at `corridor_speed_mps` with head yaw, turns
///   round at the ends. The room_size_* and num_boxes options do not apply.
/// - `room_kidnap_unknown`: handheld motion looking at the -x half of the room until
///   `kidnap_start_s`, black for `kidnap_black_s`, then reappears in the +x half looking at
///   the +x wall (never seen before), and walks and turns back over `kidnap_return_s` until
///   it sees the mapped -x half again.
/// - `room_repeated`: look-alike places for relocalization (use `repeat_texture` >= 2: the
///   same panel on the -x wall, A, and the +x wall, B, 6-8 m apart). Hand-held, facing A for
///   2 s with a sideways sway, then a walk round a 0.9 m circle about the room centre looking
///   outwards (A, -y wall, B, +y wall, A) that ends 1 s before `kidnap_start_s`; then facing A,
///   stepping slowly towards it with the sway, black from `kidnap_start_s` for
///   `kidnap_black_s` while the camera moves on (no jump; no ground truth while black),
///   facing A for 3 s more, then walks over 8 s to the +y half of the room facing the +y wall.
/// - `hall_repeated`: look-alike places for loop closure (use `repeat_texture`: copies every
///   few metres along both long walls). A car-like drive (1.65 m up) at `drive_speed_mps`
///   round a stadium in a hall of `hall_size_x` x `hall_size_y` x `hall_height`: along the -y
///   side heading +x, a 180 degree left turn at the far end, back along the +y side, a turn at
///   the near end and on through its start (a true loop); straights 4 m from the long walls,
///   looking 35 degrees to the right (sideways-forward, at the near wall's panels).
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

  /// The copies of the repeated panel (`repeat_texture`), sorted by wall (valid after open()).
  const std::vector<WallPanel>& panels() const { return panels_; }

  /// The photos used as textures, one per wall (empty with procedural textures; valid after
  /// open()).
  const std::vector<std::string>& photo_files() const { return photo_files_; }

  /// Every photo of `opts.photo_dir` in `opts.photo_set`, sorted by file name, or an error
  /// naming the folder (and the package to install) when there is none.
  static Status list_photos(const SyntheticOptions& opts, std::vector<std::string>& out);

  /// The room's (or hall's) minimum and maximum corners, world, m (valid after open()).
  Eigen::Vector3d room_lo() const { return {room_lo_[0], room_lo_[1], room_lo_[2]}; }
  Eigen::Vector3d room_hi() const { return {room_hi_[0], room_hi_[1], room_hi_[2]}; }

  /// Renders the view from `T_w_c` into `gray` (CV_8UC1) and optionally `depth` (CV_32FC1,
  /// may be empty), with exposure `gain`. `noise_offset` selects the noise pattern.
  /// No allocation.
  void render(const SE3d& T_w_c, cv::Mat& gray, cv::Mat* depth, std::uint64_t noise_offset,
              float gain = 1.0F) const;

  /// The exposure gain at `t_s`: 1 + A sin(2 pi t / period), times the exposure steps.
  double gain_at(double t_s) const;

 private:
  enum class Scenario {
    kOrbit,
    kLoop,
    kKidnap,
    kFastRotation,
    kHallDrive,
    kHallTurn,
    kRoomExplore,
    kRoomRotation,
    kCorridor,
    kKidnapUnknown,
    kRoomRepeated,
    kHallRepeated
  };
  /// A wall texture as a mip pyramid: level l is (w >> l) x (h >> l), row-major.
  struct Texture {
    int w = 0;
    int h = 0;
    std::vector<std::vector<std::uint8_t>> levels;
  };
  /// hall_turn: the planar path tabulated at kPathStepS (x, y, heading), world, m and rad.
  struct PathPoint {
    double x = 0.0;
    double y = 0.0;
    double heading = 0.0;
  };
  SE3d orbit_pose(double t_s) const;
  SE3d drive_pose(double t_s) const;
  SE3d turn_pose(double t_s) const;
  SE3d explore_pose(double t_s) const;
  SE3d rotation_pose(double t_s) const;
  SE3d corridor_pose(double t_s) const;
  ScenarioSample kidnap_unknown_sample(double t_s) const;
  ScenarioSample repeated_room_sample(double t_s) const;
  SE3d repeated_hall_pose(double t_s) const;
  // room_repeated, hall_repeated: checks that the scene fits the script.
  Status check_repeated_script() const;
  // repeat_texture: the panel's texture, cut from the first wall's photo or texture `first`,
  // and its copies on the walls (after the wall textures, before the boxes).
  void make_panels(const cv::Mat& first);
  void place_boxes(std::uint32_t seed);
  void place_hall_boxes(std::uint32_t seed);
  // Boxes clear of the camera positions sampled over the whole sequence (new scenarios).
  void place_boxes_clear_of_path(std::uint32_t seed, bool hall);
  Status make_turn_path_checked();
  // One grey photo per wall, picked from the photo set by `rng` (fills photo_files_).
  Status load_wall_photos(std::mt19937& rng, std::vector<cv::Mat>& photos);
  void make_photo_textures(const std::vector<cv::Mat>& photos, std::mt19937& rng);
  // corridor: white walls from `sources` (one grey image per wall), doors, posters, lights.
  void make_corridor_textures(const std::vector<cv::Mat>& sources, std::mt19937& rng);
  void render_impl(const SE3d& T_w_c, cv::Mat& gray, cv::Mat* depth, std::uint64_t noise_offset,
                   float gain, bool add_noise) const;
  /// A box and the pixel rectangle its projection covers (render_impl's per-frame culling).
  struct BoxWindow {
    const SceneBox* box = nullptr;
    int u0 = 0;
    int u1 = 0;
    int v0 = 0;
    int v1 = 0;
  };
  /// The boxes not wholly behind the camera at (R, o) (world from camera), each with the
  /// bounding rectangle of its projection in a cols x rows image (the whole image when a
  /// corner is behind the camera); at most out.size(). Returns how many.
  std::size_t cull_boxes(const Eigen::Matrix3f& R, const Eigen::Vector3f& o, int cols, int rows,
                         std::span<BoxWindow> out) const;
  /// Bilinear lookup at level-0 texel coordinates (fu, fv) in [0, w - 1) x [0, h - 1) of mip
  /// level `level`.
  static float sample_texture(const Texture& texture, int level, float fu, float fv);
  // Motion blur: the mean of blur_samples renders over the exposure, then noise.
  void render_blurred(double t_s, Frame& f, float gain);
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
  // One texture per wall (index axis * 2 + side), shared by boxes.
  std::array<Texture, 6> textures_;
  int texture_size_ = 0;                      // texels per side of level 0 (square textures)
  bool use_mips_ = false;                     // pick a texture level per pixel (hall_drive only)
  std::array<float, 6> wall_texels_per_m_{};  // per wall: level-0 texels per metre (max of axes)
  std::vector<SceneBox> boxes_;
  Texture panel_;                             // repeat_texture: the repeated panel
  float panel_texels_per_m_ = 1.0F;           // its level-0 texels per metre
  std::vector<WallPanel> panels_;             // its copies, sorted by wall
  std::array<std::size_t, 7> wall_panels_{};  // copies on wall k: [wall_panels_[k], [k + 1])
  std::array<float, 3> room_lo_{};            // scene box minimum corner, world, m
  std::array<float, 3> room_hi_{};            // scene box maximum corner, world, m
  float box_texture_metres_ = 1.0F;       // one texture tile spans this many metres on a box face
  std::vector<std::int8_t> noise_;        // precomputed noise table
  std::vector<std::string> photo_files_;  // photo per wall (photo textures)
  std::vector<PathPoint> turn_path_;      // hall_turn: tabulated path, world
  double turn_path_end_s_ = 0.0;          // hall_turn: the car stops here, s
  cv::Mat blur_scratch_;                  // motion blur: one sub-exposure render
  std::vector<std::uint16_t> blur_sum_;   // motion blur: per-pixel sum of the renders
  std::uint64_t next_seq_ = 0;
  std::int64_t start_wall_ns_ = 0;
  bool started_ = false;
  Status last_error_;
};

}  // namespace mer::hal
