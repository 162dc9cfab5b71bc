// Keyframe database: the inverted index scores exactly what a merge of two sorted key lists
// scores (loop closure's retrieval before the index, bit for bit), ranks the keyframe a
// revisit sees in its top 3, forgets culled keyframes, and queries without allocating.
#include "loop/keyframe_database.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <random>
#include <vector>

#include <gtest/gtest.h>

#include "platform/alloc_counter.h"
#include "synthetic_map.h"

namespace mer::loop {
namespace {

// The score of the file comment computed directly: merge of the two slots' sorted keys.
double merged_score(const KeyframeDatabase& db, map::KeyframeId a, map::KeyframeId b) {
  double shared = 0.0;
  const double n = std::max(1.0, static_cast<double>(db.size()));
  for (int t = 0; t < kKeyTables; ++t) {
    const auto x = db.keys(a, t);
    const auto y = db.keys(b, t);
    std::size_t i = 0;
    std::size_t j = 0;
    while (i < x.size() && j < y.size()) {
      if (x[i] < y[j]) {
        ++i;
      } else if (y[j] < x[i]) {
        ++j;
      } else {
        shared += std::log(n / std::max(1.0, static_cast<double>(db.key_frequency(t, x[i]))));
        ++i;
        ++j;
      }
    }
  }
  return shared;
}

struct Orbit {
  scene::OrbitWorld world;
  map::Map map{scene::OrbitWorld::map_options()};
  std::mt19937_64 rng{11};
  std::vector<map::KeyframeId> ids;
  // 36 keyframes, one every 10 degrees, all the way round.
  explicit Orbit(int count = 36, double step = 10.0) {
    ids = world.build(map, 0.0, step, count, rng);
  }
};

TEST(KeyframeDatabase, IndexScoresEqualTheSortedListMerge) {
  Orbit o;
  KeyframeDatabase db(o.map);
  db.refresh_live();
  ASSERT_EQ(db.size(), o.ids.size());
  for (const map::KeyframeId a : {o.ids[0], o.ids[7], o.ids[20]}) {
    const std::span<const double> s = db.score_keyframe(a);
    ASSERT_GE(s.size(), o.ids.size());
    int nonzero = 0;
    for (const map::KeyframeId b : o.ids) {
      EXPECT_EQ(s[b], merged_score(db, a, b)) << a << " vs " << b;  // bit for bit
      nonzero += s[b] > 0.0 ? 1 : 0;
    }
    EXPECT_GE(nonzero, 7);  // its overlapping neighbours at least
  }
}

TEST(KeyframeDatabase, RevisitRanksTheTrueKeyframeInTopThree) {
  Orbit o;
  KeyframeDatabase db(o.map);
  db.refresh_live();
  std::mt19937_64 rng(5);
  int found = 0;
  int first = 0;
  int cases = 0;
  // Revisits between keyframes, 3-4 degrees and a few cm off the nearest one, new noise.
  for (int k = 1; k < 36; k += 3) {
    const double deg = 10.0 * k + (k % 2 == 0 ? 3.0 : -4.0);
    const scene::View v = o.world.observe(scene::OrbitWorld::pose(deg, 0.05), rng);
    std::array<RetrievalHit, 3> top{};
    const std::size_t n = db.query(v.descriptors, top);
    ++cases;
    const map::KeyframeId truth = o.ids[static_cast<std::size_t>(k)];
    bool in_top = false;
    for (std::size_t i = 0; i < n; ++i) in_top = in_top || top[i].id == truth;
    found += in_top ? 1 : 0;
    first += (n > 0 && top[0].id == truth) ? 1 : 0;
    ASSERT_GT(n, 0U);
    for (std::size_t i = 1; i < n; ++i) EXPECT_GE(top[i - 1].score, top[i].score);
  }
  std::printf("revisits: true keyframe in top 3: %d / %d, first: %d / %d\n", found, cases, first,
              cases);
  EXPECT_EQ(found, cases);
  EXPECT_GE(first, cases * 3 / 4);
}

TEST(KeyframeDatabase, CulledKeyframesAreNotReturnedAndReusedSlotsAreRekeyed) {
  Orbit o(12, 30.0);
  KeyframeDatabase db(o.map);
  db.refresh_live();
  std::mt19937_64 rng(9);
  const scene::View v = o.world.observe(scene::OrbitWorld::pose(90.0), rng);
  std::array<RetrievalHit, 3> top{};
  ASSERT_GT(db.query(v.descriptors, top), 0U);
  const map::KeyframeId culled = top[0].id;
  ASSERT_EQ(culled, o.ids[3]);
  ASSERT_TRUE(o.map.remove_keyframe(culled, 1));
  EXPECT_FALSE(db.contains(culled));
  const std::size_t n = db.query(v.descriptors, top);
  for (std::size_t i = 0; i < n; ++i) EXPECT_NE(top[i].id, culled);
  // Explicit removal drops the slot's share of the key frequencies.
  const std::uint32_t keyed = db.size();
  db.remove(culled);
  EXPECT_EQ(db.size(), keyed - 1);
  EXPECT_TRUE(db.keys(culled, 0).empty());
  EXPECT_FALSE(db.refresh(culled));  // not live: nothing to key
}

TEST(KeyframeDatabase, QueryDoesNotAllocate) {
  if (!platform::alloc::counter_linked()) GTEST_SKIP() << "allocation counter not linked";
  Orbit o(18, 20.0);
  KeyframeDatabase db(o.map);
  db.refresh_live();
  std::mt19937_64 rng(2);
  const scene::View v = o.world.observe(scene::OrbitWorld::pose(45.0), rng);
  std::array<RetrievalHit, 5> top{};
  (void)db.query(v.descriptors, top);
  const std::uint64_t before = platform::alloc::thread_allocations();
  const std::size_t n = db.query(v.descriptors, top);
  db.refresh_live();
  (void)db.score_keyframe(o.ids[2]);
  EXPECT_EQ(platform::alloc::thread_allocations() - before, 0U);
  EXPECT_GT(n, 0U);
}

// The storage at the map's default capacities (400 keyframes x 1500 keypoints) is the figure
// the file comment and docs/relocalization.md give: one instance, shared by loop closure and
// relocalization.
TEST(KeyframeDatabase, MemoryAtTheDefaultsIsTheDocumentedFigure) {
  const map::Map map{map::MapOptions{}};
  const KeyframeDatabase db(map);
  const double mib = static_cast<double>(db.memory_bytes()) / (1024.0 * 1024.0);
  std::printf("keyframe database: %.2f MiB at the defaults\n", mib);
  EXPECT_NEAR(mib, 20.2, 0.05);
}

}  // namespace
}  // namespace mer::loop
