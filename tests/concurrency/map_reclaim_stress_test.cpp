// Slot reuse under concurrency: one writer keeps a small map full, removing the oldest
// keyframes and random points and reusing their slots, while a registered reader (the
// tracker's role) passes a quiescent point per iteration, reads keyframes and points, and
// keeps ids across iterations. Every keyframe's immutable data encodes its serial and every
// point's position encodes its birth, so the reader detects a torn read, a slot rewritten
// under it (only possible if reclamation were wrong) and a kept id naming a newer occupant
// with an unchanged generation. Run under TSan too (label concurrency).
#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <deque>
#include <random>
#include <thread>
#include <vector>

#include <gtest/gtest.h>

#include "map/map.h"
#include "stress_config.h"

namespace mer::map {
namespace {

constexpr int kKeypoints = 48;        // per keyframe
constexpr int kNewPointsPerKf = 16;   // points created from each keyframe
constexpr std::size_t kLiveKfs = 10;  // the writer removes the oldest beyond this
constexpr int kPointsFreedPerKf = 6;  // random points freed per keyframe
constexpr int kMovesPerKf = 40;       // point moves per keyframe
constexpr auto kWriterTime = std::chrono::milliseconds(2000);
constexpr double kRoom = 4.0;  // half extent of the point cloud

std::uint64_t mix(std::uint64_t k) {
  k ^= k >> 31U;
  k *= 0x9E3779B97F4A7C15ULL;
  k ^= k >> 29U;
  return k;
}

/// Descriptor of keypoint i of the keyframe with serial s (its last word a checksum).
features::Descriptor descriptor_of(std::uint64_t s, std::uint64_t i) {
  features::Descriptor d{s, i, mix(s * 131 + i), 0};
  d[3] = mix(d[0] ^ mix(d[1] ^ mix(d[2])));
  return d;
}

bool descriptor_ok(const features::Descriptor& d) {
  return d[3] == mix(d[0] ^ mix(d[1] ^ mix(d[2])));
}

/// z is a function of (x, y); x is fixed at a point's birth (its identity), y moves.
double z_of(double x, double y) {
  return std::fmod(std::abs(7.3 * x + 13.1 * y), 2.0 * kRoom) - kRoom;
}

Eigen::Vector3d position(double x, double y) {
  return {x, y, z_of(x, y)};
}

struct ReaderStats {
  std::uint64_t iterations = 0;
  std::uint64_t keyframe_reads = 0;
  std::uint64_t point_reads = 0;
  std::uint64_t stale_keyframes = 0;  // kept ids whose generation changed (detected)
  std::uint64_t stale_points = 0;
  std::uint64_t kept_keyframes_checked = 0;
  std::uint64_t kept_points_checked = 0;
  std::uint64_t torn = 0;            // must stay 0
  std::uint64_t wrong_identity = 0;  // must stay 0: same generation, other occupant
  std::uint64_t bad_covis = 0;       // must stay 0
};

TEST(MapReclaimConcurrency, ReusedSlotsAreNeverSeenTornOrUnderAnUnchangedGeneration) {
  MapOptions o;
  o.max_keyframes = 16;
  o.max_points = 600;
  o.max_keypoints_per_keyframe = kKeypoints;
  o.max_observations_per_point = 8;
  o.max_covisible_per_keyframe = 8;
  o.cell_size = 0.5;
  o.cell_table_size = 1024;
  o.points_per_cell = 64;
  ASSERT_TRUE(validate(o).is_ok());
  Map map(o);
  const Result<int> reader = map.register_reader();  // before the threads start
  ASSERT_TRUE(reader.is_ok());
  std::atomic<bool> writer_done{false};

  std::uint64_t add_refused = 0;  // map full until the reader passes (expected, counted)
  std::uint64_t serial = 0;
  std::thread writer([&] {
    std::mt19937 rng(1);
    std::uniform_real_distribution<double> u(-1.0, 1.0);
    std::vector<features::Keypoint> kps(kKeypoints);
    std::vector<features::Descriptor> descs(kKeypoints);
    std::deque<KeyframeId> live;  // oldest first; the first keyframe (anchor) is kept
    KeyframeId anchor = kNoId;
    const auto t_end = std::chrono::steady_clock::now() + kWriterTime;
    while (std::chrono::steady_clock::now() < t_end) {
      for (int i = 0; i < kKeypoints; ++i) {
        features::Keypoint& k = kps[static_cast<std::size_t>(i)];
        k.x = static_cast<float>(serial);
        k.y = static_cast<float>(i);
        k.scale = 1.2F;
        descs[static_cast<std::size_t>(i)] = descriptor_of(serial, static_cast<std::uint64_t>(i));
      }
      KeyframeInput in;
      in.seq = serial;
      in.t_ns = static_cast<std::int64_t>(serial) * 1000;
      in.T_w_c.translation() = Eigen::Vector3d(u(rng), u(rng), u(rng));
      in.keypoints = kps;
      in.descriptors = descs;
      const Result<KeyframeId> kf = map.add_keyframe(in);
      if (!kf.is_ok()) {
        ++add_refused;
        std::this_thread::yield();
        continue;
      }
      if (anchor == kNoId) anchor = kf.value();
      if (kf.value() != anchor) live.push_back(kf.value());
      const std::uint32_t used = map.num_points();
      for (int i = 0; i < kNewPointsPerKf; ++i) {
        const double x =
            std::fmod(static_cast<double>(serial) * 0.37 + 0.01 * i, 2.0 * kRoom) - kRoom;
        (void)map.add_point(position(x, kRoom * u(rng)), kf.value(), static_cast<std::uint32_t>(i));
      }
      for (int i = kNewPointsPerKf; i < kKeypoints && used > 0; ++i) {
        const auto p = static_cast<PointId>(rng() % used);
        if (map.add_observation(p, kf.value(), static_cast<std::uint32_t>(i))) map.update_point(p);
      }
      map.update_covisibility(kf.value());
      for (int i = 0; i < kMovesPerKf && used > 0; ++i) {
        const auto p = static_cast<PointId>(rng() % used);
        PointView v;
        if (map.read_point(p, v)) map.set_point_position(p, position(v.p_w.x(), kRoom * u(rng)));
      }
      for (int i = 0; i < kPointsFreedPerKf && used > 0; ++i) {
        map.set_point_bad(static_cast<PointId>(rng() % used));
      }
      while (live.size() > kLiveKfs) {
        EXPECT_TRUE(map.remove_keyframe(live.front(), 2));
        live.pop_front();
      }
      ++serial;
    }
    writer_done.store(true, std::memory_order_release);
  });

  ReaderStats st;
  std::mt19937 rng(2);
  std::vector<CovisibleKeyframe> cov(16);
  std::vector<PointId> ids(1024);
  const geometry::Pinhole K{500, 500, 320, 240};
  // Ids kept across quiescent points, with what they named.
  KeyframeId kept_kf = kNoId;
  Generation kept_kf_gen = kNoGeneration;
  float kept_kf_serial = 0.0F;
  PointId kept_p = kNoId;
  Generation kept_p_gen = kNoGeneration;
  double kept_p_x = 0.0;
  while (!writer_done.load(std::memory_order_acquire)) {
    map.reader_quiescent(reader.value());
    ++st.iterations;
    // Kept ids: an unchanged generation must still name the same keyframe / point.
    if (kept_kf != kNoId) {
      const Generation g = map.keyframe_generation(kept_kf);
      const auto kps = map.keyframe_keypoints(kept_kf);
      if (g != kept_kf_gen) {
        ++st.stale_keyframes;
      } else if (!kps.empty()) {
        ++st.kept_keyframes_checked;
        st.wrong_identity += kps[0].x == kept_kf_serial ? 0 : 1;
      }
    }
    if (kept_p != kNoId) {
      PointView v;
      if (map.point_generation(kept_p) != kept_p_gen) {
        ++st.stale_points;
      } else if (map.read_point(kept_p, v) && v.generation == kept_p_gen) {
        ++st.kept_points_checked;
        st.wrong_identity += v.p_w.x() == kept_p_x ? 0 : 1;
      }
    }
    // Fresh reads of a random slot.
    const auto kf = static_cast<KeyframeId>(rng() % static_cast<std::uint32_t>(o.max_keyframes));
    const Generation g = map.keyframe_generation(kf);
    const auto kps = map.keyframe_keypoints(kf);
    const auto kd = map.keyframe_descriptors(kf);
    if (g != kNoGeneration && !kps.empty() && kd.size() == kps.size()) {
      ++st.keyframe_reads;
      const float s = kps[0].x;
      for (std::size_t i = 0; i < kps.size(); ++i) {
        const bool ok = kps[i].x == s && kps[i].y == static_cast<float>(i) &&
                        kd[i] == descriptor_of(static_cast<std::uint64_t>(s), i);
        st.torn += ok ? 0 : 1;
      }
      const std::int64_t t = map.keyframe_t_ns(kf);  // 0 once removed (not reused yet)
      st.torn += (t == 0 || t == static_cast<std::int64_t>(s) * 1000) ? 0 : 1;
      kept_kf = kf;
      kept_kf_gen = g;
      kept_kf_serial = s;
      for (std::size_t i = 0; i < kps.size(); i += 7) {
        const PointId p = map.keyframe_point(kf, static_cast<std::uint32_t>(i));
        PointView v;
        if (p == kNoId || !map.read_point(p, v)) continue;
        ++st.point_reads;
        const bool ok = v.p_w.z() == z_of(v.p_w.x(), v.p_w.y()) && descriptor_ok(v.descriptor) &&
                        v.ref_keyframe < static_cast<KeyframeId>(o.max_keyframes) &&
                        v.generation != kNoGeneration;
        st.torn += ok ? 0 : 1;
        kept_p = p;
        kept_p_gen = v.generation;
        kept_p_x = v.p_w.x();
      }
      const std::size_t nc = map.covisible_keyframes(kf, cov);
      for (std::size_t i = 0; i < nc; ++i) {
        st.bad_covis += (cov[i].id < static_cast<KeyframeId>(o.max_keyframes) && cov[i].id != kf &&
                         cov[i].weight > 0)
                            ? 0
                            : 1;
      }
    }
    if (st.iterations % 8 == 0) {
      const std::size_t n = map.query_radius(Eigen::Vector3d::Zero(), kRoom, 0, ids);
      for (std::size_t i = 0; i < n; ++i) {
        PointView v;
        if (map.read_point(ids[i], v)) st.torn += v.p_w.z() == z_of(v.p_w.x(), v.p_w.y()) ? 0 : 1;
      }
      (void)map.query_visible(SE3d::Identity(), K, 640, 480, 0.1, 10.0, 0, ids);
    }
  }
  writer.join();

  const MapCounters c = map.counters();
  std::printf(
      "writer: %llu keyframes added (%llu refused while full), %llu removed, %llu points freed, "
      "reused %llu keyframe / %llu point slots; reader: %llu iterations, %llu keyframe and %llu "
      "point reads, stale ids detected %llu keyframes / %llu points, kept ids checked %llu / "
      "%llu\n",
      static_cast<unsigned long long>(serial), static_cast<unsigned long long>(add_refused),
      static_cast<unsigned long long>(c.removed_keyframes),
      static_cast<unsigned long long>(c.bad_points),
      static_cast<unsigned long long>(c.reused_keyframe_slots),
      static_cast<unsigned long long>(c.reused_point_slots),
      static_cast<unsigned long long>(st.iterations),
      static_cast<unsigned long long>(st.keyframe_reads),
      static_cast<unsigned long long>(st.point_reads),
      static_cast<unsigned long long>(st.stale_keyframes),
      static_cast<unsigned long long>(st.stale_points),
      static_cast<unsigned long long>(st.kept_keyframes_checked),
      static_cast<unsigned long long>(st.kept_points_checked));
  EXPECT_EQ(st.torn, 0u);
  EXPECT_EQ(st.wrong_identity, 0u);
  EXPECT_EQ(st.bad_covis, 0u);
  // The scenario really reused slots and the reader really met stale ids.
  EXPECT_GT(c.reused_keyframe_slots, 10u);
  EXPECT_GT(c.reused_point_slots, 100u);
  EXPECT_GT(st.stale_keyframes, 0u);
  EXPECT_GT(st.stale_points, 0u);
  EXPECT_GT(st.kept_keyframes_checked, 0u);
  EXPECT_GT(st.kept_points_checked, 0u);
  EXPECT_GT(st.keyframe_reads, 100u);
  EXPECT_LE(c.live_keyframes, static_cast<std::uint32_t>(o.max_keyframes));

  // Quiescent checks: every point observation names a live keyframe that associates the
  // point back; no covisibility edge names a removed keyframe.
  for (PointId p = 0; p < map.num_points(); ++p) {
    std::pair<KeyframeId, std::uint32_t> obs[8];
    const std::size_t n = map.point_observations(p, obs);
    for (std::size_t i = 0; i < n; ++i) {
      EXPECT_TRUE(map.keyframe_is_live(obs[i].first));
      EXPECT_EQ(map.keyframe_point(obs[i].first, obs[i].second), p);
    }
  }
  for (KeyframeId k = 0; k < map.num_keyframes(); ++k) {
    const std::size_t n = map.covisible_keyframes(k, cov);
    for (std::size_t i = 0; i < n; ++i) EXPECT_TRUE(map.keyframe_is_live(cov[i].id));
  }
}

}  // namespace
}  // namespace mer::map
