// One writer (mapping thread) grows and edits the map while a reader (tracking thread)
// reads it continuously. Every value the writer stores carries a checksum, so a torn read
// (half of one write, half of another) is detected; the reader also checks the publication
// invariants (ids below the published counts, immutable keyframe data complete) and that
// queries return distinct ids while points move between cells. Run under TSan too.
#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <random>
#include <thread>
#include <vector>

#include <gtest/gtest.h>

#include "map/map.h"
#include "stress_config.h"

namespace mer::map {
namespace {

constexpr int kKeypoints = 200;      // per keyframe
constexpr int kNewPointsPerKf = 60;  // points created from each keyframe
constexpr int kMovesPerKf = 300;     // point moves per keyframe
constexpr std::uint32_t kHot = 32;   // points / keyframes edited (and read) most often
constexpr int kHotEdits = 400;       // hot point moves + hot pose updates per iteration
constexpr auto kWriterTime = std::chrono::milliseconds(2500);
const Eigen::Vector3d kRoom(4.0, 1.5, 4.0);  // half extents
const Eigen::Vector3d kAxis = Eigen::Vector3d(1, 2, 3).normalized();

std::uint64_t mix(std::uint64_t k) {
  k ^= k >> 31U;
  k *= 0x9E3779B97F4A7C15ULL;
  k ^= k >> 29U;
  return k;
}

/// z is a function of (x, y): a position read torn across two writes fails the check.
double z_of(double x, double y) {
  return std::fmod(std::abs(7.3 * x + 13.1 * y), 2.0 * kRoom.z()) - kRoom.z();
}

Eigen::Vector3d encoded_position(std::mt19937& rng) {
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  const double x = u(rng) * kRoom.x();
  const double y = u(rng) * kRoom.y();
  return {x, y, z_of(x, y)};
}

bool position_ok(const Eigen::Vector3d& p) {
  return p.z() == z_of(p.x(), p.y());
}

/// Descriptor whose last word is a hash of the other three.
features::Descriptor encoded_descriptor(std::mt19937_64& rng) {
  features::Descriptor d{rng(), rng(), rng(), 0};
  d[3] = mix(d[0] ^ mix(d[1] ^ mix(d[2])));
  return d;
}

bool descriptor_ok(const features::Descriptor& d) {
  return d[3] == mix(d[0] ^ mix(d[1] ^ mix(d[2])));
}

/// Pose and scale that are functions of one angle.
SE3d encoded_pose(double theta) {
  SE3d T = SE3d::Identity();
  T.linear() = Eigen::AngleAxisd(theta, kAxis).toRotationMatrix();
  T.translation() = Eigen::Vector3d(theta, 2.0 * theta, -theta);
  return T;
}
double encoded_scale(double theta) {
  return 1.0 + theta * theta;
}

/// add_keyframe publishes scale 1; set_keyframe_pose then sets the encoded scale.
bool pose_ok(const SE3d& T, double scale) {
  const double theta = T.translation().x();
  const SE3d E = encoded_pose(theta);
  return T.translation() == E.translation() && T.linear() == E.linear() &&
         (scale == encoded_scale(theta) || scale == 1.0);
}

struct ReaderStats {
  std::uint64_t iterations = 0;
  std::uint64_t pose_reads = 0;
  std::uint64_t point_reads = 0;
  std::uint64_t read_give_ups = 0;  // seqlock retries exhausted (allowed, counted)
  std::uint64_t queries = 0;
  std::uint64_t torn = 0;           // must stay 0
  std::uint64_t bad_ids = 0;        // must stay 0
  std::uint64_t duplicates = 0;     // must stay 0
  std::uint64_t bad_immutable = 0;  // must stay 0
  std::uint64_t bad_covis = 0;      // must stay 0
};

TEST(MapConcurrency, WriterAndReaderNeverSeeTornOrUnpublishedData) {
  MapOptions o;
  o.max_keyframes = 400;
  o.max_points = 40000;
  o.max_keypoints_per_keyframe = kKeypoints;
  o.max_observations_per_point = 8;
  o.max_covisible_per_keyframe = 16;
  o.cell_size = 0.5;
  o.cell_table_size = 4096;
  o.points_per_cell = 128;
  ASSERT_TRUE(validate(o).is_ok());
  Map map(o);
  std::atomic<bool> writer_done{false};

  // Keyframe inputs are prepared up front (the writer thread must not allocate in its loop
  // in production; here it simply keeps the test fast).
  std::mt19937_64 drng(11);
  std::vector<std::vector<features::Keypoint>> kps(static_cast<std::size_t>(o.max_keyframes));
  std::vector<std::vector<features::Descriptor>> descs(kps.size());
  for (std::size_t k = 0; k < kps.size(); ++k) {
    for (int i = 0; i < kKeypoints; ++i) {
      features::Keypoint kp;
      kp.x = static_cast<float>(k);
      kp.y = static_cast<float>(i);
      kp.response = static_cast<float>(k * 1000 + static_cast<std::size_t>(i));
      kp.scale = 1.2F;
      kps[k].push_back(kp);
      descs[k].push_back(encoded_descriptor(drng));
    }
  }

  std::uint64_t writer_ops = 0;
  std::uint64_t iterations = 0;
  std::thread writer([&] {
    std::mt19937 rng(1);
    std::uniform_real_distribution<double> angle(-3.0, 3.0);
    const auto t_end = std::chrono::steady_clock::now() + kWriterTime;
    // Grow the map while there is room, then keep editing it until the time is up.
    std::size_t k = 0;
    while (std::chrono::steady_clock::now() < t_end) {
      const std::uint32_t np0 = map.num_points();
      if (k < kps.size()) {
        KeyframeInput in;
        in.seq = k;
        in.t_ns = static_cast<std::int64_t>(k) * 33'000'000;
        const double theta = angle(rng);
        in.T_w_c = encoded_pose(theta);
        in.keypoints = kps[k];
        in.descriptors = descs[k];
        Result<KeyframeId> kf = map.add_keyframe(in);
        if (!kf.is_ok()) {
          ADD_FAILURE() << kf.status().message();
          break;
        }
        map.set_keyframe_pose(kf.value(), encoded_pose(theta), encoded_scale(theta));
        for (int i = 0; i < kNewPointsPerKf; ++i) {
          Result<PointId> p =
              map.add_point(encoded_position(rng), kf.value(), static_cast<std::uint32_t>(i));
          if (!p.is_ok()) break;  // map full
          ++writer_ops;
        }
        // The remaining keypoints observe random older points.
        for (int i = kNewPointsPerKf; i < kKeypoints && np0 > 0; ++i) {
          const auto p = static_cast<PointId>(rng() % np0);
          if (map.add_observation(p, kf.value(), static_cast<std::uint32_t>(i))) {
            map.update_point(p);
            ++writer_ops;
          }
        }
        map.update_covisibility(kf.value());
        ++k;
      }
      const std::uint32_t np = map.num_points();
      for (int i = 0; i < kMovesPerKf && np > 0; ++i) {
        map.set_point_position(static_cast<PointId>(rng() % np), encoded_position(rng));
        ++writer_ops;
      }
      for (int i = 0; i < 3; ++i) {
        const double t = angle(rng);
        map.set_keyframe_pose(static_cast<KeyframeId>(rng() % k), encoded_pose(t),
                              encoded_scale(t));
        map.set_keyframe_depth(static_cast<KeyframeId>(rng() % k),
                               static_cast<std::uint32_t>(rng() % kKeypoints),
                               static_cast<float>(t), 0.5F);
      }
      for (int i = 0; i < kHotEdits && np > 0; ++i) {
        map.set_point_position(static_cast<PointId>(rng() % std::min(np, kHot)),
                               encoded_position(rng));
        const double t = angle(rng);
        map.set_keyframe_pose(static_cast<KeyframeId>(rng() % std::min<std::size_t>(k, kHot)),
                              encoded_pose(t), encoded_scale(t));
        writer_ops += 2;
      }
      for (int i = 0; i < 4 && np > kHot; ++i) {
        map.set_point_bad(kHot + static_cast<PointId>(rng() % (np - kHot)));
      }
      map.update_covisibility(static_cast<KeyframeId>(rng() % k));
      ++iterations;
    }
    writer_done.store(true, std::memory_order_release);
  });

  ReaderStats st;
  std::vector<PointId> ids(8192);
  std::vector<PointId> sorted_ids(8192);
  std::vector<CovisibleKeyframe> cov(64);
  const geometry::Pinhole K{500, 500, 320, 240};
  std::mt19937 rng(2);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  auto check_ids = [&](std::size_t n) {
    const std::uint32_t np = map.num_points();  // loaded after the query
    std::copy_n(ids.begin(), n, sorted_ids.begin());
    std::sort(sorted_ids.begin(), sorted_ids.begin() + static_cast<std::ptrdiff_t>(n));
    for (std::size_t i = 0; i < n; ++i) {
      st.bad_ids += sorted_ids[i] >= np ? 1 : 0;
      st.duplicates += (i > 0 && sorted_ids[i] == sorted_ids[i - 1]) ? 1 : 0;
    }
  };
  while (!writer_done.load(std::memory_order_acquire)) {
    ++st.iterations;
    const std::uint32_t nk = map.num_keyframes();
    const std::uint32_t np = map.num_points();
    if (nk > 0) {
      const auto kf = static_cast<KeyframeId>(rng() % (rng() % 2 == 0 ? std::min(nk, kHot) : nk));
      SE3d T;
      double scale = 0.0;
      if (map.keyframe_pose(kf, T, &scale)) {
        ++st.pose_reads;
        st.torn += pose_ok(T, scale) ? 0 : 1;
      } else {
        ++st.read_give_ups;
      }
      const auto kp = map.keyframe_keypoints(kf);
      const auto kd = map.keyframe_descriptors(kf);
      if (kp.size() != kKeypoints || kd.size() != kKeypoints) {
        ++st.bad_immutable;
      } else {
        for (int s = 0; s < 4; ++s) {
          const std::size_t i = rng() % kKeypoints;
          const bool ok = kp[i].x == static_cast<float>(kf) && kp[i].y == static_cast<float>(i) &&
                          kp[i].response == static_cast<float>(kf * 1000 + i) &&
                          kd[i] == descs[kf][i];
          st.bad_immutable += ok ? 0 : 1;
          const PointId p = map.keyframe_point(kf, static_cast<std::uint32_t>(i));
          st.bad_ids += (p != kNoId && p >= map.num_points()) ? 1 : 0;
          st.bad_immutable +=
              std::isfinite(map.keyframe_depth(kf, static_cast<std::uint32_t>(i))) ? 0 : 1;
        }
      }
      const std::size_t nc = map.covisible_keyframes(kf, cov);
      const std::uint32_t nk_after = map.num_keyframes();
      for (std::size_t i = 0; i < nc; ++i) {
        const bool ok = cov[i].id < nk_after && cov[i].id != kf && cov[i].weight > 0 &&
                        (i == 0 || cov[i - 1].weight >= cov[i].weight);
        st.bad_covis += ok ? 0 : 1;
      }
      if (map.keyframe_t_ns(kf) != static_cast<std::int64_t>(kf) * 33'000'000) ++st.bad_immutable;
    }
    for (int s = 0; s < 16 && np > 0; ++s) {
      const auto p = static_cast<PointId>(rng() % (s % 2 == 0 ? std::min(np, kHot) : np));
      PointView v;
      if (map.read_point(p, v)) {
        ++st.point_reads;
        const float nn = v.normal.norm();
        const bool ok = position_ok(v.p_w) && descriptor_ok(v.descriptor) &&
                        std::abs(nn - 1.0F) < 1e-4F && v.ref_keyframe < nk &&
                        v.ref_keypoint < kNewPointsPerKf && v.min_distance <= v.max_distance &&
                        v.min_distance >= 0.0F;
        st.torn += ok ? 0 : 1;
      } else if (!map.point_is_bad(p)) {
        ++st.read_give_ups;
      }
    }
    if (st.iterations % 4 == 0) {
      const Eigen::Vector3d eye(0.8 * kRoom.x() * u(rng), 0.8 * kRoom.y() * u(rng),
                                0.8 * kRoom.z() * u(rng));
      const Eigen::Vector3d target(kRoom.x() * u(rng), kRoom.y() * u(rng), kRoom.z() * u(rng));
      const SE3d T =
          look_at(eye, target + Eigen::Vector3d(0.01, 0.02, 0.03), Eigen::Vector3d(0, -1, 0));
      check_ids(
          map.query_visible(T, K, 640, 480, 0.1, st.iterations % 8 == 0 ? 20.0 : 4.0, 0, ids));
      check_ids(map.query_radius(eye, 1.0, 0, ids));
      st.queries += 2;
    }
  }
  writer.join();

  std::printf(
      "writer: %llu iterations, ops %llu, keyframes %u, points %u; reader: %llu iterations, %llu "
      "pose "
      "reads, %llu point reads, %llu queries, %llu give-ups\n",
      static_cast<unsigned long long>(iterations), static_cast<unsigned long long>(writer_ops),
      map.num_keyframes(), map.num_points(), static_cast<unsigned long long>(st.iterations),
      static_cast<unsigned long long>(st.pose_reads),
      static_cast<unsigned long long>(st.point_reads), static_cast<unsigned long long>(st.queries),
      static_cast<unsigned long long>(st.read_give_ups));
  EXPECT_EQ(st.torn, 0u);
  EXPECT_EQ(st.bad_ids, 0u);
  EXPECT_EQ(st.duplicates, 0u);
  EXPECT_EQ(st.bad_immutable, 0u);
  EXPECT_EQ(st.bad_covis, 0u);
  EXPECT_GT(st.point_reads, 100u);
  EXPECT_GT(st.queries, 10u);
  EXPECT_GT(map.num_keyframes(), 2u);

  // Quiescent checks: every live point is in the cell of its final position, and the
  // covisibility weights equal the shared points counted from the associations.
  ASSERT_EQ(map.cell_insert_failures(), 0u);
  std::vector<PointId> near(4096);
  for (PointId p = 0; p < map.num_points(); ++p) {
    PointView v;
    if (!map.read_point(p, v)) {
      EXPECT_TRUE(map.point_is_bad(p));
      continue;
    }
    const std::size_t n = map.query_radius(v.p_w, 0.0, 0, near);
    EXPECT_EQ(std::count(near.begin(), near.begin() + static_cast<std::ptrdiff_t>(n), p), 1)
        << "point " << p;
  }
  const std::uint32_t nk = map.num_keyframes();
  for (KeyframeId k = 0; k < nk; ++k) map.update_covisibility(k);
  std::vector<std::vector<std::uint32_t>> shared(nk, std::vector<std::uint32_t>(nk, 0));
  for (PointId p = 0; p < map.num_points(); ++p) {
    if (map.point_is_bad(p)) continue;
    std::pair<KeyframeId, std::uint32_t> obs[8];
    const std::size_t n = map.point_observations(p, obs);
    for (std::size_t i = 0; i < n; ++i) {
      EXPECT_EQ(map.keyframe_point(obs[i].first, obs[i].second), p);
      for (std::size_t j = 0; j < n; ++j) {
        if (i != j) ++shared[obs[i].first][obs[j].first];
      }
    }
  }
  for (KeyframeId k = 0; k < nk; ++k) {
    const std::size_t n = map.covisible_keyframes(k, cov);
    for (std::size_t i = 0; i < n; ++i) EXPECT_EQ(cov[i].weight, shared[k][cov[i].id]);
  }
}

}  // namespace
}  // namespace mer::map
