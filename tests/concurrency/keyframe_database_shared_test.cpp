// One keyframe database shared by loop closure (back-end thread) and relocalization (depth
// thread) under its lock, as the threaded pipeline wires them.
#include <array>
#include <atomic>
#include <mutex>
#include <random>
#include <thread>

#include <gtest/gtest.h>

#include "loop/keyframe_database.h"
#include "unit/loop/synthetic_map.h"

namespace mer::loop {
namespace {

struct Orbit {
  scene::OrbitWorld world;
  map::Map map{scene::OrbitWorld::map_options()};
  std::mt19937_64 rng{11};
  std::vector<map::KeyframeId> ids;
  explicit Orbit(int count, double step) { ids = world.build(map, 0.0, step, count, rng); }
};

// Loop closure (refresh + scoring, reading the scores) and relocalization (refresh_live +
// query) on two threads share one database under its lock: every query answers as it does
// alone (CI runs this under TSan).
TEST(KeyframeDatabase, TwoThreadsShareOneDatabaseUnderItsLock) {
  Orbit o(18, 20.0);
  KeyframeDatabase db(o.map);
  std::mt19937_64 rng(5);
  const scene::View v = o.world.observe(scene::OrbitWorld::pose(45.0), rng);
  std::array<RetrievalHit, 5> alone{};
  std::size_t n_alone = 0;
  {
    const std::lock_guard<platform::PiMutex> lock(db.mutex());
    db.refresh_live();
    n_alone = db.query(v.descriptors, alone);
  }
  ASSERT_GT(n_alone, 0U);
  std::atomic<bool> stop{false};
  std::atomic<int> differing{0};
  std::thread relocalizer([&] {
    std::array<RetrievalHit, 5> top{};
    for (int i = 0; i < 200; ++i) {
      const std::lock_guard<platform::PiMutex> lock(db.mutex());
      db.refresh_live();
      const std::size_t n = db.query(v.descriptors, top);
      if (n != n_alone || top[0].id != alone[0].id) differing.fetch_add(1);
    }
    stop.store(true);
  });
  double sink = 0.0;
  for (std::size_t k = 0; !stop.load(); k = (k + 1) % o.ids.size()) {
    const std::lock_guard<platform::PiMutex> lock(db.mutex());
    (void)db.refresh(o.ids[k]);
    const std::span<const double> scores = db.score_keyframe(o.ids[k]);
    for (const double s : scores) sink += s;
  }
  relocalizer.join();
  EXPECT_EQ(differing.load(), 0);
  EXPECT_GT(sink, 0.0);
}

}  // namespace
}  // namespace mer::loop
