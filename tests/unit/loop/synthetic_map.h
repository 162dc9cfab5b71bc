#pragma once
/// @file synthetic_map.h
/// Synthetic maps with known ground truth for the loop tests (loop closure, retrieval,
/// relocalization): keyframes whose keypoints are exact projections of known points.

#include <cmath>
#include <cstdint>
#include <random>
#include <vector>

#include <gtest/gtest.h>

#include "core/pose.h"
#include "features/keypoint.h"
#include "geometry/camera_model.h"
#include "map/map.h"

namespace mer::loop::scene {

/// Adds a keyframe whose keypoints are pts seen from T_true (level 0; point i gives keypoint
/// i), stored in the map with pose T_stored and descriptors desc; capture time t ms; in map
/// segment `segment`.
inline map::KeyframeId add_view(map::Map& map, const geometry::Pinhole& K, const SE3d& T_true,
                                const SE3d& T_stored, const std::vector<Eigen::Vector3d>& pts,
                                const std::vector<features::Descriptor>& desc, std::uint64_t seq,
                                std::uint64_t t, std::uint16_t segment = 0) {
  std::vector<features::Keypoint> kps;
  for (const Eigen::Vector3d& p : pts) {
    const Eigen::Vector2d uv = K.project(T_true.inverse() * p);
    features::Keypoint k;
    k.x = static_cast<float>(uv.x());
    k.y = static_cast<float>(uv.y());
    k.level = 0;
    k.scale = 1.0F;
    kps.push_back(k);
  }
  map::KeyframeInput in;
  in.seq = seq;
  in.t_ns = static_cast<std::int64_t>(t) * 1000000;
  in.T_w_c = T_stored;
  in.segment = segment;
  in.keypoints = kps;
  in.descriptors = desc;
  const Result<map::KeyframeId> r = map.add_keyframe(in);
  EXPECT_TRUE(r.is_ok()) << r.status().message();
  return r.is_ok() ? r.value() : map::kNoId;
}

/// One image of an OrbitWorld: keypoints, descriptors and, per keypoint, the world point it
/// sees (-1: clutter, a keypoint of nothing in the world).
struct View {
  std::vector<features::Keypoint> keypoints;
  std::vector<features::Descriptor> descriptors;
  std::vector<int> point;
};

/// A room seen from its middle: kPoints textured points on a cylinder (radius 5 m, height
/// 3 m) around a camera that turns on the spot and looks outwards. Every point has its own
/// descriptor; each view of it flips `bit_flips` random bits (another view's noise).
struct OrbitWorld {
  static constexpr int kPoints = 3000;
  static constexpr int kWidth = 640;
  static constexpr int kHeight = 480;
  geometry::Pinhole K{400.0, 400.0, 320.0, 240.0};
  std::vector<Eigen::Vector3d> points;
  std::vector<features::Descriptor> descriptors;

  explicit OrbitWorld(std::uint64_t seed = 3) {
    std::mt19937_64 rng(seed);
    std::uniform_real_distribution<double> angle(0.0, 2.0 * M_PI);
    std::uniform_real_distribution<double> height(-1.5, 1.5);
    std::uniform_real_distribution<double> radius(4.5, 5.5);
    for (int i = 0; i < kPoints; ++i) {
      const double a = angle(rng);
      const double r = radius(rng);
      points.emplace_back(r * std::cos(a), height(rng), r * std::sin(a));
      descriptors.push_back({rng(), rng(), rng(), rng()});
    }
  }

  /// Camera-to-world pose looking outwards at heading `deg` (degrees about the vertical),
  /// its centre `offset` m from the middle (sideways, along the camera x axis).
  static SE3d pose(double deg, double offset = 0.0) {
    const double a = deg * M_PI / 180.0;
    const Eigen::Vector3d dir(std::cos(a), 0.0, std::sin(a));
    const Eigen::Vector3d side(-std::sin(a), 0.0, std::cos(a));
    const Eigen::Vector3d eye = offset * side;
    return look_at(eye, eye + dir, Eigen::Vector3d(0.0, -1.0, 0.0));
  }

  /// The image from T_w_c: the points in front that project inside it (keypoint noise
  /// `px_noise` px), then `clutter` keypoints with random descriptors.
  View observe(const SE3d& T_w_c, std::mt19937_64& rng, int bit_flips = 10, double px_noise = 0.3,
               int clutter = 100) const {
    View v;
    std::normal_distribution<double> noise(0.0, px_noise > 0.0 ? px_noise : 1.0);
    std::uniform_int_distribution<int> bit(0, 255);
    const SE3d T_c_w = T_w_c.inverse();
    for (int i = 0; i < kPoints; ++i) {
      const Eigen::Vector3d p_c = T_c_w * points[static_cast<std::size_t>(i)];
      if (p_c.z() < 0.5) continue;
      Eigen::Vector2d uv = K.project(p_c);
      if (px_noise > 0.0) uv += Eigen::Vector2d(noise(rng), noise(rng));
      if (uv.x() < 0.0 || uv.y() < 0.0 || uv.x() >= kWidth || uv.y() >= kHeight) continue;
      features::Descriptor d = descriptors[static_cast<std::size_t>(i)];
      for (int b = 0; b < bit_flips; ++b) {
        const int k = bit(rng);
        d[static_cast<std::size_t>(k / 64)] ^= 1ULL << static_cast<unsigned>(k % 64);
      }
      add(v, uv, d, i);
    }
    std::uniform_real_distribution<double> ux(0.0, kWidth - 1.0);
    std::uniform_real_distribution<double> uy(0.0, kHeight - 1.0);
    for (int c = 0; c < clutter; ++c) add(v, {ux(rng), uy(rng)}, {rng(), rng(), rng(), rng()}, -1);
    return v;
  }

  static map::MapOptions map_options() {
    map::MapOptions o;
    o.max_keyframes = 64;
    o.max_points = kPoints;
    o.max_keypoints_per_keyframe = 1024;
    o.max_observations_per_point = 16;
    o.max_covisible_per_keyframe = 16;
    o.cell_table_size = 4096;
    o.points_per_cell = 64;
    return o;
  }

  /// Maps the views at headings first_deg, first_deg + step_deg, ... (count keyframes, exact
  /// poses and point positions): keyframes, points (created by the first keyframe that sees
  /// them, observed by the others), point descriptors and covisibility. Returns the ids.
  std::vector<map::KeyframeId> build(map::Map& map, double first_deg, double step_deg, int count,
                                     std::mt19937_64& rng) const {
    std::vector<map::KeyframeId> ids;
    std::vector<map::PointId> point_of(static_cast<std::size_t>(kPoints), map::kNoId);
    for (int k = 0; k < count; ++k) {
      const SE3d T_w_c = pose(first_deg + step_deg * k);
      const View v = observe(T_w_c, rng);
      map::KeyframeInput in;
      in.seq = static_cast<std::uint64_t>(k) * 10;
      in.t_ns = static_cast<std::int64_t>(k) * 333000000;
      in.T_w_c = T_w_c;
      in.keypoints = v.keypoints;
      in.descriptors = v.descriptors;
      const Result<map::KeyframeId> r = map.add_keyframe(in);
      EXPECT_TRUE(r.is_ok()) << r.status().message();
      if (!r.is_ok()) return ids;
      const map::KeyframeId kf = r.value();
      ids.push_back(kf);
      for (std::size_t j = 0; j < v.point.size(); ++j) {
        if (v.point[j] < 0) continue;
        map::PointId& p = point_of[static_cast<std::size_t>(v.point[j])];
        const auto kp = static_cast<std::uint32_t>(j);
        if (p == map::kNoId) {
          const Result<map::PointId> pr =
              map.add_point(points[static_cast<std::size_t>(v.point[j])], kf, kp);
          if (pr.is_ok()) p = pr.value();
        } else {
          (void)map.add_observation(p, kf, kp);
        }
      }
    }
    for (const map::PointId p : point_of) {
      if (p != map::kNoId) map.update_point(p);
    }
    for (const map::KeyframeId kf : ids) map.update_covisibility(kf);
    return ids;
  }

 private:
  static void add(View& v, const Eigen::Vector2d& uv, const features::Descriptor& d, int point) {
    features::Keypoint k;
    k.x = static_cast<float>(uv.x());
    k.y = static_cast<float>(uv.y());
    k.level = 0;
    k.scale = 1.0F;
    v.keypoints.push_back(k);
    v.descriptors.push_back(d);
    v.point.push_back(point);
  }
};

}  // namespace mer::loop::scene
