// CellGrid: keys, insert / remove / move, bounded storage with counted failures, and the
// frustum / radius queries against brute force.
#include "map/cell_grid.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <random>
#include <set>
#include <vector>

#include <gtest/gtest.h>

namespace mer::map {
namespace {

constexpr double kCell = 0.25;

std::vector<PointId> sorted(std::span<const PointId> ids) {
  std::vector<PointId> v(ids.begin(), ids.end());
  std::sort(v.begin(), v.end());
  return v;
}

bool distinct(std::span<const PointId> ids) {
  const std::vector<PointId> v = sorted(ids);
  return std::adjacent_find(v.begin(), v.end()) == v.end();
}

TEST(CellGrid, KeyRoundTripAndRange) {
  CellGrid g(kCell, 64, 4);
  const CellKey k = g.key_of(Eigen::Vector3d(-0.01, 0.3, 2.6), 0);
  ASSERT_NE(k, kNoCell);
  const CellCoord c = CellGrid::coord_of(k);
  EXPECT_EQ(c.x, -1);
  EXPECT_EQ(c.y, 1);
  EXPECT_EQ(c.z, 10);
  EXPECT_EQ(CellGrid::key_of(c.x, c.y, c.z, 0), k);
  const CellCoord lo = CellGrid::coord_of(CellGrid::key_of(-(1 << 17), (1 << 17) - 1, 0, 0));
  EXPECT_EQ(lo.x, -(1 << 17));
  EXPECT_EQ(lo.y, (1 << 17) - 1);
  EXPECT_EQ(CellGrid::key_of(1 << 17, 0, 0, 0), kNoCell);
  EXPECT_EQ(CellGrid::key_of(0, -(1 << 17) - 1, 0, 0), kNoCell);
  EXPECT_EQ(CellGrid::key_of(0, 0, 0, kMaxSegments), kNoCell);
  EXPECT_EQ(g.key_of(Eigen::Vector3d(1e9, 0.0, 0.0), 0), kNoCell);
  EXPECT_EQ(g.key_of(Eigen::Vector3d(std::nan(""), 0.0, 0.0), 0), kNoCell);
}

// Every (coordinates, segment) has its own key, and the key gives both back: the same cell
// of two segments (unrelated world frames) is two cells.
TEST(CellGrid, KeysAreDistinctPerSegmentAndRoundTrip) {
  const std::int64_t coords[] = {-(1 << 17), -(1 << 16) - 3, -1, 0, 1, 4097, (1 << 17) - 1};
  std::vector<CellKey> keys;
  for (const std::int64_t x : coords) {
    for (const std::int64_t y : coords) {
      for (const std::int64_t z : {coords[0], coords[3], coords[6]}) {
        for (const unsigned seg : {0U, 1U, 7U, 8U, 63U, 64U, 200U, 255U}) {
          const auto segment = static_cast<std::uint16_t>(seg);
          const CellKey k = CellGrid::key_of(x, y, z, segment);
          ASSERT_NE(k, kNoCell);
          const CellCoord c = CellGrid::coord_of(k);
          EXPECT_EQ(c.x, x);
          EXPECT_EQ(c.y, y);
          EXPECT_EQ(c.z, z);
          EXPECT_EQ(c.segment, segment);
          keys.push_back(k);
        }
      }
    }
  }
  std::sort(keys.begin(), keys.end());
  EXPECT_EQ(std::adjacent_find(keys.begin(), keys.end()), keys.end());
}

// Segments 0 and 1 each fill the same cells (their world frames overlap): a query of one
// segment returns that segment's points only, all of them, whether it marches cells or scans
// the table, and a full output is not taken by the other segment's points.
TEST(CellGrid, QueriesReturnTheirSegmentOnly) {
  CellGrid g(kCell, 65536, 48);
  constexpr PointId kPerSegment = 200;
  for (PointId i = 0; i < 2 * kPerSegment; ++i) {
    const auto segment = static_cast<std::uint16_t>(i / kPerSegment);
    const PointId j = i % kPerSegment;
    const Eigen::Vector3d p(0.1 * static_cast<double>(j % 10) - 0.5,
                            0.1 * static_cast<double>((j / 10) % 5) - 0.25,
                            1.0 + 0.1 * static_cast<double>(j / 50));
    ASSERT_TRUE(g.insert(i, g.key_of(p, segment)));
  }
  const geometry::Pinhole K{300.0, 300.0, 320.0, 240.0};
  for (const double far : {1.6, 500.0}) {  // marched, then a table scan
    Frustum f;
    ASSERT_TRUE(Frustum::make(SE3d::Identity(), K, 640, 480, 0.1, far, f));
    for (const std::uint16_t segment : {std::uint16_t{0}, std::uint16_t{1}}) {
      std::vector<PointId> out(kPerSegment);
      const std::size_t n = g.query_frustum(f, segment, out);
      EXPECT_EQ(n, kPerSegment) << "segment " << segment << ", far " << far;
      for (std::size_t k = 0; k < n; ++k) EXPECT_EQ(out[k] / kPerSegment, segment);
    }
  }
  std::vector<PointId> out(2 * kPerSegment);
  EXPECT_EQ(g.query_radius(Eigen::Vector3d(0.0, 0.0, 1.5), 3.0, 1, out), kPerSegment);
  EXPECT_EQ(g.query_radius(Eigen::Vector3d(0.0, 0.0, 1.5), 3.0, 2, out), 0U);
}

TEST(CellGrid, InsertRemoveMove) {
  CellGrid g(kCell, 64, 8);
  const CellKey a = g.key_of(Eigen::Vector3d(0.1, 0.1, 0.1), 0);
  const CellKey b = g.key_of(Eigen::Vector3d(1.1, 0.1, 0.1), 0);
  ASSERT_NE(a, b);
  for (PointId id = 0; id < 5; ++id) ASSERT_TRUE(g.insert(id, a));
  PointId buf[16];
  EXPECT_EQ(sorted({buf, g.cell_points(a, buf)}), (std::vector<PointId>{0, 1, 2, 3, 4}));
  EXPECT_EQ(g.cell_points(b, buf), 0u);

  EXPECT_TRUE(g.remove(1, a));
  EXPECT_FALSE(g.remove(1, a));  // not there any more
  EXPECT_FALSE(g.remove(7, b));  // unknown cell
  EXPECT_EQ(sorted({buf, g.cell_points(a, buf)}), (std::vector<PointId>{0, 2, 3, 4}));

  EXPECT_TRUE(g.move(3, a, b));
  EXPECT_EQ(sorted({buf, g.cell_points(a, buf)}), (std::vector<PointId>{0, 2, 4}));
  EXPECT_EQ(sorted({buf, g.cell_points(b, buf)}), (std::vector<PointId>{3}));
  EXPECT_TRUE(g.move(3, b, b));  // same cell: no-op
  EXPECT_EQ(g.cell_points(b, buf), 1u);
  EXPECT_TRUE(g.move(9, kNoCell, b));  // from nowhere: a plain insert
  EXPECT_EQ(sorted({buf, g.cell_points(b, buf)}), (std::vector<PointId>{3, 9}));
  // A short output span is filled, not overrun.
  EXPECT_EQ(g.cell_points(a, std::span<PointId>(buf, 2)), 2u);
  EXPECT_EQ(g.failures(), 0u);
  EXPECT_EQ(g.stats().used_entries, 2u);
}

TEST(CellGrid, FullCellIsCountedNotSilent) {
  CellGrid g(kCell, 64, 4);
  const std::size_t bytes = g.memory_bytes();
  const CellKey a = g.key_of(Eigen::Vector3d::Zero(), 0);
  for (PointId id = 0; id < 4; ++id) ASSERT_TRUE(g.insert(id, a));
  EXPECT_FALSE(g.insert(4, a));
  EXPECT_FALSE(g.insert(5, a));
  EXPECT_EQ(g.stats().cell_full, 2u);
  EXPECT_EQ(g.failures(), 2u);
  PointId buf[8];
  EXPECT_EQ(g.cell_points(a, buf), 4u);
  // Room again after a removal.
  ASSERT_TRUE(g.remove(2, a));
  EXPECT_TRUE(g.insert(4, a));
  EXPECT_FALSE(g.insert(6, kNoCell));  // out of range position
  EXPECT_EQ(g.stats().out_of_range, 1u);
  EXPECT_EQ(g.memory_bytes(), bytes);
}

TEST(CellGrid, FullTableIsCountedAndEmptyCellsAreReused) {
  constexpr std::uint32_t kTable = 64;
  CellGrid g(kCell, kTable, 2);
  const std::size_t bytes = g.memory_bytes();
  std::vector<CellKey> keys;
  for (int i = 0; i < 100; ++i) keys.push_back(CellGrid::key_of(i, 2 * i, -i, 0));
  std::uint32_t ok = 0;
  for (int i = 0; i < 100; ++i) ok += g.insert(static_cast<PointId>(i), keys[i]) ? 1U : 0U;
  EXPECT_EQ(ok, kTable);  // every entry used, the rest counted
  EXPECT_EQ(g.stats().used_entries, kTable);
  EXPECT_EQ(g.stats().table_full, 100u - kTable);
  EXPECT_EQ(g.failures(), 100u - kTable);
  EXPECT_EQ(g.memory_bytes(), bytes);

  // Empty every cell: new cells re-key the empty entries instead of failing.
  PointId buf[4];
  for (int i = 0; i < 100; ++i) {
    if (g.cell_points(keys[i], buf) == 1) {
      ASSERT_TRUE(g.remove(buf[0], keys[i]));
    }
  }
  for (int i = 0; i < static_cast<int>(kTable); ++i) {
    EXPECT_TRUE(g.insert(static_cast<PointId>(1000 + i), CellGrid::key_of(-i, 5, 7 * i, 0)));
  }
  EXPECT_EQ(g.stats().used_entries, kTable);
  for (int i = 0; i < static_cast<int>(kTable); ++i) {
    ASSERT_EQ(g.cell_points(CellGrid::key_of(-i, 5, 7 * i, 0), buf), 1u);
    EXPECT_EQ(buf[0], static_cast<PointId>(1000 + i));
  }
}

TEST(CellGrid, DegenerateFrustumRejected) {
  const geometry::Pinhole K{500, 500, 320, 240};
  Frustum f;
  EXPECT_TRUE(Frustum::make(SE3d::Identity(), K, 640, 480, 0.1, 5.0, f));
  EXPECT_FALSE(Frustum::make(SE3d::Identity(), K, 0, 480, 0.1, 5.0, f));
  EXPECT_FALSE(Frustum::make(SE3d::Identity(), K, 640, 480, 0.0, 5.0, f));
  EXPECT_FALSE(Frustum::make(SE3d::Identity(), K, 640, 480, 1.0, 0.5, f));
  EXPECT_FALSE(Frustum::make(SE3d::Identity(), K, 640, 480, 0.1, INFINITY, f));
  EXPECT_FALSE(Frustum::make(SE3d::Identity(), {0, 500, 320, 240}, 640, 480, 0.1, 5.0, f));
  // Every corner lies on the planes it belongs to and inside the others.
  for (const Eigen::Vector3d& c : f.corner) {
    for (int i = 0; i < 6; ++i) EXPECT_GE(f.normal[i].dot(c) + f.offset[i], -1e-9);
  }
}

// A room of random points and random cameras inside it.
struct Room {
  std::vector<Eigen::Vector3d> pts;
  std::mt19937 rng{7};
  Eigen::Vector3d half{4.0, 1.5, 4.0};
  Room(CellGrid& g, int n) {
    std::uniform_real_distribution<double> u(-1.0, 1.0);
    for (int i = 0; i < n; ++i) {
      pts.emplace_back(u(rng) * half.x(), u(rng) * half.y(), u(rng) * half.z());
      EXPECT_TRUE(g.insert(static_cast<PointId>(i), g.key_of(pts.back(), 0)));
    }
  }
  SE3d random_pose() {
    std::uniform_real_distribution<double> u(-1.0, 1.0);
    const Eigen::Vector3d eye(0.8 * u(rng) * half.x(), 0.8 * u(rng) * half.y(),
                              0.8 * u(rng) * half.z());
    Eigen::Vector3d target(u(rng) * half.x(), u(rng) * half.y(), u(rng) * half.z());
    if ((target - eye).norm() < 0.5) target = eye + Eigen::Vector3d(1, 0.1, 0.2);
    return look_at(eye, target, Eigen::Vector3d(0.3 * u(rng), -1.0, 0.3 * u(rng)).normalized());
  }
};

std::vector<PointId> brute_visible(const std::vector<Eigen::Vector3d>& pts, const SE3d& T_w_c,
                                   const geometry::Pinhole& K, int w, int h, double near,
                                   double far) {
  std::vector<PointId> v;
  const SE3d T_c_w = T_w_c.inverse();
  for (std::size_t i = 0; i < pts.size(); ++i) {
    const Eigen::Vector3d p = T_c_w * pts[i];
    if (p.z() < near || p.z() > far) continue;
    const Eigen::Vector2d uv = K.project(p);
    if (uv.x() >= 0 && uv.x() < w && uv.y() >= 0 && uv.y() < h)
      v.push_back(static_cast<PointId>(i));
  }
  return v;
}

void check_frustum_superset(double far, double max_ratio) {
  CellGrid g(kCell, 65536, 64);
  Room room(g, 20000);
  ASSERT_EQ(g.failures(), 0u);
  const geometry::Pinhole K{500, 500, 320, 240};
  std::vector<PointId> out(20000);
  std::size_t returned = 0;
  std::size_t visible = 0;
  for (int trial = 0; trial < 200; ++trial) {
    const SE3d T = room.random_pose();
    Frustum f;
    ASSERT_TRUE(Frustum::make(T, K, 640, 480, 0.1, far, f));
    const std::size_t n = g.query_frustum(f, 0, out);
    const std::span<const PointId> got(out.data(), n);
    ASSERT_TRUE(distinct(got));
    const std::vector<PointId> truth = brute_visible(room.pts, T, K, 640, 480, 0.1, far);
    const std::vector<PointId> s = sorted(got);
    for (const PointId id : truth) {
      ASSERT_TRUE(std::binary_search(s.begin(), s.end(), id)) << "trial " << trial << " id " << id;
    }
    // Nothing far from the frustum: every returned point is within one cell diagonal of it.
    const double diag = std::sqrt(3.0) * kCell;
    for (const PointId id : got) {
      for (int i = 0; i < 6; ++i) {
        ASSERT_GE(f.normal[i].dot(room.pts[id]) + f.offset[i], -diag - 1e-9);
      }
    }
    returned += n;
    visible += truth.size();
  }
  const double ratio = static_cast<double>(returned) / static_cast<double>(visible);
  std::printf("far %.1f: returned / visible = %zu / %zu = %.3f\n", far, returned, visible, ratio);
  EXPECT_LT(ratio, max_ratio);
}

TEST(CellGrid, FrustumQueryIsSupersetOfBruteForceMarch) {
  check_frustum_superset(5.0, 1.6);
}
TEST(CellGrid, FrustumQueryIsSupersetOfBruteForceScan) {
  check_frustum_superset(60.0, 1.6);
}

// A truncated query keeps the nearest cells: marching (far 4) and table scan (far 8).
void check_nearest_first(double far) {
  CellGrid g(kCell, 65536, 64);
  Room room(g, 20000);
  const geometry::Pinhole K{500, 500, 320, 240};
  const SE3d T = look_at({-3.5, 0, 0}, {3.5, 0, 0}, {0, -1, 0});  // looking along +x
  Frustum f;
  ASSERT_TRUE(Frustum::make(T, K, 640, 480, 0.1, far, f));
  std::vector<PointId> all(20000);
  const std::size_t n_all = g.query_frustum(f, 0, all);
  std::vector<PointId> few(200);
  const std::size_t n = g.query_frustum(f, 0, few);
  ASSERT_EQ(n, 200u);
  ASSERT_TRUE(distinct({few.data(), n}));
  // All 200 are nearer than the 20% quantile of all the returned points (plus one band).
  std::vector<double> depth;
  for (std::size_t i = 0; i < n_all; ++i) depth.push_back(room.pts[all[i]].x());
  std::nth_element(depth.begin(), depth.begin() + depth.size() / 5, depth.end());
  const double q20 = depth[depth.size() / 5];
  for (const PointId id : few) EXPECT_LT(room.pts[id].x(), q20) << "far " << far;
}

TEST(CellGrid, FrustumQueryNearestFirstWhenTruncatedMarch) {
  check_nearest_first(4.0);
}
TEST(CellGrid, FrustumQueryNearestFirstWhenTruncatedScan) {
  check_nearest_first(8.0);
}

TEST(CellGrid, RadiusQueryMatchesBruteForce) {
  CellGrid g(kCell, 65536, 64);
  Room room(g, 20000);
  std::vector<PointId> out(20000);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  std::uniform_real_distribution<double> ur(0.0, 1.5);
  const double diag = std::sqrt(3.0) * kCell;
  for (int trial = 0; trial < 100; ++trial) {
    const Eigen::Vector3d c(u(room.rng) * 4, u(room.rng) * 1.5, u(room.rng) * 4);
    // Small radii (march) and one huge radius (table scan).
    const double r = trial == 99 ? 20.0 : ur(room.rng);
    const std::size_t n = g.query_radius(c, r, 0, out);
    const std::span<const PointId> got(out.data(), n);
    ASSERT_TRUE(distinct(got));
    const std::vector<PointId> s = sorted(got);
    std::size_t truth = 0;
    for (std::size_t i = 0; i < room.pts.size(); ++i) {
      if ((room.pts[i] - c).norm() <= r) {
        ++truth;
        ASSERT_TRUE(std::binary_search(s.begin(), s.end(), static_cast<PointId>(i)));
      }
    }
    for (const PointId id : got) ASSERT_LE((room.pts[id] - c).norm(), r + diag + 1e-9);
    if (trial == 99) {
      EXPECT_EQ(n, room.pts.size());
    }
    (void)truth;
  }
  EXPECT_EQ(g.query_radius(Eigen::Vector3d::Zero(), -1.0, 0, out), 0u);
}

}  // namespace
}  // namespace mer::map
