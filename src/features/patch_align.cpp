#include "features/patch_align.h"

#include <algorithm>
#include <cmath>

#include <Eigen/Dense>

namespace mer::features {

namespace {

constexpr float kWarpCentre = 0.5F * static_cast<float>(kWarpSide - 1);  // 4.5
constexpr float kMinTextureDet = 1e-3F;  // smallest normalized gradient determinant aligned

// Bilinear sample of a CV_8UC1 image at (x, y); the caller checks the bounds.
inline float bilinear(const cv::Mat& img, float x, float y) {
  const int x0 = static_cast<int>(std::floor(x));
  const int y0 = static_cast<int>(std::floor(y));
  const float ax = x - static_cast<float>(x0);
  const float ay = y - static_cast<float>(y0);
  const std::uint8_t* r0 = img.ptr<std::uint8_t>(y0) + x0;
  const std::uint8_t* r1 = img.ptr<std::uint8_t>(y0 + 1) + x0;
  return (1.0F - ay) * ((1.0F - ax) * r0[0] + ax * r0[1]) + ay * ((1.0F - ax) * r1[0] + ax * r1[1]);
}

// Whether a bilinear sample at every point of [x0, x1] x [y0, y1] stays inside the image.
inline bool inside(const cv::Mat& img, float x0, float y0, float x1, float y1) {
  return x0 >= 0.0F && y0 >= 0.0F && x1 < static_cast<float>(img.cols - 1) &&
         y1 < static_cast<float>(img.rows - 1);
}

}  // namespace

bool sample_anchor_patch(const cv::Mat& img, float x, float y, AnchorPixels& out,
                         Eigen::Vector2f& centre) {
  if (img.empty() || img.type() != CV_8UC1 || !std::isfinite(x) || !std::isfinite(y)) return false;
  constexpr int kHalfSide = kAnchorSide / 2;
  const int x0 = static_cast<int>(std::lround(x)) - kHalfSide;
  const int y0 = static_cast<int>(std::lround(y)) - kHalfSide;
  if (x0 < 0 || y0 < 0 || x0 + kAnchorSide > img.cols || y0 + kAnchorSide > img.rows) return false;
  for (int r = 0; r < kAnchorSide; ++r) {
    const std::uint8_t* row = img.ptr<std::uint8_t>(y0 + r) + x0;
    std::copy_n(row, kAnchorSide, out.begin() + static_cast<std::ptrdiff_t>(r * kAnchorSide));
  }
  centre = Eigen::Vector2f(x - static_cast<float>(x0), y - static_cast<float>(y0));
  return true;
}

bool warp_anchor_patch(const AnchorPixels& anchor, const Eigen::Vector2f& centre,
                       const Eigen::Matrix2f& M, WarpedPatch& out) {
  // The anchor as a 16x16 image for the bilinear sampler (no copy).
  // NOLINTNEXTLINE(cppcoreguidelines-pro-type-const-cast): cv::Mat has no const view
  const cv::Mat a(kAnchorSide, kAnchorSide, CV_8UC1, const_cast<std::uint8_t*>(anchor.data()));
  for (int r = 0; r < kWarpSide; ++r) {
    for (int c = 0; c < kWarpSide; ++c) {
      const Eigen::Vector2f m = centre + M * Eigen::Vector2f(static_cast<float>(c) - kWarpCentre,
                                                             static_cast<float>(r) - kWarpCentre);
      if (!inside(a, m.x(), m.y(), m.x(), m.y())) return false;
      out[static_cast<std::size_t>(r * kWarpSide + c)] = bilinear(a, m.x(), m.y());
    }
  }
  return true;
}

AlignResult align_patch(const cv::Mat& img, const WarpedPatch& ref, int max_iterations,
                        float tolerance_px, Eigen::Vector2f& uv) {
  AlignResult res;
  if (img.empty() || img.type() != CV_8UC1) return res;
  constexpr int kN = kAlignSide * kAlignSide;
  std::array<float, kN> gx{};
  std::array<float, kN> gy{};
  std::array<float, kN> tv{};
  Eigen::Matrix3f H = Eigen::Matrix3f::Zero();
  float mean_ref = 0.0F;
  for (int r = 0; r < kAlignSide; ++r) {
    for (int c = 0; c < kAlignSide; ++c) {
      const auto k = static_cast<std::size_t>(r * kAlignSide + c);
      const auto at = [&](int rr, int cc) {
        return ref[static_cast<std::size_t>(rr * kWarpSide + cc)];
      };
      gx[k] = 0.5F * (at(r + 1, c + 2) - at(r + 1, c));
      gy[k] = 0.5F * (at(r + 2, c + 1) - at(r, c + 1));
      tv[k] = at(r + 1, c + 1);
      mean_ref += tv[k];
      const Eigen::Vector3f J(gx[k], gy[k], 1.0F);
      H += J * J.transpose();
    }
  }
  mean_ref /= static_cast<float>(kN);
  // Texture: the gradient's second moment must not be (near) singular, relative to its size.
  const float tr = H(0, 0) + H(1, 1);
  const float det2 = H(0, 0) * H(1, 1) - H(0, 1) * H(1, 0);
  if (tr <= 0.0F || det2 < kMinTextureDet * tr * tr) return res;
  const Eigen::Matrix3f H_inv = H.inverse();
  constexpr float kHalf = 0.5F * static_cast<float>(kAlignSide - 1);  // 3.5
  Eigen::Vector2f p = uv;
  float bias = 0.0F;  // brightness offset: image - reference
  bool have_bias = false;
  for (int it = 0; it < max_iterations; ++it) {
    if (!inside(img, p.x() - kHalf, p.y() - kHalf, p.x() + kHalf, p.y() + kHalf)) return res;
    std::array<float, kN> cur{};
    float mean_cur = 0.0F;
    for (int r = 0; r < kAlignSide; ++r) {
      for (int c = 0; c < kAlignSide; ++c) {
        const auto k = static_cast<std::size_t>(r * kAlignSide + c);
        cur[k] = bilinear(img, p.x() + static_cast<float>(c) - kHalf,
                          p.y() + static_cast<float>(r) - kHalf);
        mean_cur += cur[k];
      }
    }
    if (!have_bias) {
      bias = mean_cur / static_cast<float>(kN) - mean_ref;
      have_bias = true;
    }
    Eigen::Vector3f b = Eigen::Vector3f::Zero();
    float ss = 0.0F;
    for (std::size_t k = 0; k < static_cast<std::size_t>(kN); ++k) {
      const float e = cur[k] - tv[k] - bias;
      ss += e * e;
      b += Eigen::Vector3f(gx[k], gy[k], 1.0F) * e;
    }
    res.rms = std::sqrt(ss / static_cast<float>(kN));
    const Eigen::Vector3f d = H_inv * b;
    // e ~ -grad(ref) . s for an image shifted by s from uv: d = -s.
    p -= d.head<2>();
    bias += d.z();
    res.iterations = it + 1;
    if (d.head<2>().squaredNorm() < tolerance_px * tolerance_px) {
      res.converged = true;
      break;
    }
  }
  if (res.converged) uv = p;
  return res;
}

}  // namespace mer::features
