#include "hal/synthetic/synthetic_camera.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <numbers>
#include <random>
#include <thread>

#include "platform/clock.h"

namespace mer::hal {
namespace {

constexpr std::array<std::string_view, 5> kScenarios{"room_orbit", "room_loop", "room_kidnap",
                                                     "room_fast_rotation", "hall_drive"};
constexpr std::size_t kNoiseTableSize = 1 << 16;  // noise values, cycled with a per-frame offset
constexpr int kShapesPerWall = 160;               // texture primitives per wall
constexpr double kNsPerS = 1e9;
constexpr double kTwoPi = 2.0 * std::numbers::pi;
constexpr double kEyeHeight = 1.3;         // camera height above the floor, m
constexpr double kOrbitPeriodS = 20.0;     // room_orbit: one revolution, s
constexpr double kOrbitRadius = 0.8;       // room_orbit: radius of the camera circle, m
constexpr double kLoopPeriodS = 20.0;      // room_loop: one lap, s
constexpr double kLoopSemiAxisX = 1.5;     // room_loop: ellipse semi-axis along x, m
constexpr double kLoopSemiAxisY = 1.0;     // room_loop: ellipse semi-axis along y, m
constexpr double kLoopOutwardRad = 0.6;    // room_loop: view turned outwards from the path
constexpr double kBurstPeriodS = 8.0;      // room_fast_rotation: one turn every 8 s
constexpr double kBurstStartS = 3.0;       // room_fast_rotation: turn starts 3 s into a period
constexpr double kBoxClearance = 0.45;     // boxes stay this far outside the camera paths, m
constexpr double kWallMargin = 0.1;        // boxes stay this far from the walls, m
constexpr double kBoxTextureMetres = 2.0;  // a texture tile spans this many metres on a box
constexpr int kBoxPlacementTries = 200;    // rejection-sampling budget per box
constexpr std::size_t kMaxBoxes = 16;      // upper bound of num_boxes (options range)
constexpr float kNearPlane = 1e-3F;        // box corners closer than this count as behind
constexpr double kShapeRadiusMin = 0.01;   // texture shapes' radius, fraction of the texture side
constexpr double kShapeRadiusMax = 0.06;
constexpr double kDriveEyeHeight = 1.65;      // hall_drive: camera height (KITTI's), m
constexpr double kDrivePathFraction = 0.6;    // hall_drive: path extent, fraction of the hall
constexpr double kDriveCornerFraction = 0.8;  // hall_drive: corner radius / smaller half extent
constexpr double kDriveBoxClearance = 3.0;    // hall_drive: boxes stay this far from the path, m
constexpr double kDriveBoxMinSide = 2.0;      // hall_drive: box footprint side range, m
constexpr double kDriveBoxMaxSide = 8.0;
constexpr double kDriveBoxMinHeight = 2.0;  // hall_drive: box height range, m
constexpr double kDriveBoxMaxHeight = 6.0;
constexpr double kHallBoxTextureMetres = 8.0;  // hall_drive: texture tile on a box, m
constexpr int kHallTextureScale = 4;           // hall_drive: texture_size multiplier
constexpr int kHallShapesPerWall = 3000;       // hall_drive: texture primitives per wall
constexpr double kHallShapeRadiusMin = 0.004;  // hall_drive: shape radius, fraction of the side
constexpr double kHallShapeRadiusMax = 0.02;
constexpr int kMinMipSize = 8;           // coarsest texture level, texels per side
constexpr float kMinObliqueCos = 0.25F;  // obliquity taken into a pixel footprint at most 4x

// Smooth 0 -> 1 ramp over x in [0, 1] with zero slope at both ends (peak slope 1.5).
double smoothstep(double x) {
  x = std::clamp(x, 0.0, 1.0);
  return x * x * (3.0 - 2.0 * x);
}

// Portable normal deviates (std::normal_distribution differs between standard libraries).
double normal_deviate(std::mt19937& rng) {
  const double u1 = (static_cast<double>(rng()) + 1.0) / 4294967297.0;
  const double u2 = static_cast<double>(rng()) / 4294967296.0;
  return std::sqrt(-2.0 * std::log(u1)) * std::cos(kTwoPi * u2);
}

double uniform(std::mt19937& rng, double lo, double hi) {
  return lo + (hi - lo) * (static_cast<double>(rng()) / 4294967296.0);
}

// A wall texture: smooth gradient plus random rectangles and discs of random grey levels.
std::vector<std::uint8_t> make_texture(int size, int shapes, double r_min, double r_max,
                                       std::mt19937& rng) {
  std::vector<std::uint8_t> tex(static_cast<std::size_t>(size) * static_cast<std::size_t>(size));
  const double g0 = uniform(rng, 60, 190);
  const double gx = uniform(rng, -60, 60);
  const double gy = uniform(rng, -60, 60);
  for (int y = 0; y < size; ++y) {
    for (int x = 0; x < size; ++x) {
      const double v = g0 + gx * x / size + gy * y / size;
      tex[static_cast<std::size_t>(y * size + x)] =
          static_cast<std::uint8_t>(std::clamp(v, 0.0, 255.0));
    }
  }
  for (int k = 0; k < shapes; ++k) {
    const auto level = static_cast<std::uint8_t>(uniform(rng, 0, 256));
    const double cx = uniform(rng, 0, size);
    const double cy = uniform(rng, 0, size);
    const double r = uniform(rng, r_min, r_max) * size;
    const bool disc = (rng() & 1U) != 0U;
    const double ax = r * uniform(rng, 0.5, 1.5);
    const double ay = r * uniform(rng, 0.5, 1.5);
    const int x0 = std::max(0, static_cast<int>(cx - ax));
    const int x1 = std::min(size - 1, static_cast<int>(cx + ax));
    const int y0 = std::max(0, static_cast<int>(cy - ay));
    const int y1 = std::min(size - 1, static_cast<int>(cy + ay));
    for (int y = y0; y <= y1; ++y) {
      for (int x = x0; x <= x1; ++x) {
        if (disc) {
          const double dx = (x - cx) / ax;
          const double dy = (y - cy) / ay;
          if (dx * dx + dy * dy > 1.0) continue;
        }
        tex[static_cast<std::size_t>(y * size + x)] = level;
      }
    }
  }
  return tex;
}

// The texture's mip pyramid: level 0 is `tex`, each next level a 2x2 box average.
std::vector<std::vector<std::uint8_t>> make_mips(std::vector<std::uint8_t> tex, int size) {
  std::vector<std::vector<std::uint8_t>> levels;
  levels.push_back(std::move(tex));
  for (int s = size / 2; s >= kMinMipSize; s /= 2) {
    const std::vector<std::uint8_t>& src = levels.back();
    const auto n = static_cast<std::size_t>(s);
    std::vector<std::uint8_t> dst(n * n);
    for (std::size_t y = 0; y < n; ++y) {
      for (std::size_t x = 0; x < n; ++x) {
        const std::size_t i = 2 * y * 2 * n + 2 * x;
        const int sum = src[i] + src[i + 1] + src[i + 2 * n] + src[i + 2 * n + 1];
        dst[y * n + x] = static_cast<std::uint8_t>((sum + 2) / 4);
      }
    }
    levels.push_back(std::move(dst));
  }
  return levels;
}

// A box standing on the floor: footprint centre (cx, cy), sides sx, sy, height sz, m.
SceneBox box_on_floor(double cx, double cy, double sx, double sy, double sz, int texture) {
  return SceneBox{
      Eigen::Vector3f(static_cast<float>(cx - 0.5 * sx), static_cast<float>(cy - 0.5 * sy), 0.0F),
      Eigen::Vector3f(static_cast<float>(cx + 0.5 * sx), static_cast<float>(cy + 0.5 * sy),
                      static_cast<float>(sz)),
      texture};
}

// Distance in the plane from (x, y) to the rectangle [-hx, hx] x [-hy, hy] (0 inside).
double rect_distance(double x, double y, double hx, double hy) {
  return std::hypot(std::max(std::abs(x) - hx, 0.0), std::max(std::abs(y) - hy, 0.0));
}

}  // namespace

std::span<const std::string_view> synthetic_scenarios() {
  return kScenarios;
}

SyntheticCamera::SyntheticCamera(std::string scenario, const SyntheticOptions& opts, bool paced)
    : scenario_(std::move(scenario)), opts_(opts), paced_(paced) {}

Status SyntheticCamera::open(std::size_t pool_size) {
  if (std::find(kScenarios.begin(), kScenarios.end(), scenario_) == kScenarios.end()) {
    std::string names;
    for (auto s : kScenarios) names += (names.empty() ? "" : ", ") + std::string(s);
    return input_error("synthetic:" + scenario_ + ": unknown scenario (available: " + names + ")");
  }
  if (Status s = options::validate(opts_); !s.is_ok()) return s;
  kind_ = scenario_ == "room_loop"            ? Scenario::kLoop
          : scenario_ == "room_kidnap"        ? Scenario::kKidnap
          : scenario_ == "room_fast_rotation" ? Scenario::kFastRotation
          : scenario_ == "hall_drive"         ? Scenario::kHallDrive
                                              : Scenario::kOrbit;
  const bool hall = kind_ == Scenario::kHallDrive;
  const double sx = hall ? opts_.hall_size_x : opts_.room_size_x;
  const double sy = hall ? opts_.hall_size_y : opts_.room_size_y;
  const double sz = hall ? opts_.hall_height : opts_.room_height;
  room_lo_ = {static_cast<float>(-0.5 * sx), static_cast<float>(-0.5 * sy), 0.0F};
  room_hi_ = {static_cast<float>(0.5 * sx), static_cast<float>(0.5 * sy), static_cast<float>(sz)};
  texture_size_ = opts_.texture_size * (hall ? kHallTextureScale : 1);
  for (int a = 0; a < 3; ++a) {
    wall_texels_per_m_[static_cast<std::size_t>(a)] =
        static_cast<float>(texture_size_) /
        (room_hi_[static_cast<std::size_t>(a)] - room_lo_[static_cast<std::size_t>(a)]);
  }
  box_texture_metres_ = static_cast<float>(hall ? kHallBoxTextureMetres : kBoxTextureMetres);
  // The rooms are seen at about one texel per pixel; the hall spans 1-60 m of depth and
  // would alias without levels.
  use_mips_ = hall;
  if (pool_size == 0) return invalid_argument("synthetic camera: pool size must be > 0");

  const int w = opts_.width;
  const int h = opts_.height;
  const double f = 0.5 * w / std::tan(0.5 * opts_.fov_x_deg * std::numbers::pi / 180.0);
  intrinsics_ = CameraIntrinsics{w, h, f, f, 0.5 * (w - 1), 0.5 * (h - 1), {}, true};

  rays_.resize(static_cast<std::size_t>(w) * static_cast<std::size_t>(h) * 2);
  for (int v = 0; v < h; ++v) {
    for (int u = 0; u < w; ++u) {
      const std::size_t i = (static_cast<std::size_t>(v) * static_cast<std::size_t>(w) +
                             static_cast<std::size_t>(u)) *
                            2;
      rays_[i] = static_cast<float>((u - intrinsics_.cx) / f);
      rays_[i + 1] = static_cast<float>((v - intrinsics_.cy) / f);
    }
  }
  std::mt19937 rng(static_cast<std::uint32_t>(opts_.seed));
  for (auto& tex : textures_) {
    tex = make_mips(
        hall ? make_texture(texture_size_, kHallShapesPerWall, kHallShapeRadiusMin,
                            kHallShapeRadiusMax, rng)
             : make_texture(texture_size_, kShapesPerWall, kShapeRadiusMin, kShapeRadiusMax, rng),
        texture_size_);
  }
  if (hall) {
    place_hall_boxes(rng());
  } else {
    place_boxes(rng());
  }
  noise_.resize(kNoiseTableSize);
  for (auto& n : noise_) {
    n = static_cast<std::int8_t>(
        std::clamp(std::lround(normal_deviate(rng) * opts_.noise_sigma), -127L, 127L));
  }
  const bool depth = opts_.render_depth;
  pool_ = std::make_unique<FramePool>(pool_size, [w, h, depth](Frame& fr, std::size_t) {
    fr.gray = cv::Mat(h, w, CV_8UC1);
    if (depth) fr.depth = cv::Mat(h, w, CV_32FC1);
  });
  return Status::ok();
}

Status SyntheticCamera::start() {
  if (!pool_) return runtime_error("synthetic camera: start() before open()");
  next_seq_ = 0;
  start_wall_ns_ = platform::monotonic_now_ns();
  started_ = true;
  return Status::ok();
}

void SyntheticCamera::stop() {
  started_ = false;
}

CameraCapabilities SyntheticCamera::capabilities() const {
  return CameraCapabilities{paced_, opts_.render_depth, true, opts_.fps};
}

std::string SyntheticCamera::describe() const {
  char buf[160];
  std::snprintf(buf, sizeof buf, "synthetic:%s (%dx%d @ %g Hz, %d frames, seed %d)",
                scenario_.c_str(), opts_.width, opts_.height, opts_.fps, opts_.num_frames,
                opts_.seed);
  return buf;
}

SE3d SyntheticCamera::orbit_pose(double t_s) const {
  // A handheld-like orbit around the room centre, looking across the room, with slow
  // height and look-at wobble.
  const double a = kTwoPi * t_s / kOrbitPeriodS;
  const Eigen::Vector3d eye(kOrbitRadius * std::cos(a), kOrbitRadius * std::sin(a),
                            kEyeHeight + 0.1 * std::sin(2.3 * a));
  const Eigen::Vector3d target(eye.x() + std::cos(a + 1.2), eye.y() + std::sin(a + 1.2),
                               kEyeHeight + 0.15 * std::sin(1.7 * a));
  return look_at(eye, target, Eigen::Vector3d::UnitZ());
}

double SyntheticCamera::drive_half_x() const {
  return 0.5 * kDrivePathFraction * opts_.hall_size_x;
}
double SyntheticCamera::drive_half_y() const {
  return 0.5 * kDrivePathFraction * opts_.hall_size_y;
}
double SyntheticCamera::drive_radius() const {
  return kDriveCornerFraction * std::min(drive_half_x(), drive_half_y());
}

SE3d SyntheticCamera::drive_pose(double t_s) const {
  // Counter-clockwise round a rounded rectangle, starting mid-way along its lower side
  // heading +x: each side is a straight, each corner a quarter circle of radius r.
  const double hx = drive_half_x();
  const double hy = drive_half_y();
  const double r = drive_radius();
  const double lx = 2.0 * (hx - r);  // straight lengths
  const double ly = 2.0 * (hy - r);
  const double arc = 0.5 * std::numbers::pi * r;
  const double perimeter = 2.0 * (lx + ly) + 4.0 * arc;
  double s = std::fmod(opts_.drive_speed_mps * t_s + 0.5 * lx, perimeter);
  // Side k (k = 0..3) starts at the end of corner k - 1; its straight runs along heading
  // k * 90 degrees from the corner point below.
  Eigen::Vector2d pos;
  double heading = 0.0;
  const std::array<double, 4> straight{lx, ly, lx, ly};
  // Start of each side's straight (lower-left, lower-right, upper-right, upper-left).
  const std::array<Eigen::Vector2d, 4> start{
      Eigen::Vector2d(-(hx - r), -hy), Eigen::Vector2d(hx, -(hy - r)), Eigen::Vector2d(hx - r, hy),
      Eigen::Vector2d(-hx, hy - r)};
  for (std::size_t k = 0; k < 4; ++k) {
    const double h0 = 0.5 * std::numbers::pi * static_cast<double>(k);
    const Eigen::Vector2d dir(std::cos(h0), std::sin(h0));
    if (s < straight[k]) {
      pos = start[k] + s * dir;
      heading = h0;
      break;
    }
    s -= straight[k];
    if (s < arc || k == 3) {
      // Turning left: the centre is r to the left of the straight's end.
      const Eigen::Vector2d end = start[k] + straight[k] * dir;
      const Eigen::Vector2d centre = end + r * Eigen::Vector2d(-dir.y(), dir.x());
      const double phi = std::min(s, arc) / r;
      heading = h0 + phi;
      pos = centre + r * Eigen::Vector2d(std::sin(heading), -std::cos(heading));
      break;
    }
    s -= arc;
  }
  // A car's gentle bounce and pitch.
  const double bounce = 0.02 * std::sin(kTwoPi * 1.3 * t_s);
  const double pitch = 0.01 * std::sin(kTwoPi * 0.7 * t_s);
  const Eigen::Vector3d eye(pos.x(), pos.y(), kDriveEyeHeight + bounce);
  const Eigen::Vector3d target = eye + Eigen::Vector3d(std::cos(heading), std::sin(heading), pitch);
  return look_at(eye, target, Eigen::Vector3d::UnitZ());
}

ScenarioSample SyntheticCamera::sample_at(double t_s) const {
  ScenarioSample s;
  switch (kind_) {
    case Scenario::kOrbit:
      s.T_w_c = orbit_pose(t_s);
      break;
    case Scenario::kLoop: {
      // Counter-clockwise ellipse, looking ahead and turned outwards (to the right).
      const double phi = kTwoPi * t_s / kLoopPeriodS;
      const Eigen::Vector3d eye(kLoopSemiAxisX * std::cos(phi), kLoopSemiAxisY * std::sin(phi),
                                kEyeHeight + 0.05 * std::sin(3.0 * phi));
      const double heading =
          std::atan2(kLoopSemiAxisY * std::cos(phi), -kLoopSemiAxisX * std::sin(phi)) -
          kLoopOutwardRad;
      const Eigen::Vector3d target = eye + Eigen::Vector3d(std::cos(heading), std::sin(heading),
                                                           -0.05 + 0.05 * std::sin(2.0 * phi));
      s.T_w_c = look_at(eye, target, Eigen::Vector3d::UnitZ());
      break;
    }
    case Scenario::kKidnap: {
      const double black_end = opts_.kidnap_start_s + opts_.kidnap_black_s;
      if (t_s < opts_.kidnap_start_s) {
        s.T_w_c = orbit_pose(t_s);
      } else if (t_s < black_end) {
        s.T_w_c = orbit_pose(opts_.kidnap_start_s);
        s.visible = false;
      } else {
        s.T_w_c = orbit_pose(std::max(0.0, t_s - opts_.kidnap_black_s - opts_.kidnap_back_s));
      }
      break;
    }
    case Scenario::kFastRotation: {
      const double in_period = std::fmod(t_s, kBurstPeriodS);
      const double turns = std::floor(t_s / kBurstPeriodS) +
                           smoothstep((in_period - kBurstStartS) / opts_.rotation_burst_s);
      const SE3d base = orbit_pose(t_s);
      SE3d T = base;
      // Yaw about the world vertical through the camera centre.
      T.linear() = Eigen::AngleAxisd(kTwoPi * turns, Eigen::Vector3d::UnitZ()).toRotationMatrix() *
                   base.linear();
      s.T_w_c = T;
      break;
    }
    case Scenario::kHallDrive:
      s.T_w_c = drive_pose(t_s);
      break;
  }
  return s;
}

void SyntheticCamera::place_boxes(std::uint32_t seed) {
  // Boxes stand on the floor, inside the room, and clear of every scripted camera path
  // (the orbit circle lies inside the loop ellipse, so clearing the ellipse clears both).
  std::mt19937 rng(seed);
  boxes_.clear();
  const double hx = 0.5 * opts_.room_size_x - kWallMargin;
  const double hy = 0.5 * opts_.room_size_y - kWallMargin;
  const double ax = kLoopSemiAxisX + kBoxClearance;
  const double ay = kLoopSemiAxisY + kBoxClearance;
  for (int b = 0; b < opts_.num_boxes; ++b) {
    for (int attempt = 0; attempt < kBoxPlacementTries; ++attempt) {
      const double sx = uniform(rng, 0.3, 0.8);
      const double sy = uniform(rng, 0.3, 0.8);
      const double sz = uniform(rng, 0.3, 1.2);
      const double cx = uniform(rng, -hx + 0.5 * sx, hx - 0.5 * sx);
      const double cy = uniform(rng, -hy + 0.5 * sy, hy - 0.5 * sy);
      // In ellipse-normalized coordinates the footprint is still an axis-aligned rectangle;
      // it clears the ellipse when its point closest to the centre lies outside it.
      const double nx = std::clamp(0.0, (cx - 0.5 * sx) / ax, (cx + 0.5 * sx) / ax);
      const double ny = std::clamp(0.0, (cy - 0.5 * sy) / ay, (cy + 0.5 * sy) / ay);
      const bool clear = nx * nx + ny * ny > 1.0;
      if (!clear) continue;
      boxes_.push_back(
          box_on_floor(cx, cy, sx, sy, sz, static_cast<int>(rng() % textures_.size())));
      break;
    }
  }
}

void SyntheticCamera::place_hall_boxes(std::uint32_t seed) {
  // Buildings and parked vehicles: boxes on the floor, clear of the drive by
  // kDriveBoxClearance on either side (inside the block or outside it).
  std::mt19937 rng(seed);
  boxes_.clear();
  const double hx = 0.5 * opts_.hall_size_x - kWallMargin;
  const double hy = 0.5 * opts_.hall_size_y - kWallMargin;
  const double r = drive_radius();
  const double ix = drive_half_x() - r;  // the path is the set at distance r from this rectangle
  const double iy = drive_half_y() - r;
  for (int b = 0; b < opts_.num_boxes; ++b) {
    for (int attempt = 0; attempt < kBoxPlacementTries; ++attempt) {
      const double sx = uniform(rng, kDriveBoxMinSide, kDriveBoxMaxSide);
      const double sy = uniform(rng, kDriveBoxMinSide, kDriveBoxMaxSide);
      const double sz = uniform(rng, kDriveBoxMinHeight, kDriveBoxMaxHeight);
      const double cx = uniform(rng, -hx + 0.5 * sx, hx - 0.5 * sx);
      const double cy = uniform(rng, -hy + 0.5 * sy, hy - 0.5 * sy);
      // Distance from the footprint to the inner rectangle (per-axis gaps), and from its
      // farthest corner.
      const double gap_x = std::max(0.0, std::abs(cx) - 0.5 * sx - ix);
      const double gap_y = std::max(0.0, std::abs(cy) - 0.5 * sy - iy);
      const double d_min = std::hypot(gap_x, gap_y);
      double d_max = 0.0;
      for (int c = 0; c < 4; ++c) {
        const double x = cx + ((c & 1) != 0 ? 0.5 : -0.5) * sx;
        const double y = cy + ((c & 2) != 0 ? 0.5 : -0.5) * sy;
        d_max = std::max(d_max, rect_distance(x, y, ix, iy));
      }
      const bool clear = d_min > r + kDriveBoxClearance || d_max < r - kDriveBoxClearance;
      if (!clear) continue;
      boxes_.push_back(
          box_on_floor(cx, cy, sx, sy, sz, static_cast<int>(rng() % textures_.size())));
      break;
    }
  }
}

void SyntheticCamera::render(const SE3d& T_w_c, cv::Mat& gray, cv::Mat* depth,
                             std::uint64_t noise_offset, float gain) const {
  const Eigen::Matrix3f R = T_w_c.linear().cast<float>();
  const Eigen::Vector3f o = T_w_c.translation().cast<float>();
  const std::array<float, 3>& lo = room_lo_;
  const std::array<float, 3>& hi = room_hi_;
  const int tsize = texture_size_;
  const float box_texels_per_m = static_cast<float>(tsize - 1) / box_texture_metres_;
  const float inv_f = 1.0F / static_cast<float>(intrinsics_.fx);
  const auto num_levels = static_cast<int>(textures_[0].size());
  const std::size_t noise_mask = kNoiseTableSize - 1;
  std::size_t noise_i = static_cast<std::size_t>(noise_offset * 7919U) & noise_mask;
  const bool noisy = opts_.noise_sigma > 0.0;
  constexpr float kTiny = 1e-9F;
  constexpr float kHuge = 1e30F;

  // Mip level for ray `d` meeting, at depth t, a surface with `texels_per_m` level-0 texels
  // per metre whose normal is world axis `normal_axis` (0 without mips).
  auto level_for = [&](const Eigen::Vector3f& d, float t, float texels_per_m, int normal_axis) {
    if (!use_mips_) return 0;
    const float cos_n = std::abs(d[normal_axis]) / d.norm();
    const float footprint = t * inv_f * texels_per_m / std::max(cos_n, kMinObliqueCos);
    if (footprint <= 1.0F) return 0;
    return std::min(static_cast<int>(std::log2(footprint)), num_levels - 1);
  };
  // Bilinear lookup at level-0 texel coordinates (fu, fv) in [0, tsize - 1) of `level`.
  auto sample = [tsize](const std::vector<std::vector<std::uint8_t>>& texture, int level, float fu,
                        float fv) {
    const int size = tsize >> level;
    const float scale = 1.0F / static_cast<float>(1 << level);
    const float lmax = static_cast<float>(size - 1) - 1e-3F;
    fu = std::min(std::max(fu * scale - 0.5F * (1.0F - scale), 0.0F), lmax);
    fv = std::min(std::max(fv * scale - 0.5F * (1.0F - scale), 0.0F), lmax);
    const int iu = static_cast<int>(fu);
    const int iv = static_cast<int>(fv);
    const float au = fu - static_cast<float>(iu);
    const float av = fv - static_cast<float>(iv);
    const std::uint8_t* t = texture[static_cast<std::size_t>(level)].data() +
                            static_cast<std::size_t>(iv) * static_cast<std::size_t>(size) +
                            static_cast<std::size_t>(iu);
    const float top = t[0] + au * (static_cast<float>(t[1]) - t[0]);
    const float bot = t[size] + au * (static_cast<float>(t[size + 1]) - t[size]);
    return top + av * (bot - top);
  };
  const float tmax = static_cast<float>(tsize - 1) - 1e-3F;
  // Repeating texture coordinate for box faces.
  auto wrap = [tmax, box_texels_per_m](float metres) {
    const float f = metres * box_texels_per_m;
    return f - tmax * std::floor(f / tmax);
  };

  // Per-frame culling: each box is only tested for the pixels inside its projected
  // bounding rectangle (the whole image when a corner is behind the camera).
  struct BoxWindow {
    const SceneBox* box;
    int u0, u1, v0, v1;
  };
  std::array<BoxWindow, kMaxBoxes> windows{};
  std::size_t num_windows = 0;
  const Eigen::Matrix3f R_c_w = R.transpose();
  for (const SceneBox& b : boxes_) {
    float u_min = kHuge, u_max = -kHuge, v_min = kHuge, v_max = -kHuge;
    int behind = 0;
    for (int c = 0; c < 8; ++c) {
      const Eigen::Vector3f corner((c & 1) ? b.hi.x() : b.lo.x(), (c & 2) ? b.hi.y() : b.lo.y(),
                                   (c & 4) ? b.hi.z() : b.lo.z());
      const Eigen::Vector3f p_c = R_c_w * (corner - o);
      if (p_c.z() <= kNearPlane) {
        ++behind;
        continue;
      }
      const float u = static_cast<float>(intrinsics_.fx) * p_c.x() / p_c.z() +
                      static_cast<float>(intrinsics_.cx);
      const float v = static_cast<float>(intrinsics_.fy) * p_c.y() / p_c.z() +
                      static_cast<float>(intrinsics_.cy);
      u_min = std::min(u_min, u);
      u_max = std::max(u_max, u);
      v_min = std::min(v_min, v);
      v_max = std::max(v_max, v);
    }
    if (behind == 8) continue;
    BoxWindow w{&b, 0, gray.cols - 1, 0, gray.rows - 1};
    if (behind == 0) {
      w.u0 = static_cast<int>(std::max(0.0F, std::floor(u_min) - 1.0F));
      w.u1 = static_cast<int>(std::min(static_cast<float>(gray.cols - 1), std::ceil(u_max) + 1.0F));
      w.v0 = static_cast<int>(std::max(0.0F, std::floor(v_min) - 1.0F));
      w.v1 = static_cast<int>(std::min(static_cast<float>(gray.rows - 1), std::ceil(v_max) + 1.0F));
      if (w.u0 > w.u1 || w.v0 > w.v1) continue;
    }
    windows[num_windows++] = w;
  }

  for (int v = 0; v < gray.rows; ++v) {
    std::uint8_t* row = gray.ptr<std::uint8_t>(v);
    float* drow = (depth != nullptr && !depth->empty()) ? depth->ptr<float>(v) : nullptr;
    const float* ray =
        rays_.data() + static_cast<std::size_t>(v) * static_cast<std::size_t>(gray.cols) * 2;
    for (int u = 0; u < gray.cols; ++u, ray += 2) {
      const Eigen::Vector3f d = R * Eigen::Vector3f(ray[0], ray[1], 1.0F);
      const Eigen::Vector3f inv(std::abs(d.x()) > kTiny ? 1.0F / d.x() : kHuge,
                                std::abs(d.y()) > kTiny ? 1.0F / d.y() : kHuge,
                                std::abs(d.z()) > kTiny ? 1.0F / d.z() : kHuge);
      // Exit distance through the room along each axis; the smallest one is the wall hit.
      float t = kHuge;
      int axis = 0;
      int side = 0;
      for (int a = 0; a < 3; ++a) {
        const int s = d[a] > 0.0F ? 1 : 0;
        const float ta = ((s != 0 ? hi[a] : lo[a]) - o[a]) * inv[a];
        if (ta > 0.0F && ta < t) {
          t = ta;
          axis = a;
          side = s;
        }
      }
      // Nearest box in front of the wall (slab test).
      const SceneBox* hit_box = nullptr;
      int box_axis = 0;
      for (std::size_t k = 0; k < num_windows; ++k) {
        const BoxWindow& w = windows[k];
        if (u < w.u0 || u > w.u1 || v < w.v0 || v > w.v1) continue;
        const SceneBox& b = *w.box;
        float t_near = 0.0F;
        float t_far = kHuge;
        int near_axis = 0;
        for (int a = 0; a < 3; ++a) {
          float t1 = (b.lo[a] - o[a]) * inv[a];
          float t2 = (b.hi[a] - o[a]) * inv[a];
          if (t1 > t2) std::swap(t1, t2);
          if (t1 > t_near) {
            t_near = t1;
            near_axis = a;
          }
          t_far = std::min(t_far, t2);
        }
        if (t_near > 0.0F && t_near <= t_far && t_near < t) {
          t = t_near;
          hit_box = &b;
          box_axis = near_axis;
        }
      }
      const Eigen::Vector3f p = o + t * d;
      float value = 0.0F;
      if (hit_box != nullptr) {
        const int pa = box_axis == 0 ? 1 : 0;
        const int qa = box_axis == 2 ? 1 : 2;
        value = sample(textures_[static_cast<std::size_t>(hit_box->texture)],
                       level_for(d, t, box_texels_per_m, box_axis), wrap(p[pa] - hit_box->lo[pa]),
                       wrap(p[qa] - hit_box->lo[qa]));
      } else {
        const int pa = axis == 0 ? 1 : 0;
        const int qa = axis == 2 ? 1 : 2;
        const float fu = std::clamp((p[pa] - lo[pa]) / (hi[pa] - lo[pa]), 0.0F, 1.0F) * tmax;
        const float fv = std::clamp((p[qa] - lo[qa]) / (hi[qa] - lo[qa]), 0.0F, 1.0F) * tmax;
        const float texels_per_m = std::max(wall_texels_per_m_[static_cast<std::size_t>(pa)],
                                            wall_texels_per_m_[static_cast<std::size_t>(qa)]);
        value = sample(textures_[static_cast<std::size_t>(axis * 2 + side)],
                       level_for(d, t, texels_per_m, axis), fu, fv);
      }
      value *= gain;
      if (noisy) {
        value += static_cast<float>(noise_[noise_i]);
        noise_i = (noise_i + 1) & noise_mask;
      }
      row[u] = static_cast<std::uint8_t>(std::clamp(value + 0.5F, 0.0F, 255.0F));
      if (drow != nullptr) drow[u] = t;  // ray has z = 1 in the camera: t is the depth
    }
  }
}

AcquireStatus SyntheticCamera::acquire(FrameHandle& out, std::int64_t timeout_ns) {
  if (!started_ || next_seq_ >= static_cast<std::uint64_t>(opts_.num_frames)) {
    return AcquireStatus::kEndOfStream;
  }
  const auto period_ns = static_cast<std::int64_t>(kNsPerS / opts_.fps);
  const std::int64_t t_ns = static_cast<std::int64_t>(next_seq_) * period_ns;
  if (paced_) {
    const std::int64_t due = start_wall_ns_ + t_ns;
    const std::int64_t wait = due - platform::monotonic_now_ns();
    if (wait > timeout_ns) {
      std::this_thread::sleep_for(std::chrono::nanoseconds(timeout_ns));
      return AcquireStatus::kTimeout;
    }
    if (wait > 0) std::this_thread::sleep_for(std::chrono::nanoseconds(wait));
  }
  const std::int64_t t_work = platform::monotonic_now_ns();
  FrameHandle h = pool_->acquire();
  if (!h) return AcquireStatus::kPoolEmpty;
  Frame& f = *h;
  f.seq = next_seq_;
  f.t_ns = t_ns;
  const double t_s = static_cast<double>(t_ns) / kNsPerS;
  const ScenarioSample sample = sample_at(t_s);
  f.T_w_c_gt = sample.T_w_c;
  f.has_ground_truth = sample.visible;
  if (sample.visible) {
    const double gain =
        1.0 + opts_.exposure_amplitude * std::sin(kTwoPi * t_s / opts_.exposure_period_s);
    render(f.T_w_c_gt, f.gray, opts_.render_depth ? &f.depth : nullptr, next_seq_,
           static_cast<float>(gain));
  } else {
    // Blacked out (lens covered): an all-black image and no depth.
    f.gray.setTo(0);
    if (opts_.render_depth) f.depth.setTo(0.0F);
  }
  ++next_seq_;
  f.t_ready_ns = platform::monotonic_now_ns();
  f.produce_ns = f.t_ready_ns - t_work;
  out = std::move(h);
  return AcquireStatus::kFrame;
}

}  // namespace mer::hal
