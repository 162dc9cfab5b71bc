// Analytic Jacobians of the back-end residuals against central differences taken through
// the rotation manifold's Plus (so the check covers the [I3; 0] convention of the file).
#include "backend/ba_residuals.h"

#include <array>
#include <atomic>
#include <initializer_list>
#include <random>
#include <vector>

#include <Eigen/Geometry>
#include <gtest/gtest.h>

namespace mer::backend {
namespace {

constexpr double kStep = 1e-6;
const geometry::Pinhole kK{450.0, 460.0, 319.5, 239.5};

struct State {
  std::array<double, 4> q{};
  std::array<double, 3> t{};
  std::array<double, 3> X{};
  std::array<double, 1> s{1.1};
};

State random_state(std::mt19937& rng) {
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  State st;
  const Eigen::Quaterniond q = Eigen::Quaterniond(
      Eigen::AngleAxisd(0.7 * u(rng), Eigen::Vector3d(u(rng), u(rng), u(rng)).normalized()));
  st.q = {q.x(), q.y(), q.z(), q.w()};
  st.t = {0.3 * u(rng), 0.3 * u(rng), 0.5 * u(rng)};
  // A point in front of the camera: choose it in the camera, map it to the world.
  const Eigen::Vector3d p_c(u(rng), 0.7 * u(rng), 3.0 + u(rng));
  const Eigen::Vector3d X = q.conjugate() * (p_c - Eigen::Vector3d(st.t[0], st.t[1], st.t[2]));
  st.X = {X.x(), X.y(), X.z()};
  return st;
}

// Residual of `cost` at `st`, with `delta` (tangent size) added to block `b`.
template <int N>
Eigen::Matrix<double, N, 1> eval(const ceres::CostFunction& cost, State st, int b,
                                 const Eigen::VectorXd& delta) {
  RotationManifold m;
  if (b == 0) {
    std::array<double, 4> q2{};
    m.Plus(st.q.data(), delta.data(), q2.data());
    st.q = q2;
  } else {
    double* blk = b == 1 ? st.t.data() : b == 2 ? st.X.data() : st.s.data();
    for (int i = 0; i < delta.size(); ++i) blk[i] += delta[i];
  }
  std::vector<const double*> params{st.q.data(), st.t.data(), st.X.data(), st.s.data()};
  Eigen::Matrix<double, N, 1> r;
  EXPECT_TRUE(cost.Evaluate(params.data(), r.data(), nullptr));
  return r;
}

// Compares the tangent Jacobians (ambient Jacobian times PlusJacobian for the rotation).
template <int N>
void check(const ceres::CostFunction& cost, const State& st) {
  const int nb = static_cast<int>(cost.parameter_block_sizes().size());
  std::vector<const double*> params{st.q.data(), st.t.data(), st.X.data(), st.s.data()};
  Eigen::Matrix<double, N, 1> r;
  std::vector<std::vector<double>> J(static_cast<std::size_t>(nb));
  std::vector<double*> Jp;
  for (int b = 0; b < nb; ++b) {
    J[static_cast<std::size_t>(b)].resize(
        static_cast<std::size_t>(N * cost.parameter_block_sizes()[static_cast<std::size_t>(b)]));
    Jp.push_back(J[static_cast<std::size_t>(b)].data());
  }
  ASSERT_TRUE(cost.Evaluate(params.data(), r.data(), Jp.data()));
  RotationManifold m;
  for (int b = 0; b < nb; ++b) {
    const int ambient = cost.parameter_block_sizes()[static_cast<std::size_t>(b)];
    const int tangent = b == 0 ? 3 : ambient;
    Eigen::MatrixXd Ja =
        Eigen::Map<Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>>(
            Jp[static_cast<std::size_t>(b)], N, ambient);
    Eigen::MatrixXd Jt = Ja;
    if (b == 0) {
      Eigen::Matrix<double, 4, 3, Eigen::RowMajor> P;
      m.PlusJacobian(st.q.data(), P.data());
      Jt = Ja * P;
    }
    for (int k = 0; k < tangent; ++k) {
      Eigen::VectorXd d = Eigen::VectorXd::Zero(tangent);
      d[k] = kStep;
      const Eigen::Matrix<double, N, 1> num =
          (eval<N>(cost, st, b, d) - eval<N>(cost, st, b, -d)) / (2.0 * kStep);
      for (int i = 0; i < N; ++i) {
        EXPECT_NEAR(Jt(i, k), num[i], 1e-5 * (1.0 + std::abs(num[i])))
            << "block " << b << " column " << k << " row " << i;
      }
    }
  }
}

TEST(BaResiduals, ReprojectionJacobiansMatchNumeric) {
  std::mt19937 rng(3);
  for (int trial = 0; trial < 20; ++trial) {
    const State st = random_state(rng);
    const ReprojectionCost cost(300.0, 200.0, 1.0 / 1.2, kK);
    check<2>(cost, st);
  }
}

TEST(BaResiduals, DepthJacobiansMatchNumeric) {
  std::mt19937 rng(4);
  for (int trial = 0; trial < 20; ++trial) {
    const State st = random_state(rng);
    const DepthCost cost(2.7, 1.0 / 0.03);
    check<2>(cost, st);  // the second row is zero (one row-block size for Ceres' Schur solver)
  }
}

// Once the abort flag is set a cost-only evaluation fails (Ceres rejects the step) and a
// Jacobian evaluation succeeds with zeros (finite: Ceres checks them), see ba_residuals.h.
TEST(BaResiduals, AbortFailsCostOnlyAndZeroesJacobianEvaluations) {
  std::mt19937 rng(5);
  const State st = random_state(rng);
  std::atomic<bool> abort{false};
  const ReprojectionCost reprojection(300.0, 200.0, 1.0, kK, &abort);
  const DepthCost depth(2.7, 1.0 / 0.03, &abort);
  const std::vector<const double*> params{st.q.data(), st.t.data(), st.X.data(), st.s.data()};
  for (const ceres::CostFunction* cost :
       std::initializer_list<const ceres::CostFunction*>{&reprojection, &depth}) {
    std::array<double, 2> r{};
    abort.store(false);
    EXPECT_TRUE(cost->Evaluate(params.data(), r.data(), nullptr));
    abort.store(true);
    EXPECT_FALSE(cost->Evaluate(params.data(), r.data(), nullptr));
    std::vector<std::vector<double>> J;
    std::vector<double*> Jp;
    for (const int size : cost->parameter_block_sizes()) {
      J.emplace_back(static_cast<std::size_t>(2 * size), 1.0);
      Jp.push_back(J.back().data());
    }
    r = {1.0, 1.0};
    EXPECT_TRUE(cost->Evaluate(params.data(), r.data(), Jp.data()));
    EXPECT_EQ(r[0], 0.0);
    EXPECT_EQ(r[1], 0.0);
    for (const auto& block : J) {
      for (const double v : block) EXPECT_EQ(v, 0.0);
    }
  }
}

TEST(BaResiduals, ManifoldPlusMinusRoundTrip) {
  RotationManifold m;
  const Eigen::Quaterniond q(Eigen::AngleAxisd(0.4, Eigen::Vector3d(1, 2, 3).normalized()));
  const std::array<double, 4> x{q.x(), q.y(), q.z(), q.w()};
  const std::array<double, 3> delta{0.01, -0.02, 0.03};
  std::array<double, 4> y{};
  ASSERT_TRUE(m.Plus(x.data(), delta.data(), y.data()));
  std::array<double, 3> back{};
  ASSERT_TRUE(m.Minus(y.data(), x.data(), back.data()));
  for (int i = 0; i < 3; ++i)
    EXPECT_NEAR(back[static_cast<std::size_t>(i)], delta[static_cast<std::size_t>(i)], 1e-12);
  // Plus is a left perturbation: R(y) = Exp(delta) R(x).
  const Eigen::Matrix3d Ry = Eigen::Map<const Eigen::Quaterniond>(y.data()).toRotationMatrix();
  const Eigen::Matrix3d Rx = q.toRotationMatrix();
  const Eigen::Matrix3d E = Eigen::AngleAxisd(Eigen::Vector3d(0.01, -0.02, 0.03).norm(),
                                              Eigen::Vector3d(0.01, -0.02, 0.03).normalized())
                                .toRotationMatrix();
  EXPECT_LT((Ry - E * Rx).norm(), 1e-12);
}

}  // namespace
}  // namespace mer::backend
