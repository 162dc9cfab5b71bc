// The synthetic camera's scripted motions (SyntheticCamera, synthetic_camera.h): the pose
// (and for some scenarios the scene state) of each scenario at a time.
#include <algorithm>
#include <cmath>
#include <numbers>

#include "hal/synthetic/synthetic_camera.h"
#include "hal/synthetic/synthetic_internal.h"

namespace mer::hal {
namespace {

using synthetic_detail::kLoopSemiAxisX;
using synthetic_detail::kLoopSemiAxisY;
using synthetic_detail::kTwoPi;

constexpr double kEyeHeight = 1.3;            // camera height above the floor, m
constexpr double kOrbitPeriodS = 20.0;        // room_orbit: one revolution, s
constexpr double kOrbitRadius = 0.8;          // room_orbit: radius of the camera circle, m
constexpr double kLoopPeriodS = 20.0;         // room_loop: one lap, s
constexpr double kLoopOutwardRad = 0.6;       // room_loop: view turned outwards from the path
constexpr double kBurstPeriodS = 8.0;         // room_fast_rotation: one turn every 8 s
constexpr double kBurstStartS = 3.0;          // room_fast_rotation: turn starts 3 s into a period
constexpr double kDriveEyeHeight = 1.65;      // hall_drive: camera height (KITTI's), m
constexpr double kDrivePathFraction = 0.6;    // hall_drive: path extent, fraction of the hall
constexpr double kDriveCornerFraction = 0.8;  // hall_drive: corner radius / smaller half extent
// Reproduction scenarios (hall_turn ... room_kidnap_unknown).
constexpr double kPathStepS = 1e-3;      // hall_turn: path table step, s
constexpr double kTurnPathMargin = 5.0;  // hall_turn: the path keeps this far from walls, m
constexpr double kSecondTurnRad = 0.5 * std::numbers::pi;  // hall_turn: second left turn
constexpr double kExploreHalfX = 0.85;  // room_explore: rounded rectangle half extents, m
constexpr double kExploreHalfY = 0.55;
constexpr double kExploreRadius = 0.4;       // room_explore: its corner radius, m
constexpr double kExploreOutwardRad = 0.7;   // room_explore: view turned 40 deg outwards
constexpr double kWalkEyeHeight = 1.45;      // walking scenarios: camera height, m
constexpr double kCorridorEndGap = 1.5;      // corridor: turn round this far from the ends, m
constexpr double kCorridorTurnS = 3.0;       // corridor: duration of the turn round, s
constexpr double kKidnapLookS = 1.5;         // room_kidnap_unknown: looks round this long, s
constexpr double kRepeatSettleS = 2.0;       // room_repeated: facing A before the lap, s
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

}  // namespace

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

}  // namespace mer::hal
