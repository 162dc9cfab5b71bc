#include "hal/synthetic/synthetic_camera.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <numbers>
#include <random>
#include <thread>

#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "platform/clock.h"

namespace mer::hal {
namespace {

constexpr std::array<std::string_view, 12> kScenarios{
    "room_orbit", "room_loop",           "room_kidnap",   "room_fast_rotation",
    "hall_drive", "hall_turn",           "room_explore",  "room_rotation",
    "corridor",   "room_kidnap_unknown", "room_repeated", "hall_repeated"};
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
// Reproduction scenarios (hall_turn ... room_kidnap_unknown).
constexpr double kPathStepS = 1e-3;      // hall_turn: path table step, s
constexpr double kTurnPathMargin = 5.0;  // hall_turn: the path keeps this far from walls, m
constexpr double kSecondTurnRad = 0.5 * std::numbers::pi;  // hall_turn: second left turn
constexpr double kBoxPathSampleS = 0.05;    // boxes are kept clear of the camera sampled so
constexpr double kBoxPathMaxS = 120.0;      // ... over at most this much of the sequence, s
constexpr double kRoomPathClearance = 0.6;  // new room scenarios: box clearance, m
constexpr double kFurnitureMinSide = 0.4;   // new room scenarios: box footprint side, m
constexpr double kFurnitureMaxSide = 1.2;
constexpr double kFurnitureMinHeight = 0.4;  // new room scenarios: box height, m
constexpr double kFurnitureMaxHeight = 1.8;
constexpr double kExploreHalfX = 0.85;  // room_explore: rounded rectangle half extents, m
constexpr double kExploreHalfY = 0.55;
constexpr double kExploreRadius = 0.4;         // room_explore: its corner radius, m
constexpr double kExploreOutwardRad = 0.7;     // room_explore: view turned 40 deg outwards
constexpr double kWalkEyeHeight = 1.45;        // walking scenarios: camera height, m
constexpr double kCorridorTexelsPerM = 160.0;  // corridor: texture density, texels per metre
constexpr double kCorridorEndGap = 1.5;        // corridor: turn round this far from the ends, m
constexpr double kCorridorTurnS = 3.0;         // corridor: duration of the turn round, s
constexpr double kCorridorWhite = 200.0;       // corridor: grey level of the painted walls
constexpr double kKidnapLookS = 1.5;           // room_kidnap_unknown: looks round this long, s
constexpr int kMinMipSize = 8;                 // coarsest texture level, texels per side
constexpr float kMinObliqueCos = 0.25F;        // obliquity taken into a pixel footprint at most 4x

// Look-alike places (repeat_texture, room_repeated, hall_repeated).
constexpr double kRoomPanelW = 2.0;        // rooms and the corridor: panel width, m
constexpr double kRoomPanelH = 1.4;        // ... height, m
constexpr double kRoomPanelZ = 0.7;        // ... height of its lower edge, m
constexpr double kHallPanelW = 3.0;        // halls: panel width, m
constexpr double kHallPanelH = 2.4;        // ... height, m
constexpr double kHallPanelZ = 0.6;        // ... height of its lower edge, m
constexpr double kPanelFill = 0.9;         // copies sharing a wall fill at most this fraction
constexpr double kPanelFrameM = 0.05;      // the panel's dark frame, m
constexpr double kPanelFrameGrey = 30.0;   // ... its grey level
constexpr double kPanelKeepOut = 3.5;      // boxes keep off the floor this far out of a panel, m
constexpr double kPanelKeepOutSide = 0.3;  // ... and this far beyond its sides, m
constexpr std::uint32_t kPanelSalt = 0x2545F491U;  // the panel's crop: its own random stream
constexpr double kRepeatSettleS = 2.0;             // room_repeated: facing A before the lap, s
constexpr double kRepeatLapGapS = 1.0;       // room_repeated: the lap ends this before the blackout
constexpr double kRepeatMinLapS = 3.0;       // room_repeated: shortest lap, s
constexpr double kRepeatRadius = 0.9;        // room_repeated: lap radius about the room centre, m
constexpr double kRepeatSway = 0.12;         // room_repeated: sideways sway amplitude, m
constexpr double kRepeatApproachMps = 0.08;  // room_repeated: stepping towards A, m/s
constexpr double kRepeatApproachMax = 0.5;   // ... at most this far, m
constexpr double kRepeatAfterS = 3.0;        // room_repeated: facing A after the blackout, s
constexpr double kRepeatLeaveS = 8.0;        // room_repeated: the walk to the +y half, s
constexpr double kHallRepeatGap = 4.0;       // hall_repeated: the path keeps this far from walls, m
constexpr double kHallRepeatLookRad = 35.0 * std::numbers::pi / 180.0;  // view right of travel

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

// Mip pyramid of a w x h texture: each next level a 2x2 box average, down to kMinMipSize.
std::vector<std::vector<std::uint8_t>> make_mips_rect(std::vector<std::uint8_t> tex, int w, int h) {
  std::vector<std::vector<std::uint8_t>> levels;
  levels.push_back(std::move(tex));
  for (int l = 1; (w >> l) >= kMinMipSize && (h >> l) >= kMinMipSize; ++l) {
    const std::vector<std::uint8_t>& src = levels.back();
    const auto sw = static_cast<std::size_t>(w >> (l - 1));
    const auto dw = static_cast<std::size_t>(w >> l);
    const auto dh = static_cast<std::size_t>(h >> l);
    std::vector<std::uint8_t> dst(dw * dh);
    for (std::size_t y = 0; y < dh; ++y) {
      for (std::size_t x = 0; x < dw; ++x) {
        const std::size_t i = 2 * y * sw + 2 * x;
        const int sum = src[i] + src[i + 1] + src[i + sw] + src[i + sw + 1];
        dst[y * dw + x] = static_cast<std::uint8_t>((sum + 2) / 4);
      }
    }
    levels.push_back(std::move(dst));
  }
  return levels;
}

// A 64-bit mix (splitmix64): exposure-step signs from (seed, step index), no state.
std::uint64_t mix64(std::uint64_t x) {
  x += 0x9E3779B97F4A7C15ULL;
  x = (x ^ (x >> 30U)) * 0xBF58476D1CE4E5B9ULL;
  x = (x ^ (x >> 27U)) * 0x94D049BB133111EBULL;
  return x ^ (x >> 31U);
}

// Cubic 0 -> 1 over s in [0, 1] with slope a at 0 and 0 at 1 (a = 0: smoothstep).
double ease_out(double s, double a) {
  s = std::clamp(s, 0.0, 1.0);
  return a * s + (3.0 - 2.0 * a) * s * s + (a - 2.0) * s * s * s;
}

// Point at arc length s (any real) of the counter-clockwise rounded rectangle with half
// extents (hx, hy) and corner radius r, centred at the origin, starting mid-way along its
// lower side heading +x. Returns the position; `heading` gets the direction of travel.
Eigen::Vector2d rounded_rect_point(double s, double hx, double hy, double r, double& heading) {
  const double lx = 2.0 * (hx - r);
  const double ly = 2.0 * (hy - r);
  const double arc = 0.5 * std::numbers::pi * r;
  const double perimeter = 2.0 * (lx + ly) + 4.0 * arc;
  s = std::fmod(s + 0.5 * lx, perimeter);
  if (s < 0.0) s += perimeter;
  const std::array<double, 4> straight{lx, ly, lx, ly};
  const std::array<Eigen::Vector2d, 4> start{
      Eigen::Vector2d(-(hx - r), -hy), Eigen::Vector2d(hx, -(hy - r)), Eigen::Vector2d(hx - r, hy),
      Eigen::Vector2d(-hx, hy - r)};
  for (std::size_t k = 0; k < 4; ++k) {
    const double h0 = 0.5 * std::numbers::pi * static_cast<double>(k);
    const Eigen::Vector2d dir(std::cos(h0), std::sin(h0));
    if (s < straight[k]) {
      heading = h0;
      return start[k] + s * dir;
    }
    s -= straight[k];
    if (s < arc || k == 3) {
      const Eigen::Vector2d centre =
          start[k] + straight[k] * dir + r * Eigen::Vector2d(-dir.y(), dir.x());
      heading = h0 + std::min(s, arc) / r;
      return centre + r * Eigen::Vector2d(std::sin(heading), -std::cos(heading));
    }
    s -= arc;
  }
  heading = 0.0;
  return start[0];
}

// Camera at `eye` looking along heading (about world z) and pitch (up positive), rad.
SE3d heading_pose(const Eigen::Vector3d& eye, double heading, double pitch) {
  const Eigen::Vector3d dir(std::cos(pitch) * std::cos(heading),
                            std::cos(pitch) * std::sin(heading), std::sin(pitch));
  return look_at(eye, eye + dir, Eigen::Vector3d::UnitZ());
}

// A random crop of `photo` with side `frac` of its smaller side and the aspect w : h,
// resized to w x h (grey, CV_8UC1).
cv::Mat photo_crop(const cv::Mat& photo, int w, int h, double frac, std::mt19937& rng) {
  const double aspect = static_cast<double>(w) / static_cast<double>(h);
  double ch = frac * std::min(photo.rows, static_cast<int>(photo.cols / aspect));
  ch = std::max(ch, 2.0);
  const double cw = std::min(static_cast<double>(photo.cols), ch * aspect);
  const int x0 = static_cast<int>(uniform(rng, 0.0, std::max(0.0, photo.cols - cw)));
  const int y0 = static_cast<int>(uniform(rng, 0.0, std::max(0.0, photo.rows - ch)));
  cv::Mat out;
  cv::resize(
      photo(cv::Rect(x0, y0, std::max(1, static_cast<int>(cw)), std::max(1, static_cast<int>(ch)))),
      out, cv::Size(w, h), 0.0, 0.0, cv::INTER_AREA);
  return out;
}

// True for file stems like "Name_3840x2160" (a resolution variant of another photo).
bool is_resolution_variant(const std::string& stem) {
  const std::size_t us = stem.rfind('_');
  if (us == std::string::npos) return false;
  const std::string tail = stem.substr(us + 1);
  const std::size_t x = tail.find('x');
  if (x == std::string::npos || x == 0 || x + 1 == tail.size()) return false;
  for (std::size_t i = 0; i < tail.size(); ++i) {
    if (i != x && (tail[i] < '0' || tail[i] > '9')) return false;
  }
  return true;
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
  kind_ = scenario_ == "room_loop"             ? Scenario::kLoop
          : scenario_ == "room_kidnap"         ? Scenario::kKidnap
          : scenario_ == "room_fast_rotation"  ? Scenario::kFastRotation
          : scenario_ == "hall_drive"          ? Scenario::kHallDrive
          : scenario_ == "hall_turn"           ? Scenario::kHallTurn
          : scenario_ == "room_explore"        ? Scenario::kRoomExplore
          : scenario_ == "room_rotation"       ? Scenario::kRoomRotation
          : scenario_ == "corridor"            ? Scenario::kCorridor
          : scenario_ == "room_kidnap_unknown" ? Scenario::kKidnapUnknown
          : scenario_ == "room_repeated"       ? Scenario::kRoomRepeated
          : scenario_ == "hall_repeated"       ? Scenario::kHallRepeated
                                               : Scenario::kOrbit;
  const bool hall = kind_ == Scenario::kHallDrive || kind_ == Scenario::kHallTurn ||
                    kind_ == Scenario::kHallRepeated;
  const bool corridor = kind_ == Scenario::kCorridor;
  // The scenarios before hall_turn keep their procedural textures and boxes bit for bit.
  const bool reproduction = static_cast<int>(kind_) >= static_cast<int>(Scenario::kHallTurn);
  const double sx = hall ? opts_.hall_size_x : corridor ? opts_.corridor_length : opts_.room_size_x;
  const double sy = hall ? opts_.hall_size_y : corridor ? opts_.corridor_width : opts_.room_size_y;
  const double sz = hall ? opts_.hall_height : corridor ? opts_.corridor_height : opts_.room_height;
  room_lo_ = {static_cast<float>(-0.5 * sx), static_cast<float>(-0.5 * sy), 0.0F};
  room_hi_ = {static_cast<float>(0.5 * sx), static_cast<float>(0.5 * sy), static_cast<float>(sz)};
  texture_size_ = opts_.texture_size * (hall ? kHallTextureScale : 1);
  box_texture_metres_ = static_cast<float>(hall ? kHallBoxTextureMetres : kBoxTextureMetres);
  // The rooms are seen at about one texel per pixel; the hall spans 1-60 m of depth and the
  // corridor 0.5-20 m: they would alias without levels.
  use_mips_ = hall || corridor;
  if (pool_size == 0) return invalid_argument("synthetic camera: pool size must be > 0");
  if (kind_ == Scenario::kHallTurn) {
    if (Status s = make_turn_path_checked(); !s.is_ok()) return s;
  }
  if (Status s = check_repeated_script(); !s.is_ok()) return s;

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
  const bool photo = opts_.texture == "photo" || (opts_.texture == "auto" && reproduction);
  photo_files_.clear();
  std::vector<cv::Mat> photos;
  if (photo) {
    if (Status s = load_wall_photos(rng, photos); !s.is_ok()) return s;
  }
  if (corridor) {
    if (!photo) {
      for (std::size_t k = 0; k < textures_.size(); ++k) {
        std::vector<std::uint8_t> tex =
            make_texture(texture_size_, kShapesPerWall, kShapeRadiusMin, kShapeRadiusMax, rng);
        photos.push_back(cv::Mat(texture_size_, texture_size_, CV_8UC1, tex.data()).clone());
      }
    }
    make_corridor_textures(photos, rng);
  } else if (photo) {
    make_photo_textures(photos, rng);
  } else {
    for (auto& tex : textures_) {
      tex.w = texture_size_;
      tex.h = texture_size_;
      tex.levels = make_mips(
          hall ? make_texture(texture_size_, kHallShapesPerWall, kHallShapeRadiusMin,
                              kHallShapeRadiusMax, rng)
               : make_texture(texture_size_, kShapesPerWall, kShapeRadiusMin, kShapeRadiusMax, rng),
          texture_size_);
    }
  }
  for (std::size_t k = 0; k < textures_.size(); ++k) {
    const auto a = k / 2;
    const std::size_t pa = a == 0 ? 1 : 0;
    const std::size_t qa = a == 2 ? 1 : 2;
    wall_texels_per_m_[k] =
        std::max(static_cast<float>(textures_[k].w) / (room_hi_[pa] - room_lo_[pa]),
                 static_cast<float>(textures_[k].h) / (room_hi_[qa] - room_lo_[qa]));
  }
  // Look-alike places: the panel is cut from the first wall's photo (or its texture).
  if (photos.empty()) {
    std::vector<std::uint8_t>& level0 = textures_[0].levels.front();
    const cv::Mat first(textures_[0].h, textures_[0].w, CV_8UC1, level0.data());
    make_panels(first);
  } else {
    make_panels(photos.front());
  }
  if (kind_ == Scenario::kHallDrive) {
    place_hall_boxes(rng());
  } else if (!reproduction) {
    place_boxes(rng());
  } else if (corridor) {
    boxes_.clear();
  } else {
    place_boxes_clear_of_path(rng(), hall);
  }
  if (!panels_.empty()) {
    for (std::size_t b = 1; b < boxes_.size(); b += 2) boxes_[b].texture = kPanelTexture;
  }
  noise_.resize(kNoiseTableSize);
  for (auto& n : noise_) {
    n = static_cast<std::int8_t>(
        std::clamp(std::lround(normal_deviate(rng) * opts_.noise_sigma), -127L, 127L));
  }
  if (opts_.exposure_time_s > 0.0) {
    blur_scratch_ = cv::Mat(h, w, CV_8UC1);
    blur_sum_.assign(static_cast<std::size_t>(w) * static_cast<std::size_t>(h), 0);
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
    case Scenario::kHallTurn:
      s.T_w_c = turn_pose(t_s);
      break;
    case Scenario::kRoomExplore:
      s.T_w_c = explore_pose(t_s);
      break;
    case Scenario::kRoomRotation:
      s.T_w_c = rotation_pose(t_s);
      break;
    case Scenario::kCorridor:
      s.T_w_c = corridor_pose(t_s);
      break;
    case Scenario::kKidnapUnknown:
      s = kidnap_unknown_sample(t_s);
      break;
    case Scenario::kRoomRepeated:
      s = repeated_room_sample(t_s);
      break;
    case Scenario::kHallRepeated:
      s.T_w_c = repeated_hall_pose(t_s);
      break;
  }
  return s;
}

Status SyntheticCamera::make_turn_path_checked() {
  // A scripted drive, integrated at kPathStepS: (duration, start and end speed, left turn).
  // Turns: the first starts at its full yaw rate (the sequence begins inside it), the
  // second eases in and out; speeds change smoothly on the straights.
  struct Segment {
    double duration_s, v0, v1, turn_rad, initial_rate;
  };
  const double vt = opts_.turn_speed_mps;
  const double vd = opts_.drive_speed_mps;
  const double vm = 0.5 * (vt + vd);
  const std::array<Segment, 7> script{{
      {opts_.turn_duration_s, vt, vt, opts_.turn_angle_deg * std::numbers::pi / 180.0, 1.0},
      {2.0, vt, vm, 0.0, 0.0},
      {1.5, vm, vt, 0.0, 0.0},
      {opts_.turn_duration_s, vt, vt, kSecondTurnRad, 0.0},
      {3.0, vt, vd, 0.0, 0.0},
      {4.0, vd, vd, 0.0, 0.0},
      {3.0, vd, 0.0, 0.0, 0.0},
  }};
  turn_path_.clear();
  PathPoint p;
  turn_path_.push_back(p);
  double t_end = 0.0;
  for (const Segment& seg : script) {
    const auto n = static_cast<int>(std::lround(seg.duration_s / kPathStepS));
    const double h0 = p.heading;
    for (int i = 0; i < n; ++i) {
      const double s = (i + 0.5) / n;
      const double v = seg.v0 + (seg.v1 - seg.v0) * smoothstep(s);
      const double heading = h0 + seg.turn_rad * ease_out(s, seg.initial_rate);
      p.x += v * std::cos(heading) * kPathStepS;
      p.y += v * std::sin(heading) * kPathStepS;
      p.heading = h0 + seg.turn_rad * ease_out((i + 1.0) / n, seg.initial_rate);
      turn_path_.push_back(p);
    }
    t_end += n * kPathStepS;
  }
  turn_path_end_s_ = t_end;
  // Centre the path's bounding box in the hall.
  double x0 = 1e30, x1 = -1e30, y0 = 1e30, y1 = -1e30;
  for (const PathPoint& q : turn_path_) {
    x0 = std::min(x0, q.x);
    x1 = std::max(x1, q.x);
    y0 = std::min(y0, q.y);
    y1 = std::max(y1, q.y);
  }
  const double cx = 0.5 * (x0 + x1);
  const double cy = 0.5 * (y0 + y1);
  for (PathPoint& q : turn_path_) {
    q.x -= cx;
    q.y -= cy;
  }
  if (x1 - x0 + 2.0 * kTurnPathMargin > opts_.hall_size_x ||
      y1 - y0 + 2.0 * kTurnPathMargin > opts_.hall_size_y) {
    char buf[256];
    std::snprintf(buf, sizeof buf,
                  "synthetic:hall_turn: the drive spans %.1f x %.1f m and needs %.0f m to the "
                  "walls; camera.synthetic.hall_size_x/y (%.1f x %.1f m) are too small",
                  x1 - x0, y1 - y0, kTurnPathMargin, opts_.hall_size_x, opts_.hall_size_y);
    return invalid_argument(buf);
  }
  return Status::ok();
}

SE3d SyntheticCamera::turn_pose(double t_s) const {
  PathPoint p;
  if (t_s <= 0.0) {
    // Before the start (motion blur of the first frame): the first turn carried backwards.
    const double rate = opts_.turn_angle_deg * std::numbers::pi / 180.0 / opts_.turn_duration_s;
    const double h = rate * t_s;
    const double r = opts_.turn_speed_mps / rate;
    p = turn_path_.front();
    p.x += r * std::sin(h);
    p.y += r * (1.0 - std::cos(h));
    p.heading = h;
  } else {
    const double fi = t_s / kPathStepS;
    const auto i = static_cast<std::size_t>(fi);
    if (i + 1 >= turn_path_.size()) {
      p = turn_path_.back();  // parked
    } else {
      const double a = fi - static_cast<double>(i);
      const PathPoint& p0 = turn_path_[i];
      const PathPoint& p1 = turn_path_[i + 1];
      p.x = p0.x + a * (p1.x - p0.x);
      p.y = p0.y + a * (p1.y - p0.y);
      p.heading = p0.heading + a * (p1.heading - p0.heading);
    }
  }
  const double bounce = 0.02 * std::sin(kTwoPi * 1.3 * t_s);
  const double pitch = 0.01 * std::sin(kTwoPi * 0.7 * t_s);
  const Eigen::Vector3d eye(p.x, p.y, kDriveEyeHeight + bounce);
  const Eigen::Vector3d target =
      eye + Eigen::Vector3d(std::cos(p.heading), std::sin(p.heading), pitch);
  return look_at(eye, target, Eigen::Vector3d::UnitZ());
}

SE3d SyntheticCamera::explore_pose(double t_s) const {
  // Walking round a rounded rectangle, looking ahead and outwards (to the right), with the
  // sway, bob and look-around of a hand-held phone.
  double heading = 0.0;
  const Eigen::Vector2d pos = rounded_rect_point(opts_.walk_speed_mps * t_s, kExploreHalfX,
                                                 kExploreHalfY, kExploreRadius, heading);
  const Eigen::Vector2d side(std::sin(heading), -std::cos(heading));  // to the right
  const Eigen::Vector2d xy = pos + 0.03 * std::sin(kTwoPi * 0.9 * t_s) * side;
  const Eigen::Vector3d eye(xy.x(), xy.y(), kWalkEyeHeight + 0.02 * std::sin(kTwoPi * 1.8 * t_s));
  const double yaw = heading - kExploreOutwardRad + 0.14 * std::sin(kTwoPi * t_s / 4.7) +
                     0.01 * std::sin(kTwoPi * 2.3 * t_s);
  const double pitch = -0.08 + 0.05 * std::sin(kTwoPi * t_s / 3.1);
  return heading_pose(eye, yaw, pitch);
}

SE3d SyntheticCamera::rotation_pose(double t_s) const {
  // Standing, sweeping the phone left-right and up-down: rotation-dominant from t = 0
  // (the yaw rate is at its peak there).
  const double a = opts_.sweep_translation_m;
  const Eigen::Vector3d eye(0.4 + a * std::sin(kTwoPi * 0.37 * t_s),
                            -0.3 + a * std::sin(kTwoPi * 0.23 * t_s + 1.0),
                            1.35 + 0.6 * a * std::sin(kTwoPi * 0.5 * t_s + 2.0));
  const double y = opts_.sweep_yaw_deg * std::numbers::pi / 180.0;
  const double p = opts_.sweep_pitch_deg * std::numbers::pi / 180.0;
  const double period = opts_.sweep_period_s;
  const double yaw = y * std::sin(kTwoPi * t_s / period) +
                     0.12 * y * std::sin(kTwoPi * t_s / (0.38 * period) + 0.5);
  const double pitch = p * std::sin(kTwoPi * t_s / (0.68 * period) + 0.3);
  return heading_pose(eye, yaw, pitch);
}

SE3d SyntheticCamera::corridor_pose(double t_s) const {
  // Walking along the corridor's x axis, turning round at each end, with head yaw.
  const double d = opts_.corridor_length - 2.0 * kCorridorEndGap;
  const double walk_s = d / opts_.corridor_speed_mps;
  const double cycle = 2.0 * (walk_s + kCorridorTurnS);
  double tau = std::fmod(t_s, cycle);
  if (tau < 0.0) tau += cycle;
  double x = 0.0;
  double heading = 0.0;
  if (tau < walk_s) {
    x = -0.5 * d + opts_.corridor_speed_mps * tau;
  } else if (tau < walk_s + kCorridorTurnS) {
    x = 0.5 * d;
    heading = std::numbers::pi * smoothstep((tau - walk_s) / kCorridorTurnS);
  } else if (tau < 2.0 * walk_s + kCorridorTurnS) {
    x = 0.5 * d - opts_.corridor_speed_mps * (tau - walk_s - kCorridorTurnS);
    heading = std::numbers::pi;
  } else {
    x = -0.5 * d;
    heading = std::numbers::pi *
              (1.0 + smoothstep((tau - 2.0 * walk_s - kCorridorTurnS) / kCorridorTurnS));
  }
  const double lateral = std::min(0.15, 0.5 * opts_.corridor_width - 0.5);
  const Eigen::Vector3d eye(
      x, lateral * std::sin(kTwoPi * t_s / 9.0),
      std::min(1.6, opts_.corridor_height - 0.4) + 0.015 * std::sin(kTwoPi * 1.8 * t_s));
  const double yaw =
      heading + 0.3 * std::sin(kTwoPi * t_s / 5.0) + 0.04 * std::sin(kTwoPi * t_s / 1.3);
  const double pitch = -0.05 + 0.03 * std::sin(kTwoPi * t_s / 3.7);
  return heading_pose(eye, yaw, pitch);
}

ScenarioSample SyntheticCamera::kidnap_unknown_sample(double t_s) const {
  // Phase 1: hand-held, looking at the -x half of the room (heading pi +- 20 deg) with a
  // sideways sway for parallax. After the blackout: in the +x half looking +x (never seen),
  // looks round, then walks and turns left back to phase 1's start pose, and goes on as in
  // phase 1.
  const double x1 = -0.1 * opts_.room_size_x;
  auto phase1 = [x1](double t) {
    const Eigen::Vector3d eye(x1 + 0.1 * std::sin(kTwoPi * t / 7.0),
                              0.45 * std::sin(kTwoPi * t / 8.0),
                              1.35 + 0.04 * std::sin(kTwoPi * t / 5.0));
    const double heading = std::numbers::pi + 0.35 * std::sin(kTwoPi * t / 6.0);
    const double pitch = -0.05 + 0.04 * std::sin(kTwoPi * t / 4.4);
    return std::array<double, 5>{eye.x(), eye.y(), eye.z(), heading, pitch};
  };
  ScenarioSample s;
  const double black_end = opts_.kidnap_start_s + opts_.kidnap_black_s;
  std::array<double, 5> q{};
  if (t_s < opts_.kidnap_start_s) {
    q = phase1(t_s);
  } else if (t_s < black_end) {
    q = phase1(opts_.kidnap_start_s);
    s.visible = false;
  } else {
    const double tau = t_s - black_end;
    const double ret = opts_.kidnap_return_s;
    if (tau >= kKidnapLookS + ret) {
      q = phase1(tau - kKidnapLookS - ret);
    } else {
      // Standing in the +x half, looking round +x.
      const std::array<double, 5> stand{
          0.25 * opts_.room_size_x + 0.04 * std::sin(kTwoPi * tau / 3.0),
          -0.15 * opts_.room_size_y + 0.04 * std::sin(kTwoPi * tau / 4.0), 1.4,
          0.17 * std::sin(kTwoPi * tau / 4.0), -0.04};
      const double u = tau < kKidnapLookS ? 0.0 : smoothstep((tau - kKidnapLookS) / ret);
      const std::array<double, 5> home = phase1(0.0);
      for (std::size_t i = 0; i < q.size(); ++i) q[i] = stand[i] + u * (home[i] - stand[i]);
    }
  }
  s.T_w_c = heading_pose(Eigen::Vector3d(q[0], q[1], q[2]), q[3], q[4]);
  return s;
}

Status SyntheticCamera::check_repeated_script() const {
  char buf[256];
  if (kind_ == Scenario::kRoomRepeated &&
      opts_.kidnap_start_s - kRepeatLapGapS - kRepeatSettleS < kRepeatMinLapS) {
    std::snprintf(buf, sizeof buf,
                  "synthetic:room_repeated: camera.synthetic.kidnap_start_s (%.1f s) must be at "
                  "least %.0f s: the mapping lap ends %.0f s before the blackout",
                  opts_.kidnap_start_s, kRepeatSettleS + kRepeatMinLapS + kRepeatLapGapS,
                  kRepeatLapGapS);
    return invalid_argument(buf);
  }
  if (kind_ == Scenario::kHallRepeated && opts_.hall_size_x < opts_.hall_size_y + 2.0) {
    std::snprintf(buf, sizeof buf,
                  "synthetic:hall_repeated: the hall must be longer than wide: "
                  "camera.synthetic.hall_size_x (%.1f m) must be at least hall_size_y (%.1f m) "
                  "+ 2 m",
                  opts_.hall_size_x, opts_.hall_size_y);
    return invalid_argument(buf);
  }
  return Status::ok();
}

ScenarioSample SyntheticCamera::repeated_room_sample(double t_s) const {
  // Facing A (the -x wall's copy), a lap round a circle about the room centre looking
  // outwards (A, the -y wall, B on the +x wall, the +y wall, A again), facing A while stepping
  // towards it (the blackout falls here; the camera moves on), then a walk to the +y half of
  // the room facing the +y wall. A hand's sway, bob and look-around on top throughout.
  const double t_lap0 = kRepeatSettleS;
  const double t_lap1 = opts_.kidnap_start_s - kRepeatLapGapS;
  const double black_end = opts_.kidnap_start_s + opts_.kidnap_black_s;
  const double t_leave = black_end + kRepeatAfterS;
  // The script's (x, y, heading) at t, before the walk to the +y half.
  auto script = [&](double t) {
    const double phi = std::numbers::pi + kTwoPi * smoothstep((t - t_lap0) / (t_lap1 - t_lap0));
    const double step =
        std::min(kRepeatApproachMps * std::max(0.0, t - t_lap1), kRepeatApproachMax);
    return std::array<double, 3>{kRepeatRadius * std::cos(phi) - step,
                                 kRepeatRadius * std::sin(phi), phi};
  };
  std::array<double, 3> q = script(std::min(t_s, t_leave));
  if (t_s > t_leave) {
    // Turning right by 90 degrees to face the +y wall.
    const std::array<double, 3> target{0.1 * opts_.room_size_x, 0.25 * opts_.room_size_y,
                                       q[2] - 0.5 * std::numbers::pi};
    const double u = smoothstep((t_s - t_leave) / kRepeatLeaveS);
    for (std::size_t i = 0; i < q.size(); ++i) q[i] += u * (target[i] - q[i]);
  }
  const double sway = kRepeatSway * std::sin(kTwoPi * t_s / 4.0);
  const Eigen::Vector3d eye(q[0] + sway * std::sin(q[2]), q[1] - sway * std::cos(q[2]),
                            kWalkEyeHeight + 0.02 * std::sin(kTwoPi * 1.8 * t_s));
  const double yaw =
      q[2] + 0.06 * std::sin(kTwoPi * t_s / 3.3) + 0.01 * std::sin(kTwoPi * 2.3 * t_s);
  const double pitch = -0.05 + 0.03 * std::sin(kTwoPi * t_s / 4.1);
  ScenarioSample s;
  s.T_w_c = heading_pose(eye, yaw, pitch);
  s.visible = t_s < opts_.kidnap_start_s || t_s >= black_end;
  return s;
}

SE3d SyntheticCamera::repeated_hall_pose(double t_s) const {
  // Counter-clockwise round a stadium kHallRepeatGap from the walls: starts where the -y
  // straight begins, heading +x.
  const double r = 0.5 * opts_.hall_size_y - kHallRepeatGap;
  const double hx = 0.5 * opts_.hall_size_x - kHallRepeatGap;
  double heading = 0.0;
  const Eigen::Vector2d pos =
      rounded_rect_point(opts_.drive_speed_mps * t_s - (hx - r), hx, r, r, heading);
  const double bounce = 0.02 * std::sin(kTwoPi * 1.3 * t_s);
  const double pitch = 0.01 * std::sin(kTwoPi * 0.7 * t_s);
  return heading_pose(Eigen::Vector3d(pos.x(), pos.y(), kDriveEyeHeight + bounce),
                      heading - kHallRepeatLookRad, pitch);
}

void SyntheticCamera::make_panels(const cv::Mat& first) {
  // One framed panel, cut from `first`, and its copies: in rooms centred on the -x, +x, -y,
  // +y walls in turn, in halls and the corridor on the two long walls; copies sharing a wall
  // spread evenly along it. Every copy has the same size and texels.
  panels_.clear();
  wall_panels_.fill(0);
  panel_ = Texture{};
  const int n = opts_.repeat_texture;
  if (n <= 0) return;
  const bool hall = kind_ == Scenario::kHallDrive || kind_ == Scenario::kHallTurn ||
                    kind_ == Scenario::kHallRepeated;
  const bool corridor = kind_ == Scenario::kCorridor;
  std::array<double, 3> ext{};
  for (std::size_t a = 0; a < 3; ++a) ext[a] = room_hi_[a] - room_lo_[a];
  std::array<int, 4> order{0, 1, 2, 3};
  std::size_t num_walls = 4;
  if (hall || corridor) {
    order = ext[0] >= ext[1] ? std::array<int, 4>{2, 3, 0, 1} : std::array<int, 4>{0, 1, 2, 3};
    num_walls = 2;
  }
  std::array<int, 4> count{};
  for (int i = 0; i < n; ++i) ++count[static_cast<std::size_t>(order[i % num_walls])];
  double width = hall ? kHallPanelW : kRoomPanelW;
  for (std::size_t k = 0; k < 4; ++k) {
    if (count[k] > 0) width = std::min(width, kPanelFill * ext[k < 2 ? 1 : 0] / count[k]);
  }
  const double z0 = hall ? kHallPanelZ : kRoomPanelZ;
  const double z1 = std::min(z0 + (hall ? kHallPanelH : kRoomPanelH), ext[2] - 0.1);
  // The texture, at the walls' density.
  const double density = corridor ? kCorridorTexelsPerM : opts_.texture_size / ext[2];
  const int tw = std::max(kMinMipSize, static_cast<int>(std::lround(width * density)));
  const int th = std::max(kMinMipSize, static_cast<int>(std::lround((z1 - z0) * density)));
  std::mt19937 rng(static_cast<std::uint32_t>(opts_.seed) ^ kPanelSalt);
  cv::Mat canvas = photo_crop(first, tw, th, uniform(rng, 0.5, 0.9), rng);
  const int frame = std::max(1, static_cast<int>(std::lround(kPanelFrameM * density)));
  canvas.rowRange(0, std::min(frame, th)).setTo(kPanelFrameGrey);
  canvas.rowRange(std::max(0, th - frame), th).setTo(kPanelFrameGrey);
  canvas.colRange(0, std::min(frame, tw)).setTo(kPanelFrameGrey);
  canvas.colRange(std::max(0, tw - frame), tw).setTo(kPanelFrameGrey);
  cv::flip(canvas, canvas, 0);  // row 0 at the bottom, as on the walls
  panel_.w = tw;
  panel_.h = th;
  panel_.levels =
      make_mips_rect(std::vector<std::uint8_t>(canvas.datastart, canvas.dataend), tw, th);
  panel_texels_per_m_ = static_cast<float>(std::max(tw / width, th / (z1 - z0)));
  for (std::size_t k = 0; k < 4; ++k) {
    wall_panels_[k] = panels_.size();
    const std::size_t pa = k < 2 ? 1 : 0;
    for (int j = 0; j < count[k]; ++j) {
      const double centre = room_lo_[pa] + ext[pa] * (j + 0.5) / count[k];
      // Seen from inside, +u runs to the right on the -x and +y walls, to the left on the
      // others: their copies are mirrored so that every copy reads the same.
      panels_.push_back(WallPanel{static_cast<int>(k), static_cast<float>(centre - 0.5 * width),
                                  static_cast<float>(centre + 0.5 * width), static_cast<float>(z0),
                                  static_cast<float>(z1), k == 1 || k == 2});
    }
  }
  for (std::size_t k = 4; k < wall_panels_.size(); ++k) wall_panels_[k] = panels_.size();
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

void SyntheticCamera::place_boxes_clear_of_path(std::uint32_t seed, bool hall) {
  // Boxes on the floor, clear of every camera position of the sequence (sampled).
  std::mt19937 rng(seed);
  boxes_.clear();
  std::vector<Eigen::Vector2d> path;
  const double duration = std::min(kBoxPathMaxS, opts_.num_frames / opts_.fps);
  for (double t = 0.0; t <= duration + 1e-9; t += kBoxPathSampleS) {
    path.push_back(sample_at(t).T_w_c.translation().head<2>());
  }
  const double clearance = hall ? kDriveBoxClearance : kRoomPathClearance;
  const double side_lo = hall ? kDriveBoxMinSide : kFurnitureMinSide;
  const double side_hi = hall ? kDriveBoxMaxSide : kFurnitureMaxSide;
  const double z_lo = hall ? kDriveBoxMinHeight : kFurnitureMinHeight;
  const double z_hi = hall ? kDriveBoxMaxHeight : kFurnitureMaxHeight;
  const double hx = 0.5 * (room_hi_[0] - room_lo_[0]) - kWallMargin;
  const double hy = 0.5 * (room_hi_[1] - room_lo_[1]) - kWallMargin;
  for (int b = 0; b < opts_.num_boxes; ++b) {
    for (int attempt = 0; attempt < kBoxPlacementTries; ++attempt) {
      const double bx = uniform(rng, side_lo, side_hi);
      const double by = uniform(rng, side_lo, side_hi);
      const double bz = uniform(rng, z_lo, std::min(z_hi, 0.8 * (room_hi_[2] - room_lo_[2])));
      const double cx = uniform(rng, -hx + 0.5 * bx, hx - 0.5 * bx);
      const double cy = uniform(rng, -hy + 0.5 * by, hy - 0.5 * by);
      bool clear = true;
      // Not in front of a panel (repeat_texture): the copies are seen unoccluded.
      for (const WallPanel& pn : panels_) {
        const auto a = static_cast<std::size_t>(pn.wall / 2);
        const std::size_t pa = a == 0 ? 1 : 0;
        const double depth = std::min(kPanelKeepOut, 0.5 * (room_hi_[a] - room_lo_[a]));
        const double n0 = pn.wall % 2 == 0 ? room_lo_[a] : room_hi_[a] - depth;
        const std::array<double, 2> c{cx, cy};
        const std::array<double, 2> half{0.5 * bx, 0.5 * by};
        const bool along = c[pa] + half[pa] > pn.u0 - kPanelKeepOutSide &&
                           c[pa] - half[pa] < pn.u1 + kPanelKeepOutSide;
        const bool out = c[a] + half[a] > n0 && c[a] - half[a] < n0 + depth;
        if (along && out) clear = false;
      }
      for (const Eigen::Vector2d& c : path) {
        if (!clear) break;
        const double gx = std::max(0.0, std::abs(c.x() - cx) - 0.5 * bx);
        const double gy = std::max(0.0, std::abs(c.y() - cy) - 0.5 * by);
        if (gx * gx + gy * gy < clearance * clearance) {
          clear = false;
          break;
        }
      }
      if (!clear) continue;
      boxes_.push_back(
          box_on_floor(cx, cy, bx, by, bz, static_cast<int>(rng() % textures_.size())));
      break;
    }
  }
}

Status SyntheticCamera::list_photos(const SyntheticOptions& opts, std::vector<std::string>& out) {
  namespace fs = std::filesystem;
  out.clear();
  const std::string hint = "install the Debian package " + std::string(kPhotoPackage) +
                           " (apt-get install " + std::string(kPhotoPackage) +
                           "), set camera.synthetic.photo_dir, or use texture: procedural";
  std::error_code ec;
  if (!fs::is_directory(opts.photo_dir, ec)) {
    return input_error("synthetic camera: photo textures: folder '" + opts.photo_dir +
                       "' not found: " + hint);
  }
  std::vector<std::pair<std::string, std::string>> found;  // (file name, path)
  for (fs::recursive_directory_iterator
           it(opts.photo_dir, fs::directory_options::skip_permission_denied, ec),
       end;
       !ec && it != end; it.increment(ec)) {
    if (!it->is_regular_file(ec)) continue;
    std::string ext = it->path().extension().string();
    std::transform(ext.begin(), ext.end(), ext.begin(),
                   [](unsigned char c) { return static_cast<char>(std::tolower(c)); });
    if (ext != ".jpg" && ext != ".jpeg") continue;
    if (is_resolution_variant(it->path().stem().string())) continue;
    found.emplace_back(it->path().filename().string(), it->path().string());
  }
  std::sort(found.begin(), found.end());
  for (std::size_t i = 0; i < found.size(); ++i) {
    const bool even = i % 2 == 0;
    if (opts.photo_set == "all" || (opts.photo_set == "dev") == even) {
      out.push_back(found[i].second);
    }
  }
  if (out.empty()) {
    return input_error("synthetic camera: photo textures: no *.jpg photos in folder '" +
                       opts.photo_dir + "'" +
                       (found.empty() ? "" : " for photo_set " + opts.photo_set) + ": " + hint);
  }
  return Status::ok();
}

Status SyntheticCamera::load_wall_photos(std::mt19937& rng, std::vector<cv::Mat>& photos) {
  std::vector<std::string> all;
  if (Status s = list_photos(opts_, all); !s.is_ok()) return s;
  // A seeded shuffle, then one photo per wall (distinct while the set has six or more).
  std::vector<std::size_t> order(all.size());
  for (std::size_t i = 0; i < order.size(); ++i) order[i] = i;
  for (std::size_t i = order.size(); i > 1; --i) std::swap(order[i - 1], order[rng() % i]);
  photos.clear();
  photo_files_.clear();
  for (std::size_t k = 0; k < textures_.size(); ++k) {
    const std::string& path = all[order[k % order.size()]];
    cv::Mat img = cv::imread(path, cv::IMREAD_GRAYSCALE);
    if (img.empty() || img.cols < 16 || img.rows < 16) {
      return input_error("synthetic camera: photo textures: cannot read '" + path + "'");
    }
    photos.push_back(img);
    photo_files_.push_back(path);
  }
  return Status::ok();
}

void SyntheticCamera::make_photo_textures(const std::vector<cv::Mat>& photos, std::mt19937& rng) {
  // Each wall: its photo at a density of texture_size texels per room height (so photos keep
  // their aspect), upright on the vertical walls (texture rows run up). Rooms: one random
  // crop of the wall's aspect; the hall: a grid of crops half the hall's height, like
  // facades and signs.
  const bool hall = kind_ == Scenario::kHallDrive || kind_ == Scenario::kHallTurn ||
                    kind_ == Scenario::kHallRepeated;
  const double density = opts_.texture_size / static_cast<double>(room_hi_[2] - room_lo_[2]);
  for (std::size_t k = 0; k < textures_.size(); ++k) {
    const std::size_t a = k / 2;
    const std::size_t pa = a == 0 ? 1 : 0;
    const std::size_t qa = a == 2 ? 1 : 2;
    const int w = std::clamp(static_cast<int>(std::lround((room_hi_[pa] - room_lo_[pa]) * density)),
                             kMinMipSize, 8192);
    const int h = std::clamp(static_cast<int>(std::lround((room_hi_[qa] - room_lo_[qa]) * density)),
                             kMinMipSize, 8192);
    cv::Mat canvas;
    if (!hall) {
      canvas = photo_crop(photos[k], w, h, uniform(rng, 0.55, 1.0), rng);
    } else {
      canvas = cv::Mat(h, w, CV_8UC1, cv::Scalar(128));
      const int tile = std::max(kMinMipSize, opts_.texture_size / 2);
      for (int y0 = 0; y0 < h; y0 += tile) {
        for (int x0 = 0; x0 < w; x0 += tile) {
          const int tw = std::min(tile, w - x0);
          const int th = std::min(tile, h - y0);
          photo_crop(photos[k], tw, th, uniform(rng, 0.3, 0.7), rng)
              .copyTo(canvas(cv::Rect(x0, y0, tw, th)));
        }
      }
    }
    if (a < 2) cv::flip(canvas, canvas, 0);  // vertical walls: row 0 is the floor
    Texture& tex = textures_[k];
    tex.w = w;
    tex.h = h;
    tex.levels = make_mips_rect(std::vector<std::uint8_t>(canvas.datastart, canvas.dataend), w, h);
  }
}

void SyntheticCamera::make_corridor_textures(const std::vector<cv::Mat>& sources,
                                             std::mt19937& rng) {
  // Painted walls: the source image flattened toward white (corridor_contrast), tiled in
  // squares of the wall's smaller side; then the few features of a real corridor: skirting,
  // doors with frames and handles, posters (side walls), floor tiles and ceiling lights.
  const double density = kCorridorTexelsPerM;
  const double contrast = opts_.corridor_contrast;
  for (std::size_t k = 0; k < textures_.size(); ++k) {
    const std::size_t a = k / 2;
    const std::size_t pa = a == 0 ? 1 : 0;
    const std::size_t qa = a == 2 ? 1 : 2;
    const double ext_u = room_hi_[pa] - room_lo_[pa];
    const double ext_v = room_hi_[qa] - room_lo_[qa];
    const int w = std::max(kMinMipSize, static_cast<int>(std::lround(ext_u * density)));
    const int h = std::max(kMinMipSize, static_cast<int>(std::lround(ext_v * density)));
    const bool floor = k == 4;
    const bool ceiling = k == 5;
    const double base = floor ? 140.0 : ceiling ? 212.0 : kCorridorWhite;
    const double gain = floor ? std::min(1.0, 2.5 * contrast) : contrast;
    cv::Mat canvas(h, w, CV_32FC1);
    const int tile = std::min(w, h);
    for (int x0 = 0; x0 < w; x0 += tile) {
      const int tw = std::min(tile, w - x0);
      for (int y0 = 0; y0 < h; y0 += tile) {
        const int th = std::min(tile, h - y0);
        cv::Mat crop;
        photo_crop(sources[k], tw, th, uniform(rng, 0.4, 0.9), rng).convertTo(crop, CV_32F);
        const double mean = cv::mean(crop)[0];
        crop.convertTo(crop, CV_32F, gain, base - gain * mean);
        crop.copyTo(canvas(cv::Rect(x0, y0, tw, th)));
      }
    }
    auto fill = [&](double u0, double v0, double u1, double v1, double value) {
      const int c0 = std::clamp(static_cast<int>(u0 * density), 0, w);
      const int c1 = std::clamp(static_cast<int>(u1 * density), 0, w);
      const int r0 = std::clamp(static_cast<int>(v0 * density), 0, h);
      const int r1 = std::clamp(static_cast<int>(v1 * density), 0, h);
      if (c1 > c0 && r1 > r0) canvas(cv::Rect(c0, r0, c1 - c0, r1 - r0)).setTo(value);
    };
    if (a < 2) {
      // Skirting board and its shadow line (rows run up from the floor).
      fill(0.0, 0.0, ext_u, 0.10, 150.0 + uniform(rng, -10, 10));
      fill(0.0, 0.10, ext_u, 0.115, kCorridorWhite - 30.0);
      // Doors: frame, leaf (a low-contrast patch of the source), handle.
      std::vector<std::pair<double, double>> taken;
      double u = a == 0 ? 0.5 * ext_u - 0.45 : uniform(rng, 1.0, 3.0);
      while (u + 1.0 < ext_u) {
        const double top = std::min(2.05, ext_v - 0.2);
        fill(u - 0.06, 0.0, u + 0.96, top + 0.06, kCorridorWhite - uniform(rng, 25, 45));
        cv::Mat leaf;
        const int lw = std::max(2, static_cast<int>(0.9 * density));
        const int lh = std::max(2, static_cast<int>(top * density));
        photo_crop(sources[(k + 3) % sources.size()], lw, lh, uniform(rng, 0.3, 0.8), rng)
            .convertTo(leaf, CV_32F);
        const double leaf_grey = uniform(rng, 170, 205);
        const double mean = cv::mean(leaf)[0];
        leaf.convertTo(leaf, CV_32F, 0.25, leaf_grey - 0.25 * mean);
        const int c0 = static_cast<int>(u * density);
        if (c0 + lw <= w && lh <= h) leaf.copyTo(canvas(cv::Rect(c0, 0, lw, lh)));
        fill(u + 0.76, 0.98, u + 0.84, 1.02, 90.0);  // handle
        taken.emplace_back(u - 0.2, u + 1.1);
        if (a == 0) break;  // one door in each end wall
        u += uniform(rng, 3.5, 6.5);
      }
      // Posters between the doors (side walls only): a photo crop at moderate contrast.
      if (a == 1) {
        for (double pu = uniform(rng, 0.5, 2.0); pu + 0.7 < ext_u; pu += uniform(rng, 3.0, 7.0)) {
          bool free = true;
          for (const auto& [t0, t1] : taken) free = free && (pu + 0.7 < t0 || pu > t1);
          if (!free) continue;
          const int pw = static_cast<int>(0.6 * density);
          const int ph = static_cast<int>(0.85 * density);
          const int c0 = static_cast<int>(pu * density);
          const int r0 = static_cast<int>(1.15 * density);
          if (c0 + pw > w || r0 + ph > h) continue;
          cv::Mat poster;
          photo_crop(sources[(k + 1) % sources.size()], pw, ph, uniform(rng, 0.3, 0.7), rng)
              .convertTo(poster, CV_32F);
          const double mean = cv::mean(poster)[0];
          poster.convertTo(poster, CV_32F, 0.5, 150.0 - 0.5 * mean);
          poster.copyTo(canvas(cv::Rect(c0, r0, pw, ph)));
        }
      }
    } else if (floor) {
      // Floor tiles: faint seams every 0.6 m.
      for (double u = 0.0; u < ext_u; u += 0.6) fill(u, 0.0, u + 0.01, ext_v, base - 12.0);
      for (double v = 0.0; v < ext_v; v += 0.6) fill(0.0, v, ext_u, v + 0.01, base - 12.0);
    } else {
      // Ceiling lights: bright panels every 2.4 m down the middle.
      for (double u = 1.2; u + 0.6 < ext_u; u += 2.4) {
        fill(u, 0.5 * ext_v - 0.3, u + 1.2, 0.5 * ext_v + 0.3, 250.0);
      }
    }
    cv::Mat grey;
    canvas.convertTo(grey, CV_8U);  // saturating
    Texture& tex = textures_[k];
    tex.w = w;
    tex.h = h;
    std::vector<std::uint8_t> data(static_cast<std::size_t>(w) * static_cast<std::size_t>(h));
    for (int r = 0; r < h; ++r) {
      std::copy(grey.ptr<std::uint8_t>(r), grey.ptr<std::uint8_t>(r) + w,
                data.begin() + static_cast<std::ptrdiff_t>(r) * w);
    }
    tex.levels = make_mips_rect(std::move(data), w, h);
  }
}

void SyntheticCamera::render(const SE3d& T_w_c, cv::Mat& gray, cv::Mat* depth,
                             std::uint64_t noise_offset, float gain) const {
  render_impl(T_w_c, gray, depth, noise_offset, gain, true);
}

void SyntheticCamera::render_impl(const SE3d& T_w_c, cv::Mat& gray, cv::Mat* depth,
                                  std::uint64_t noise_offset, float gain, bool add_noise) const {
  const Eigen::Matrix3f R = T_w_c.linear().cast<float>();
  const Eigen::Vector3f o = T_w_c.translation().cast<float>();
  const std::array<float, 3>& lo = room_lo_;
  const std::array<float, 3>& hi = room_hi_;
  const float inv_f = 1.0F / static_cast<float>(intrinsics_.fx);
  const std::size_t noise_mask = kNoiseTableSize - 1;
  std::size_t noise_i = static_cast<std::size_t>(noise_offset * 7919U) & noise_mask;
  const bool noisy = add_noise && opts_.noise_sigma > 0.0;
  constexpr float kTiny = 1e-9F;
  constexpr float kHuge = 1e30F;

  // Mip level for ray `d` meeting, at depth t, a surface with `texels_per_m` level-0 texels
  // per metre whose normal is world axis `normal_axis` (0 without mips).
  auto level_for = [&](const Eigen::Vector3f& d, float t, float texels_per_m, int normal_axis,
                       int num_levels) {
    if (!use_mips_) return 0;
    const float cos_n = std::abs(d[normal_axis]) / d.norm();
    const float footprint = t * inv_f * texels_per_m / std::max(cos_n, kMinObliqueCos);
    if (footprint <= 1.0F) return 0;
    return std::min(static_cast<int>(std::log2(footprint)), num_levels - 1);
  };
  // Bilinear lookup at level-0 texel coordinates (fu, fv) in [0, w - 1) x [0, h - 1) of `level`.
  auto sample = [](const Texture& texture, int level, float fu, float fv) {
    const int wl = texture.w >> level;
    const int hl = texture.h >> level;
    const float scale = 1.0F / static_cast<float>(1 << level);
    const float lmax_u = static_cast<float>(wl - 1) - 1e-3F;
    const float lmax_v = static_cast<float>(hl - 1) - 1e-3F;
    fu = std::min(std::max(fu * scale - 0.5F * (1.0F - scale), 0.0F), lmax_u);
    fv = std::min(std::max(fv * scale - 0.5F * (1.0F - scale), 0.0F), lmax_v);
    const int iu = static_cast<int>(fu);
    const int iv = static_cast<int>(fv);
    const float au = fu - static_cast<float>(iu);
    const float av = fv - static_cast<float>(iv);
    const std::uint8_t* t = texture.levels[static_cast<std::size_t>(level)].data() +
                            static_cast<std::size_t>(iv) * static_cast<std::size_t>(wl) +
                            static_cast<std::size_t>(iu);
    const float top = t[0] + au * (static_cast<float>(t[1]) - t[0]);
    const float bot = t[wl] + au * (static_cast<float>(t[wl + 1]) - t[wl]);
    return top + av * (bot - top);
  };
  // Repeating texture coordinate for box faces, along a texture side of `size` texels.
  const float box_texture_metres = box_texture_metres_;
  // `texels_per_m` is the same along both sides (the smaller side spans box_texture_metres).
  auto wrap = [](float metres, float texels_per_m, int size) {
    const float tmax = static_cast<float>(size - 1) - 1e-3F;
    const float f = metres * texels_per_m;
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
        const Texture& tex = hit_box->texture == kPanelTexture
                                 ? panel_
                                 : textures_[static_cast<std::size_t>(hit_box->texture)];
        const float box_texels_per_m =
            static_cast<float>(std::min(tex.w, tex.h) - 1) / box_texture_metres;
        value = sample(
            tex, level_for(d, t, box_texels_per_m, box_axis, static_cast<int>(tex.levels.size())),
            wrap(p[pa] - hit_box->lo[pa], box_texels_per_m, tex.w),
            wrap(p[qa] - hit_box->lo[qa], box_texels_per_m, tex.h));
      } else {
        const int pa = axis == 0 ? 1 : 0;
        const int qa = axis == 2 ? 1 : 2;
        const auto wall = static_cast<std::size_t>(axis * 2 + side);
        const WallPanel* panel = nullptr;
        for (std::size_t k = wall_panels_[wall]; k < wall_panels_[wall + 1]; ++k) {
          const WallPanel& pn = panels_[k];
          if (p[pa] >= pn.u0 && p[pa] < pn.u1 && p[qa] >= pn.v0 && p[qa] < pn.v1) {
            panel = &pn;
            break;
          }
        }
        if (panel == nullptr) {
          const Texture& tex = textures_[wall];
          const float tmax_u = static_cast<float>(tex.w - 1) - 1e-3F;
          const float tmax_v = static_cast<float>(tex.h - 1) - 1e-3F;
          const float fu = std::clamp((p[pa] - lo[pa]) / (hi[pa] - lo[pa]), 0.0F, 1.0F) * tmax_u;
          const float fv = std::clamp((p[qa] - lo[qa]) / (hi[qa] - lo[qa]), 0.0F, 1.0F) * tmax_v;
          value = sample(
              tex,
              level_for(d, t, wall_texels_per_m_[wall], axis, static_cast<int>(tex.levels.size())),
              fu, fv);
        } else {
          const float tmax_u = static_cast<float>(panel_.w - 1) - 1e-3F;
          const float tmax_v = static_cast<float>(panel_.h - 1) - 1e-3F;
          float across = (p[pa] - panel->u0) / (panel->u1 - panel->u0);
          if (panel->mirror) across = 1.0F - across;
          const float fu = std::clamp(across, 0.0F, 1.0F) * tmax_u;
          const float fv =
              std::clamp((p[qa] - panel->v0) / (panel->v1 - panel->v0), 0.0F, 1.0F) * tmax_v;
          value = sample(
              panel_,
              level_for(d, t, panel_texels_per_m_, axis, static_cast<int>(panel_.levels.size())),
              fu, fv);
        }
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

double SyntheticCamera::gain_at(double t_s) const {
  double gain = 1.0 + opts_.exposure_amplitude * std::sin(kTwoPi * t_s / opts_.exposure_period_s);
  if (opts_.exposure_step_every_s > 0.0 && t_s > 0.0) {
    // Auto-exposure jumps: at each step the level moves one notch up or down (the sign from
    // the seed and the step index), kept within +-2 notches.
    const auto steps = static_cast<std::int64_t>(std::floor(t_s / opts_.exposure_step_every_s));
    int level = 0;
    for (std::int64_t i = 1; i <= steps; ++i) {
      const std::uint64_t key =
          (static_cast<std::uint64_t>(opts_.seed) << 32U) ^ static_cast<std::uint64_t>(i);
      int d = (mix64(key) & 1U) != 0U ? 1 : -1;
      if (std::abs(level + d) > 2) d = -d;
      level += d;
    }
    gain *= std::pow(1.0 + opts_.exposure_step_size, level);
  }
  return gain;
}

void SyntheticCamera::render_blurred(double t_s, Frame& f, float gain) {
  // The exposure [t - e/2, t + e/2] sampled at blur_samples evenly spaced instants, each
  // rendered without noise; the mean gets the noise a single render would. The middle
  // sample of an odd count is exactly t: it also renders the depth.
  const int k_samples = opts_.blur_samples;
  const double e = opts_.exposure_time_s;
  std::fill(blur_sum_.begin(), blur_sum_.end(), std::uint16_t{0});
  const bool depth = opts_.render_depth;
  const bool odd = (k_samples % 2) == 1;
  for (int k = 0; k < k_samples; ++k) {
    const double t_k = t_s + e * ((k + 0.5) / k_samples - 0.5);
    const ScenarioSample s = sample_at(t_k);
    if (!s.visible) continue;  // lens covered for part of the exposure: adds black
    const bool middle = odd && k == k_samples / 2;
    render_impl(middle ? f.T_w_c_gt : s.T_w_c, blur_scratch_,
                (depth && middle) ? &f.depth : nullptr, 0, gain, false);
    std::uint16_t* sum = blur_sum_.data();
    for (int v = 0; v < blur_scratch_.rows; ++v) {
      const std::uint8_t* row = blur_scratch_.ptr<std::uint8_t>(v);
      for (int u = 0; u < blur_scratch_.cols; ++u) *sum++ += row[u];
    }
  }
  if (depth && !odd) render_impl(f.T_w_c_gt, blur_scratch_, &f.depth, 0, gain, false);
  const std::size_t noise_mask = kNoiseTableSize - 1;
  std::size_t noise_i = static_cast<std::size_t>(f.seq * 7919U) & noise_mask;
  const bool noisy = opts_.noise_sigma > 0.0;
  const auto n = static_cast<float>(k_samples);
  const std::uint16_t* sum = blur_sum_.data();
  for (int v = 0; v < f.gray.rows; ++v) {
    std::uint8_t* row = f.gray.ptr<std::uint8_t>(v);
    for (int u = 0; u < f.gray.cols; ++u) {
      float value = static_cast<float>(*sum++) / n;
      if (noisy) {
        value += static_cast<float>(noise_[noise_i]);
        noise_i = (noise_i + 1) & noise_mask;
      }
      row[u] = static_cast<std::uint8_t>(std::clamp(value + 0.5F, 0.0F, 255.0F));
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
    const double gain = gain_at(t_s);
    if (opts_.exposure_time_s > 0.0) {
      render_blurred(t_s, f, static_cast<float>(gain));
    } else {
      render(f.T_w_c_gt, f.gray, opts_.render_depth ? &f.depth : nullptr, next_seq_,
             static_cast<float>(gain));
    }
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
