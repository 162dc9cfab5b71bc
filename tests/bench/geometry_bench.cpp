// Absolute-pose benchmarks: P3P and PnpRansac::solve() at tracking-thread sizes
// (300 correspondences, 30 % outliers, 1 px noise) on one core.
#include <cmath>
#include <random>
#include <vector>

#include <benchmark/benchmark.h>

#include "geometry/p3p.h"
#include "geometry/pnp.h"

namespace mer::geometry {
namespace {

const Pinhole kK{500.0, 500.0, 320.0, 240.0};
constexpr double kWidth = 640.0;
constexpr double kHeight = 480.0;

struct Problem {
  SE3d T_c_w;
  std::vector<Eigen::Vector3d> points_w;
  std::vector<Eigen::Vector2d> uv;
  std::vector<float> sigma;
};

// Points at 2..8 m over the whole image; the first `outlier_ratio` share gets uniform
// random pixels; observation noise 1 px x sigma (sigma = 1.2^level, levels 0..3).
Problem make_problem(std::uint64_t seed, int n, double outlier_ratio) {
  std::mt19937_64 gen(seed);
  std::normal_distribution<double> n01(0.0, 1.0);
  std::uniform_real_distribution<double> u01(0.0, 1.0);
  Problem p;
  SE3d T_w_c = SE3d::Identity();
  T_w_c.linear() =
      Eigen::Quaterniond(n01(gen), n01(gen), n01(gen), n01(gen)).normalized().toRotationMatrix();
  T_w_c.translation() = Eigen::Vector3d(n01(gen), n01(gen), n01(gen));
  p.T_c_w = T_w_c.inverse();
  for (int i = 0; i < n; ++i) {
    const Eigen::Vector2d px(u01(gen) * kWidth, u01(gen) * kHeight);
    const double z = 2.0 + 6.0 * u01(gen);
    p.points_w.push_back(T_w_c * (kK.unproject(px) * z));
    const double sig = std::pow(1.2, static_cast<int>(u01(gen) * 4));
    p.sigma.push_back(static_cast<float>(sig));
    if (u01(gen) < outlier_ratio) {
      p.uv.emplace_back(u01(gen) * kWidth, u01(gen) * kHeight);
    } else {
      p.uv.push_back(px + sig * Eigen::Vector2d(n01(gen), n01(gen)));
    }
  }
  return p;
}

// args: correspondences, outlier percentage, use the true pose as prior (0/1).
void bm_pnp_solve(benchmark::State& state) {
  const int n = static_cast<int>(state.range(0));
  const double outliers = static_cast<double>(state.range(1)) / 100.0;
  const bool use_prior = state.range(2) != 0;
  constexpr int kProblems = 16;
  std::vector<Problem> problems;
  for (int k = 0; k < kProblems; ++k) problems.push_back(make_problem(k + 1, n, outliers));
  PnpRansac pnp(PnpOptions{}, static_cast<std::size_t>(n));
  std::vector<std::uint8_t> mask(static_cast<std::size_t>(n));
  std::size_t k = 0;
  int failures = 0;
  for (auto _ : state) {
    const Problem& p = problems[k++ % kProblems];
    const PnpInput in{p.points_w, p.uv, p.sigma, kK};
    const PnpResult r = pnp.solve(in, mask, use_prior ? &p.T_c_w : nullptr);
    failures += r.ok ? 0 : 1;
    benchmark::DoNotOptimize(r);
  }
  if (failures > 0) state.SkipWithError("PnP failed");
  state.SetItemsProcessed(state.iterations());
}
BENCHMARK(bm_pnp_solve)
    ->Args({300, 30, 0})
    ->Args({300, 30, 1})
    ->Args({100, 30, 0})
    ->Args({600, 30, 0})
    ->Args({300, 50, 0})
    ->Unit(benchmark::kMicrosecond);

void bm_pnp_solve_with_focal(benchmark::State& state) {
  const Problem p = make_problem(3, 300, 0.2);
  PnpRansac pnp(PnpOptions{}, 300);
  std::vector<std::uint8_t> mask(300);
  const PnpInput in{p.points_w, p.uv, p.sigma, kK.with_focal(350.0)};
  for (auto _ : state) benchmark::DoNotOptimize(pnp.solve_with_focal(in, mask));
}
BENCHMARK(bm_pnp_solve_with_focal)->Unit(benchmark::kMicrosecond);

void bm_p3p(benchmark::State& state) {
  const Problem p = make_problem(5, 3, 0.0);
  std::array<Eigen::Vector3d, 3> y;
  std::array<Eigen::Vector3d, 3> X;
  for (int i = 0; i < 3; ++i) {
    y[i] = (p.T_c_w * p.points_w[i]).normalized();
    X[i] = p.points_w[i];
  }
  std::array<SE3d, kMaxP3pSolutions> sols;
  for (auto _ : state) {
    benchmark::DoNotOptimize(solve_p3p(y, X, sols));
    benchmark::ClobberMemory();
  }
}
BENCHMARK(bm_p3p)->Unit(benchmark::kNanosecond);

}  // namespace
}  // namespace mer::geometry

BENCHMARK_MAIN();
