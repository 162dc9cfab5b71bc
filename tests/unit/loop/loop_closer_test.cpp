// Loop closure: retrieval keys (each table reads its own bits of the descriptor, so a bit no
// table uses changes no key and a bit one table uses changes that table's key only), and the
// geometric check's guided search on a map whose loop keyframe sees repeated texture.
#include "loop/loop_closer.h"

#include <array>
#include <cmath>
#include <cstdio>
#include <random>
#include <vector>

#include <gtest/gtest.h>

#include "map/map.h"
#include "support/doc_check.h"
#include "synthetic_map.h"

namespace mer::loop {
namespace {

TEST(LoopCloserKeys, EachTableReadsItsOwnBits) {
  const features::Descriptor d{0x0123456789abcdefULL, 0xfedcba9876543210ULL, 0x0f0f0f0f0f0f0f0fULL,
                               0x5555aaaa5555aaaaULL};
  const auto k = descriptor_keys(d);
  EXPECT_EQ(descriptor_keys(d), k);
  // Table t reads bits t, t + 4, ..., t + 60 of word t: bit 1 of word 0 is nobody's.
  features::Descriptor unused = d;
  unused[0] ^= 1ULL << 1U;
  EXPECT_EQ(descriptor_keys(unused), k);
  for (std::size_t t = 0; t < k.size(); ++t) {
    features::Descriptor flipped = d;
    flipped[t] ^= 1ULL << t;  // table t's first bit
    const auto kf = descriptor_keys(flipped);
    for (std::size_t u = 0; u < k.size(); ++u) {
      if (u == t) {
        EXPECT_NE(kf[u], k[u]) << "table " << t;
      } else {
        EXPECT_EQ(kf[u], k[u]) << "table " << u << " changed by table " << t << "'s bit";
      }
    }
  }
}

TEST(LoopOptions, EveryFieldHasADocLine) {
  testing::DocCheck v;
  LoopOptions o;
  o.visit(v);
  EXPECT_EQ(v.fields, 31);
}

// An old keyframe A and, after a detour, a new keyframe B at nearly the same place, whose map
// has drifted by a similarity (its own points are a transformed copy of A's). Two thirds of
// the points come in triples with one descriptor (repeated texture): a descriptor-only match
// cannot tell them apart (ratio test), projecting with the similarity fitted on the distinct
// ones can.
struct LoopScene {
  static constexpr int kPoints = 120;
  static constexpr double kDrift = 1.04;                 // scale of the new side's drift
  static constexpr double kBaseline = 0.1;               // B's true offset from A, m
  static constexpr std::uint64_t kMsPerKeyframe = 1000;  // B comes 5 s after A
  map::Map map;
  geometry::Pinhole K{400.0, 400.0, 320.0, 240.0};
  map::KeyframeId a = map::kNoId;
  map::KeyframeId b = map::kNoId;

  // The drift of B's side: yaw 3 deg, a shift, and `scale`.
  static geometry::Sim3d drift(double scale) {
    geometry::Sim3d S;
    S.R = Eigen::AngleAxisd(3.0 * M_PI / 180.0, Eigen::Vector3d::UnitY()).toRotationMatrix();
    S.t = Eigen::Vector3d(0.05, 0.02, -0.03);
    S.s = scale;
    return S;
  }
  // A true pose as the drifted map holds it: rotated by S, its centre moved by S.
  static SE3d drifted(const geometry::Sim3d& S, const SE3d& T_w_c_true) {
    SE3d T_w_c = SE3d::Identity();
    T_w_c.linear() = S.R * T_w_c_true.linear();
    T_w_c.translation() = S * T_w_c_true.translation();
    return T_w_c;
  }

  static map::MapOptions options() {
    map::MapOptions o;
    o.max_keyframes = 16;
    o.max_points = 512;
    o.max_keypoints_per_keyframe = 256;
    o.max_observations_per_point = 8;
    o.max_covisible_per_keyframe = 8;
    o.cell_table_size = 1024;
    o.points_per_cell = 32;
    return o;
  }

  // depth_noise: each map point (both sides) is off its true position along its keyframe's
  // ray by this relative standard deviation, as triangulated points are; the keypoints stay
  // exact.
  // B_segment: B is made in that map segment (another one than A's: a merge); drift_scale:
  // the scale of B's side (a new monocular segment's scale is its own, any ratio).
  explicit LoopScene(double depth_noise = 0.0, std::uint16_t b_segment = 0,
                     double drift_scale = kDrift)
      : map(options()) {
    std::mt19937_64 rng(7);
    // (std::normal_distribution needs a positive sigma; without noise nothing is drawn.)
    std::normal_distribution<double> noise(0.0, depth_noise > 0.0 ? depth_noise : 1.0);
    auto depth_err = [&](std::mt19937_64& g) { return depth_noise > 0.0 ? noise(g) : 0.0; };
    std::uniform_real_distribution<double> ux(-1.5, 1.5);
    std::uniform_real_distribution<double> uy(-1.0, 1.0);
    std::uniform_real_distribution<double> uz(2.0, 4.0);
    std::vector<Eigen::Vector3d> pts;
    std::vector<features::Descriptor> desc;
    features::Descriptor shared{};
    for (int i = 0; i < kPoints; ++i) {
      pts.emplace_back(ux(rng), uy(rng), uz(rng));
      if (i % 3 == 0) {
        desc.push_back({rng(), rng(), rng(), rng()});  // a distinct point
      } else {
        if (i % 3 == 1) shared = {rng(), rng(), rng(), rng()};
        desc.push_back(shared);  // two points with one descriptor
      }
    }
    // Keyframe A at the origin, with the points.
    const SE3d T_w_a = SE3d::Identity();
    a = add_view(T_w_a, T_w_a, pts, desc, 0, 0);
    for (int i = 0; i < kPoints; ++i) {
      const Eigen::Vector3d p_a = pts[static_cast<std::size_t>(i)] * (1.0 + depth_err(rng));
      EXPECT_TRUE(map.add_point(p_a, a, static_cast<std::uint32_t>(i)).is_ok());
    }
    // A detour of keyframes looking elsewhere (their keypoints share nothing with A's).
    for (int k = 1; k <= 4; ++k) {
      std::vector<features::Descriptor> other;
      for (int i = 0; i < kPoints; ++i) other.push_back({rng(), rng(), rng(), rng()});
      const SE3d T(Eigen::Translation3d(static_cast<double>(k), 0.0, 0.0));
      (void)add_view(T, T, pts, other, static_cast<std::uint64_t>(k),
                     static_cast<std::uint64_t>(k) * kMsPerKeyframe);
    }
    // Keyframe B: truly 10 cm right of A, but the map drifted by S (yaw 3 deg, a shift and
    // scale 1.04): its pose and its points are S times the true ones.
    const geometry::Sim3d S = drift(drift_scale);
    const SE3d T_w_b_true(Eigen::Translation3d(kBaseline, 0.0, 0.0));
    const SE3d T_w_b = drifted(S, T_w_b_true);
    std::vector<features::Descriptor> desc_b = desc;
    for (features::Descriptor& d : desc_b) d[0] ^= 0x11ULL;  // 2 bits: another view's noise
    b = add_view(T_w_b_true, T_w_b, pts, desc_b, 5, 5 * kMsPerKeyframe, b_segment);
    for (int i = 0; i < kPoints; ++i) {
      const Eigen::Vector3d& p = pts[static_cast<std::size_t>(i)];
      const Eigen::Vector3d p_b =
          T_w_b_true * ((T_w_b_true.inverse() * p) * (1.0 + depth_err(rng)));
      EXPECT_TRUE(map.add_point(S * p_b, b, static_cast<std::uint32_t>(i)).is_ok());
    }
  }

  map::KeyframeId add_view(const SE3d& T_true, const SE3d& T_stored,
                           const std::vector<Eigen::Vector3d>& pts,
                           const std::vector<features::Descriptor>& desc, std::uint64_t seq,
                           std::uint64_t t, std::uint16_t segment = 0) {
    return scene::add_view(map, K, T_true, T_stored, pts, desc, seq, t, segment);
  }
};

// LoopScene's loop checked with options o (candidates 2 keyframes apart).
LoopReport close_true_loop(LoopOptions o) {
  LoopScene scene;
  o.min_keyframe_gap = 2;
  LoopCloser closer(o, scene.map, {1.0F}, false, nullptr);
  return closer.spin_once(scene.b, scene.K);
}

LoopReport close_loop(int guided_min_inliers) {
  LoopOptions o;
  o.guided_min_inliers = guided_min_inliers;
  return close_true_loop(o);
}

TEST(LoopCloser, GuidedSearchFindsTheRepeatedTextureMatches) {
  const LoopReport without = close_loop(0);
  const LoopReport with = close_loop(10);
  std::printf("loop matches / inliers: descriptor-only %d / %d, with the guided search %d / %d\n",
              without.matches, without.inliers, with.matches, with.inliers);
  // The distinct third is found either way, and is enough to close this loop.
  ASSERT_TRUE(without.closed);
  EXPECT_GE(without.inliers, LoopScene::kPoints / 3 - 4);
  EXPECT_LE(without.inliers, LoopScene::kPoints / 3 + 4);
  // The guided search adds the repeated ones.
  ASSERT_TRUE(with.closed);
  EXPECT_GE(with.inliers, LoopScene::kPoints - 8);
  EXPECT_EQ(with.loop_keyframe, without.loop_keyframe);
  EXPECT_NEAR(with.scale, without.scale, 0.02);
}

// Monocular map points are uncertain mostly along their rays. A similarity fitted to their 3D
// positions takes those errors in full; refined on the reprojection errors in both keyframes
// it is held by the keypoints, which are exact here. The true S_cand_new is B's true pose in
// A (the points in B's camera are the true ones times kDrift): rotation identity, translation
// (kBaseline, 0, 0) in metres of A, scale 1 / kDrift.
TEST(LoopCloser, ReprojectionRefinementRecoversTheLoopSimilarity) {
  struct Error {
    double scale = 0.0;  // relative
    double t = 0.0;      // m
    double rot_deg = 0.0;
  };
  auto fit = [](int refine_iterations, LoopReport& rep) {
    LoopScene scene(0.03);
    LoopOptions o;
    o.min_keyframe_gap = 2;
    o.refine_iterations = refine_iterations;
    LoopCloser closer(o, scene.map, {1.0F}, false, nullptr);
    rep = closer.spin_once(scene.b, scene.K);
    const geometry::Sim3d& S = rep.similarity;
    Error e;
    e.scale = std::abs(S.s * LoopScene::kDrift - 1.0);
    e.t = (S.t - Eigen::Vector3d(LoopScene::kBaseline, 0.0, 0.0)).norm();
    e.rot_deg = Eigen::AngleAxisd(S.R).angle() * 180.0 / M_PI;
    return e;
  };
  LoopReport plain;
  LoopReport refined;
  const Error e0 = fit(0, plain);
  const Error e1 = fit(10, refined);
  std::printf(
      "loop similarity error, 3D fit / refined: scale %.4f / %.4f, translation %.4f / "
      "%.4f m, rotation %.3f / %.3f deg; inliers %d / %d\n",
      e0.scale, e1.scale, e0.t, e1.t, e0.rot_deg, e1.rot_deg, plain.inliers, refined.inliers);
  ASSERT_TRUE(plain.closed);
  ASSERT_TRUE(refined.closed);
  EXPECT_GE(refined.inliers, plain.inliers);
  // With 3 % depth noise the 3D fit is off by 1.4 % in scale, 2.6 cm and 0.47 degrees;
  // refined by 0.6 %, 2.4 mm and 0.03 degrees. The scale gains least: the keypoints hold it
  // only through the 10 cm baseline.
  EXPECT_LT(e1.rot_deg, 0.5 * e0.rot_deg);
  EXPECT_LT(e1.t, 0.5 * e0.t);
  EXPECT_LT(e1.scale, 0.5 * e0.scale + 1e-3);
}

// A loop onto another segment's keyframe merges the two: B's segment (its own scale, 0.3 of
// A's, as a new monocular segment has) moves into A's frame and lands where the truth is. The
// correction after the merge is rigid: the merge applied the scale, the loop must not apply
// it again (it did: B's neighbourhood shrank by 0.3 around B). Also past the loop scale
// bound of one segment (2): between segments any scale ratio is possible.
TEST(LoopCloser, MergeOfASegmentWithAnotherScaleLandsOnTheTruth) {
  constexpr double kSegmentScale = 0.3;
  LoopScene scene(0.0, 1, kSegmentScale);
  LoopOptions o;
  o.min_keyframe_gap = 2;
  LoopCloser closer(o, scene.map, {1.0F}, false, nullptr);
  const LoopReport rep = closer.spin_once(scene.b, scene.K);
  ASSERT_TRUE(rep.closed);
  EXPECT_EQ(rep.merged_from, 1);
  EXPECT_EQ(rep.merged_into, 0);
  EXPECT_NEAR(rep.merge_similarity.s, 1.0 / kSegmentScale, 0.01 / kSegmentScale);
  EXPECT_NEAR(rep.scale, 1.0, 1e-3) << "the merge's scale applied again by the correction";
  EXPECT_EQ(scene.map.keyframe_segment(scene.b), 0);
  SE3d T_w_b;
  ASSERT_TRUE(scene.map.keyframe_pose(scene.b, T_w_b));
  EXPECT_LT((T_w_b.translation() - Eigen::Vector3d(LoopScene::kBaseline, 0.0, 0.0)).norm(), 0.01);
  // B's points (after the fusion, A's or B's, wherever they are) where the truth has them.
  SE3d T_w_a;
  ASSERT_TRUE(scene.map.keyframe_pose(scene.a, T_w_a));
  int checked = 0;
  double worst = 0.0;
  for (std::uint32_t i = 0; i < static_cast<std::uint32_t>(LoopScene::kPoints); ++i) {
    map::PointView pa;
    map::PointView pb;
    const map::PointId qa = scene.map.keyframe_point(scene.a, i);
    const map::PointId qb = scene.map.keyframe_point(scene.b, i);
    if (qa == map::kNoId || qb == map::kNoId || !scene.map.read_point(qa, pa) ||
        !scene.map.read_point(qb, pb)) {
      continue;
    }
    worst = std::max(worst, (pa.p_w - pb.p_w).norm());
    ++checked;
  }
  EXPECT_GT(checked, LoopScene::kPoints / 2);
  EXPECT_LT(worst, 0.01) << "A's and B's views of one point disagree after the merge";
}

// The same loop made 5 ms after the old keyframe instead of 5 s: within min_time_gap_s the old
// keyframe is no candidate at all.
TEST(LoopCloser, KeyframesOfTheLastSecondsAreNoCandidates) {
  LoopScene scene;
  LoopOptions o;
  o.min_keyframe_gap = 2;
  o.min_time_gap_s = 6.0;  // B is 5 s after A
  LoopCloser closer(o, scene.map, {1.0F}, false, nullptr);
  const LoopReport r = closer.spin_once(scene.b, scene.K);
  EXPECT_FALSE(r.closed);
  EXPECT_EQ(r.candidates, 0);
}

// A look-alike place: keyframe B sees a copy of the poster keyframe A sees, from the same
// relative pose and where the map expects A's place (so no drift bound can tell), but the
// rest of each view differs. The poster alone makes a perfect similarity; projected with it,
// A's surroundings are not found in B nor B's in A. The true loop of LoopScene is found both
// ways.
struct LookAlikeScene {
  static constexpr int kPoster = 60;
  static constexpr int kSurroundings = 90;
  map::Map map;
  geometry::Pinhole K{400.0, 400.0, 320.0, 240.0};
  map::KeyframeId a = map::kNoId;
  map::KeyframeId b = map::kNoId;

  static map::MapOptions options() {
    map::MapOptions o = LoopScene::options();
    o.max_points = 1024;  // 6 views of 150 points (B shares B0's)
    return o;
  }

  LookAlikeScene() : map(options()) {
    std::mt19937_64 rng(11);
    std::uniform_real_distribution<double> px(-0.6, 0.6);
    std::uniform_real_distribution<double> py(-0.4, 0.4);
    std::uniform_real_distribution<double> ux(-1.5, 1.5);
    std::uniform_real_distribution<double> uy(-1.0, 1.0);
    std::uniform_real_distribution<double> uz(2.0, 4.0);
    auto random_desc = [&] { return features::Descriptor{rng(), rng(), rng(), rng()}; };
    std::vector<Eigen::Vector3d> poster;  // a flat poster 3 m ahead, in the camera frame
    std::vector<features::Descriptor> poster_desc;
    for (int i = 0; i < kPoster; ++i) {
      poster.emplace_back(px(rng), py(rng), 3.0);
      poster_desc.push_back(random_desc());
    }
    std::vector<map::PointId> last_points;  // of the last view made
    auto view = [&](std::uint64_t seq, std::uint64_t t_ms, const SE3d& T_w_c, bool copy) {
      std::vector<Eigen::Vector3d> pts_w;
      std::vector<features::Descriptor> desc;
      for (int i = 0; i < kPoster; ++i) {
        pts_w.push_back(T_w_c * poster[static_cast<std::size_t>(i)]);
        features::Descriptor d = poster_desc[static_cast<std::size_t>(i)];
        if (copy) d[0] ^= 0x11ULL;  // another view's noise
        desc.push_back(d);
      }
      for (int i = 0; i < kSurroundings; ++i) {  // each view's own surroundings
        pts_w.push_back(T_w_c * Eigen::Vector3d(ux(rng), uy(rng), uz(rng)));
        desc.push_back(random_desc());
      }
      const map::KeyframeId id = scene::add_view(map, K, T_w_c, T_w_c, pts_w, desc, seq, t_ms);
      last_points.clear();
      for (std::size_t i = 0; i < pts_w.size(); ++i) {
        const auto p = map.add_point(pts_w[i], id, static_cast<std::uint32_t>(i));
        EXPECT_TRUE(p.is_ok());
        last_points.push_back(p.is_ok() ? p.value() : map::kNoId);
      }
      last_pts_w_ = pts_w;
      last_desc_ = desc;
      return id;
    };
    a = view(0, 0, SE3d::Identity(), false);
    for (std::uint64_t k = 1; k <= 4; ++k) {  // a detour elsewhere
      (void)view(k, k * 1000, SE3d(Eigen::Translation3d(0.0, 0.0, -5.0 * static_cast<double>(k))),
                 false);
    }
    // B0, then B 5 cm further: the same look-alike place seen twice, B observing B0's points
    // (the share of the same place, which the check compares with).
    const map::KeyframeId b0 = view(5, 4900, SE3d(Eigen::Translation3d(0.05, 0.0, 0.0)), true);
    (void)b0;
    b = scene::add_view(map, K, SE3d(Eigen::Translation3d(0.1, 0.0, 0.0)),
                        SE3d(Eigen::Translation3d(0.1, 0.0, 0.0)), last_pts_w_, last_desc_, 6,
                        5000);
    for (std::size_t i = 0; i < last_points.size(); ++i) {
      EXPECT_TRUE(map.add_observation(last_points[i], b, static_cast<std::uint32_t>(i)));
    }
    map.update_covisibility(b);
  }

 private:
  std::vector<Eigen::Vector3d> last_pts_w_;
  std::vector<features::Descriptor> last_desc_;
};

TEST(LoopCloser, LookAlikeIsRefusedWhenNotFoundBothWays) {
  for (const double min_found : {0.0, 0.5}) {
    LookAlikeScene scene;
    LoopOptions o;
    o.min_keyframe_gap = 2;
    o.min_found_fraction = min_found;
    LoopCloser closer(o, scene.map, {1.0F}, false, nullptr);
    const LoopReport r = closer.spin_once(scene.b, scene.K);
    std::printf("look-alike, min_found_fraction %.1f: closed %d, refused %d\n", min_found,
                r.closed ? 1 : 0, r.refused_found);
    if (min_found == 0.0) {
      // Unchecked, the poster closes the loop.
      ASSERT_TRUE(r.closed);
      EXPECT_GE(r.inliers, LookAlikeScene::kPoster - 6);
      // About the poster's share of each view is found: 60 of 150 points; B's own place is
      // found in full in B0.
      EXPECT_NEAR(r.found_new, 0.4, 0.1);
      EXPECT_NEAR(r.found_old, 0.4, 0.1);
      EXPECT_GT(r.found_usual, 0.9);
    } else {
      EXPECT_FALSE(r.closed);
      EXPECT_EQ(r.refused_found, 1);
      EXPECT_EQ(closer.totals().rejected.not_found, 1U);
    }
  }
  // The true loop passes the same check: its views are found both ways.
  LoopOptions o;
  o.min_found_fraction = 0.5;
  const LoopReport r = close_true_loop(o);
  ASSERT_TRUE(r.closed);
  EXPECT_GT(r.found_new, 0.9);
  EXPECT_GT(r.found_old, 0.9);
}

// Panels repeating along a hall every kPeriod m: keyframe A faces panel -4 and C panel 1; a
// detour of kDetour m away from the wall follows; then B, truly facing panel 3 (never seen
// before), with B0 just before it. Every panel is the same, so B's view matches A's and C's
// exactly, each by a similarity that puts B where that keyframe was. The map's poses are
// exact, so both are wrong: A's asks for a 35 m correction over 85 m of path (refused by the
// drift bound), C's for 10 m over 60 m (within it), and both explain all of B's points.
struct RepeatedPanelsScene {
  static constexpr int kPanelPoints = 90;
  static constexpr double kPeriod = 5.0;
  map::Map map;
  geometry::Pinhole K{400.0, 400.0, 320.0, 240.0};
  map::KeyframeId a = map::kNoId;
  map::KeyframeId c = map::kNoId;
  map::KeyframeId b = map::kNoId;

  static map::MapOptions options() {
    map::MapOptions o = LoopScene::options();
    o.max_points = 1024;
    return o;
  }

  RepeatedPanelsScene() : map(options()) {
    std::mt19937_64 rng(5);
    std::uniform_real_distribution<double> px(-1.2, 1.2);
    std::uniform_real_distribution<double> py(-0.9, 0.9);
    auto random_desc = [&] { return features::Descriptor{rng(), rng(), rng(), rng()}; };
    std::vector<Eigen::Vector3d> panel;  // a panel 3 m ahead, in the frame of a camera facing it
    std::vector<features::Descriptor> panel_desc;
    for (int i = 0; i < kPanelPoints; ++i) {
      panel.emplace_back(px(rng), py(rng), 3.0);
      panel_desc.push_back(random_desc());
    }
    std::vector<map::PointId> last_points;
    std::vector<Eigen::Vector3d> last_pts_w;
    std::vector<features::Descriptor> last_desc;
    // A keyframe facing the panel at x (the first `shown` of its points seen), or, panel
    // false, a view of random texture elsewhere.
    auto view = [&](std::uint64_t seq, std::uint64_t t_ms, const SE3d& T_w_c, bool facing_panel,
                    int shown) {
      last_pts_w.clear();
      last_desc.clear();
      for (int i = 0; i < shown; ++i) {
        const auto k = static_cast<std::size_t>(i);
        last_pts_w.push_back(T_w_c *
                             (facing_panel ? panel[k] : Eigen::Vector3d(px(rng), py(rng), 3.0)));
        features::Descriptor d = facing_panel ? panel_desc[k] : random_desc();
        if (facing_panel && seq > 7) d[0] ^= 0x11ULL;  // another view's noise
        last_desc.push_back(d);
      }
      const map::KeyframeId id =
          scene::add_view(map, K, T_w_c, T_w_c, last_pts_w, last_desc, seq, t_ms);
      last_points.clear();
      for (std::size_t i = 0; i < last_pts_w.size(); ++i) {
        const auto p = map.add_point(last_pts_w[i], id, static_cast<std::uint32_t>(i));
        EXPECT_TRUE(p.is_ok());
        last_points.push_back(p.is_ok() ? p.value() : map::kNoId);
      }
      return id;
    };
    const auto at = [](double x, double z) { return SE3d(Eigen::Translation3d(x, 0.0, z)); };
    a = view(0, 0, at(-4.0 * kPeriod, 0.0), true, kPanelPoints);
    c = view(1, 1000, at(kPeriod, 0.0), true, kPanelPoints);
    // The detour: 25 m back from the wall, 10 m along, 25 m forward again.
    const std::array<Eigen::Vector2d, 6> detour{{{kPeriod, -12.5},
                                                 {kPeriod, -25.0},
                                                 {2.0 * kPeriod, -25.0},
                                                 {3.0 * kPeriod, -25.0},
                                                 {3.0 * kPeriod, -15.0},
                                                 {3.0 * kPeriod, -5.0}}};
    std::uint64_t seq = 2;
    for (const Eigen::Vector2d& xz : detour) {
      (void)view(seq, 1000 + 200 * seq, at(xz.x(), xz.y()), false, kPanelPoints);
      ++seq;
    }
    const map::KeyframeId b0 = view(seq, 5900, at(3.0 * kPeriod, 0.0), true, kPanelPoints);
    (void)b0;
    b = scene::add_view(map, K, at(3.0 * kPeriod + 0.05, 0.0), at(3.0 * kPeriod + 0.05, 0.0),
                        last_pts_w, last_desc, seq + 1, 6000);
    for (std::size_t i = 0; i < last_points.size(); ++i) {
      EXPECT_TRUE(map.add_observation(last_points[i], b, static_cast<std::uint32_t>(i)));
    }
    map.update_covisibility(b);
  }
};

TEST(LoopCloser, AmbiguousPlaceIsRefusedWhenALookAlikeElsewhereIsAsStrong) {
  for (const double ratio : {0.0, 0.5}) {
    RepeatedPanelsScene scene;
    LoopOptions o;
    o.min_keyframe_gap = 2;
    o.ambiguity_ratio = ratio;
    LoopCloser closer(o, scene.map, {1.0F}, false, nullptr);
    const LoopReport r = closer.spin_once(scene.b, scene.K);
    std::printf(
        "repeated panels, ambiguity_ratio %.1f: closed %d (onto %s, %d inliers), "
        "look-alike %d inliers, drift refusals %d, ambiguous %d\n",
        ratio, r.closed ? 1 : 0, r.loop_keyframe == scene.c ? "C" : "other", r.inliers,
        r.lookalike_inliers, r.refused_drift, r.refused_ambiguous);
    // A's similarity passes every check but the drift bound: a look-alike of B's view.
    EXPECT_GE(r.refused_drift, 1);
    EXPECT_GE(r.lookalike_inliers, RepeatedPanelsScene::kPanelPoints - 9);
    if (ratio == 0.0) {
      // Unchecked, C's copy of the panel closes a loop 10 m off.
      ASSERT_TRUE(r.closed);
      EXPECT_EQ(r.loop_keyframe, scene.c);
      EXPECT_EQ(r.rival_inliers, 0);
    } else {
      EXPECT_FALSE(r.closed);
      EXPECT_EQ(r.refused_ambiguous, 1);
      EXPECT_EQ(closer.totals().rejected.ambiguous, 1U);
    }
  }
  // A true loop without a look-alike closes with the check on (the default).
  ASSERT_GT(LoopOptions{}.ambiguity_ratio, 0.0);
  const LoopReport r = close_true_loop(LoopOptions{});
  EXPECT_TRUE(r.closed);
  EXPECT_EQ(r.refused_ambiguous, 0);
}

// A straight drive past panels repeating every 5 m (a road's identical facades): a keyframe
// every 2.5 m, every second one facing a panel, all of them exact. Each panel view matches
// every panel seen before, by a similarity that puts the camera back where that one was:
// look-alikes, which the drift bound refuses (the correction is the whole path since). The
// drive never comes back, so no loop may close.
TEST(LoopCloser, AStraightDrivePastRepeatedPanelsClosesNoLoop) {
  constexpr int kPanelPoints = 90;
  constexpr int kKeyframes = 24;  // 57.5 m
  map::MapOptions mo = LoopScene::options();
  mo.max_keyframes = 32;
  mo.max_points = 4096;
  map::Map map(mo);
  const geometry::Pinhole K{400.0, 400.0, 320.0, 240.0};
  std::mt19937_64 rng(9);
  std::uniform_real_distribution<double> px(-1.2, 1.2);
  std::uniform_real_distribution<double> py(-0.9, 0.9);
  std::vector<Eigen::Vector3d> panel;
  std::vector<features::Descriptor> panel_desc;
  for (int i = 0; i < kPanelPoints; ++i) {
    panel.emplace_back(px(rng), py(rng), 3.0);
    panel_desc.push_back({rng(), rng(), rng(), rng()});
  }
  LoopOptions o;
  o.min_keyframe_gap = 2;
  LoopCloser closer(o, map, {1.0F}, false, nullptr);
  int closed = 0;
  int refused_drift = 0;
  for (int k = 0; k < kKeyframes; ++k) {
    const SE3d T_w_c(Eigen::Translation3d(2.5 * k, 0.0, 0.0));
    std::vector<Eigen::Vector3d> pts_w;
    std::vector<features::Descriptor> desc;
    for (int i = 0; i < kPanelPoints; ++i) {
      const auto u = static_cast<std::size_t>(i);
      const bool facing_panel = k % 2 == 0;
      pts_w.push_back(T_w_c * (facing_panel ? panel[u] : Eigen::Vector3d(px(rng), py(rng), 3.0)));
      features::Descriptor d =
          facing_panel ? panel_desc[u] : features::Descriptor{rng(), rng(), rng(), rng()};
      if (facing_panel) d[static_cast<std::size_t>(k / 2) % 4] ^= 0x101ULL;  // view noise
      desc.push_back(d);
    }
    const auto seq = static_cast<std::uint64_t>(k);
    const map::KeyframeId kf = scene::add_view(map, K, T_w_c, T_w_c, pts_w, desc, seq, 500 * seq);
    for (std::size_t i = 0; i < pts_w.size(); ++i) {
      ASSERT_TRUE(map.add_point(pts_w[i], kf, static_cast<std::uint32_t>(i)).is_ok());
    }
    const LoopReport r = closer.spin_once(kf, K);
    closed += r.closed ? 1 : 0;
    refused_drift += r.refused_drift;
  }
  std::printf(
      "straight drive past repeated panels: %d loops closed, %d look-alikes refused by "
      "the drift bound\n",
      closed, refused_drift);
  EXPECT_EQ(closed, 0);
  EXPECT_EQ(closer.totals().loops_closed, 0U);
  // The look-alikes were found and refused, not missed.
  EXPECT_GT(refused_drift, 0);
}

// A drift-refused match onto the loop's own place is no look-alike of it. A and A2 see one
// place from the same pose (A2 observes A's points, made after a detour); B sees it again
// later from a drifted pose (LoopScene's drift). Onto A the correction is 3 % of the 8 m
// path since A: a loop. Onto A2 it is most of the 0.3 m since A2: refused by the drift bound,
// with as many inliers. Counted as a rival, A2 would refuse the loop onto A.
TEST(LoopCloser, ADriftRefusedMatchOntoTheLoopsOwnPlaceIsNoRival) {
  map::MapOptions mo = LoopScene::options();
  mo.max_points = 1024;
  map::Map map(mo);
  const geometry::Pinhole K{400.0, 400.0, 320.0, 240.0};
  std::mt19937_64 rng(13);
  std::uniform_real_distribution<double> ux(-1.5, 1.5);
  std::uniform_real_distribution<double> uy(-1.0, 1.0);
  std::uniform_real_distribution<double> uz(2.0, 4.0);
  std::vector<Eigen::Vector3d> pts;
  std::vector<features::Descriptor> desc;
  for (int i = 0; i < LoopScene::kPoints; ++i) {
    pts.emplace_back(ux(rng), uy(rng), uz(rng));
    desc.push_back({rng(), rng(), rng(), rng()});
  }
  const auto elsewhere = [&] {
    std::vector<features::Descriptor> other;
    for (int i = 0; i < LoopScene::kPoints; ++i) other.push_back({rng(), rng(), rng(), rng()});
    return other;
  };
  const auto at = [](double x) { return SE3d(Eigen::Translation3d(x, 0.0, 0.0)); };
  const map::KeyframeId a = scene::add_view(map, K, at(0.0), at(0.0), pts, desc, 0, 0);
  std::vector<map::PointId> a_points;
  for (int i = 0; i < LoopScene::kPoints; ++i) {
    const auto pr =
        map.add_point(pts[static_cast<std::size_t>(i)], a, static_cast<std::uint32_t>(i));
    ASSERT_TRUE(pr.is_ok());
    a_points.push_back(pr.value());
  }
  std::uint64_t seq = 1;
  for (const double x : {1.0, 2.0, 3.0, 4.0}) {  // out and back: 8 m
    (void)scene::add_view(map, K, at(x), at(x), pts, elsewhere(), seq, 1000 * seq);
    ++seq;
  }
  const map::KeyframeId a2 = scene::add_view(map, K, at(0.0), at(0.0), pts, desc, seq, 4900);
  for (std::size_t i = 0; i < a_points.size(); ++i) {
    ASSERT_TRUE(map.add_observation(a_points[i], a2, static_cast<std::uint32_t>(i)));
  }
  map.update_covisibility(a2);
  ++seq;
  for (const double x : {0.1, 0.2}) {  // two keyframes looking elsewhere, 10 cm apart
    (void)scene::add_view(map, K, at(x), at(x), pts, elsewhere(), seq, 5000 + 1000 * (seq - 5));
    ++seq;
  }
  // B: truly 10 cm from A, stored with LoopScene's drift (yaw 3 deg, a shift, scale 1.04).
  const geometry::Sim3d S = LoopScene::drift(LoopScene::kDrift);
  const SE3d T_w_b_true = at(LoopScene::kBaseline);
  const SE3d T_w_b = LoopScene::drifted(S, T_w_b_true);
  std::vector<features::Descriptor> desc_b = desc;
  for (features::Descriptor& d : desc_b) d[0] ^= 0x11ULL;
  const map::KeyframeId b = scene::add_view(map, K, T_w_b_true, T_w_b, pts, desc_b, seq, 9000);
  for (int i = 0; i < LoopScene::kPoints; ++i) {
    ASSERT_TRUE(
        map.add_point(S * pts[static_cast<std::size_t>(i)], b, static_cast<std::uint32_t>(i))
            .is_ok());
  }
  LoopOptions o;
  o.min_keyframe_gap = 2;
  LoopCloser closer(o, map, {1.0F}, false, nullptr);
  const LoopReport r = closer.spin_once(b, K);
  std::printf(
      "own place: closed %d onto %s, drift refusals %d, look-alike %d inliers, "
      "ambiguous %d\n",
      r.closed ? 1 : 0, r.loop_keyframe == a ? "A" : "other", r.refused_drift, r.lookalike_inliers,
      r.refused_ambiguous);
  EXPECT_GE(r.refused_drift, 1);  // onto A2
  EXPECT_GT(r.lookalike_inliers, 0);
  EXPECT_TRUE(r.closed);
  EXPECT_EQ(r.loop_keyframe, a);
  EXPECT_EQ(r.refused_ambiguous, 0);
}

}  // namespace
}  // namespace mer::loop
