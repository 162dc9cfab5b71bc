// The cost volume of the plane-sweep stereo (PlaneSweepStereo, plane_sweep.h): each source
// warped onto the reference's planes, ZNCC or census costs per row, SGM aggregation, and the
// depth and confidence chosen per pixel.
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>

#include <Eigen/Core>

#if defined(__SSE2__)
#include <emmintrin.h>
#endif

#include "depth/plane_sweep.h"
#include "depth/plane_sweep_internal.h"

namespace mer::depth {
namespace {

using plane_sweep_detail::kCostUnits;
using plane_sweep_detail::kNoCost;

// SGM: the out-of-range neighbours of plane 0 and plane P-1 (never the minimum).
constexpr std::int16_t kPathSentinel = 0x3FFF;
// Homogeneous z below this: the point is behind (or at) the source camera.
constexpr float kMinHomogeneousZ = 1e-6F;
// One SGM path step over all planes (Hirschmueller 2008):
//   L(d) = C(d) + min(Lp(d), Lp(d +- 1) + P1, min Lp + P2) - min Lp,
// accumulated into `sum`. `lp` and `l` point at plane 0 of buffers with a sentinel on both
// sides. Returns min_d L(d).
std::int16_t path_step(const std::int16_t* c, const std::int16_t* lp, std::int16_t min_prev,
                       std::int16_t p1, std::int16_t p2, std::int16_t* l, std::int16_t* sum,
                       int planes) {
  const auto jump = static_cast<std::int16_t>(min_prev + p2);
  std::int16_t m = kPathSentinel;
  for (int d = 0; d < planes; ++d) {
    auto v = std::min(lp[d], jump);
    v = std::min(v, static_cast<std::int16_t>(std::min(lp[d - 1], lp[d + 1]) + p1));
    const auto ld = static_cast<std::int16_t>(c[d] + v - min_prev);
    l[d] = ld;
    sum[d] = static_cast<std::int16_t>(sum[d] + ld);
    m = std::min(m, ld);
  }
  return m;
}

// First pixel of a path: L(d) = C(d).
std::int16_t path_start(const std::int16_t* c, std::int16_t* l, std::int16_t* sum, int planes) {
  std::int16_t m = kPathSentinel;
  for (int d = 0; d < planes; ++d) {
    l[d] = c[d];
    sum[d] = static_cast<std::int16_t>(sum[d] + c[d]);
    m = std::min(m, c[d]);
  }
  return m;
}

}  // namespace

std::size_t PlaneSweepStereo::ring_row(int yp) const {
  return static_cast<std::size_t>(yp % (2 * r_ + 1)) * static_cast<std::size_t>(wp_);
}

void PlaneSweepStereo::warp_row(const float* src, const SourceGeometry& g, float rho, int yp,
                                float* out, float* inside) {
  const auto& A = g.A;
  const auto max_x = static_cast<float>(w_ - 1);
  const auto max_y = static_cast<float>(h_ - 1);
  // Clamped sample positions keep (x0 + 1, y0 + 1) inside the image.
  const float clamp_x = std::nextafter(max_x, 0.0F);
  const float clamp_y = std::nextafter(max_y, 0.0F);
  const auto v = static_cast<float>(yp - r_);
  const float hx0 = A[1] * v + A[2] + rho * g.b[0];
  const float hy0 = A[4] * v + A[5] + rho * g.b[1];
  const float hz0 = A[7] * v + A[8] + rho * g.b[2];
  // Projection of the row (Eigen: explicitly vectorised), then bilinear weights.
  const Eigen::Map<const Eigen::ArrayXf> u(column_u_.data(), wp_);
  Eigen::Map<Eigen::ArrayXf> x(warp_ax_.data(), wp_);
  Eigen::Map<Eigen::ArrayXf> y(warp_ay_.data(), wp_);
  Eigen::Map<Eigen::ArrayXi> index(warp_index_.data(), wp_);
  Eigen::Map<Eigen::ArrayXi> y0(warp_y0_.data(), wp_);
  Eigen::Map<Eigen::ArrayXf> inv_z(warp_inv_z_.data(), wp_);
  inv_z = (hz0 + A[6] * u).max(kMinHomogeneousZ).inverse();
  x = (hx0 + A[0] * u) * inv_z;
  y = (hy0 + A[3] * u) * inv_z;
  {
    // Inside the source and in front of it (branch-free: the compiler vectorises this).
    const float* __restrict px = warp_ax_.data();
    const float* __restrict py = warp_ay_.data();
    const float* __restrict pu = column_u_.data();
    float* __restrict in = inside;
    for (int xp = 0; xp < wp_; ++xp) {
      const float hz = hz0 + A[6] * pu[xp];
      in[xp] = static_cast<float>((hz > kMinHomogeneousZ) & (px[xp] >= 0.0F) & (px[xp] <= max_x) &
                                  (py[xp] >= 0.0F) & (py[xp] <= max_y));
    }
  }
  x = x.max(0.0F).min(clamp_x);
  y = y.max(0.0F).min(clamp_y);
  index = x.cast<int>();
  y0 = y.cast<int>();
  x -= index.cast<float>();  // x, y: bilinear weights from here on
  y -= y0.cast<float>();
  index += y0 * w_;
  // Bilinear samples (border-clamped outside the source; those are flagged not inside).
  int xp = 0;
#if defined(__SSE2__)
  // Four pixels at a time: 64-bit loads of the (left, right) pairs of the top and bottom
  // rows, de-interleaved into left and right vectors, then vector lerps.
  for (; xp + 4 <= wp_; xp += 4) {
    const float* p0 = src + index[xp];
    const float* p1 = src + index[xp + 1];
    const float* p2 = src + index[xp + 2];
    const float* p3 = src + index[xp + 3];
    const auto pair = [](const float* a, const float* b) {
      return _mm_loadh_pi(_mm_loadl_pi(_mm_setzero_ps(), reinterpret_cast<const __m64*>(a)),
                          reinterpret_cast<const __m64*>(b));
    };
    const __m128 t01 = pair(p0, p1);
    const __m128 t23 = pair(p2, p3);
    const __m128 b01 = pair(p0 + w_, p1 + w_);
    const __m128 b23 = pair(p2 + w_, p3 + w_);
    const __m128 tl = _mm_shuffle_ps(t01, t23, _MM_SHUFFLE(2, 0, 2, 0));
    const __m128 tr = _mm_shuffle_ps(t01, t23, _MM_SHUFFLE(3, 1, 3, 1));
    const __m128 bl = _mm_shuffle_ps(b01, b23, _MM_SHUFFLE(2, 0, 2, 0));
    const __m128 br = _mm_shuffle_ps(b01, b23, _MM_SHUFFLE(3, 1, 3, 1));
    const __m128 wx = _mm_loadu_ps(&x[xp]);
    const __m128 wy = _mm_loadu_ps(&y[xp]);
    const __m128 top = _mm_add_ps(tl, _mm_mul_ps(wx, _mm_sub_ps(tr, tl)));
    const __m128 bottom = _mm_add_ps(bl, _mm_mul_ps(wx, _mm_sub_ps(br, bl)));
    _mm_storeu_ps(out + xp, _mm_add_ps(top, _mm_mul_ps(wy, _mm_sub_ps(bottom, top))));
  }
#endif
  for (; xp < wp_; ++xp) {
    const float* p = src + index[xp];
    const float top = p[0] + x[xp] * (p[1] - p[0]);
    const float bottom = p[w_] + x[xp] * (p[w_ + 1] - p[w_]);
    out[xp] = top + y[xp] * (bottom - top);
  }
}

void PlaneSweepStereo::cost_row_zncc(int y, float* cost) {
  using Row = Eigen::Map<Eigen::ArrayXf>;
  using ConstRow = Eigen::Map<const Eigen::ArrayXf>;
  const int side = 2 * r_ + 1;
  const auto n = static_cast<float>(side * side);
  const float inv_n = 1.0F / n;
  const float floor_n = n * static_cast<float>(opts_.zncc_variance_floor);
  Row va(sum_v_[0].data(), wp_);
  Row vb(sum_v_[1].data(), wp_);
  Row vc(sum_v_[2].data(), wp_);
  // Vertical window sums over the 2r+1 rows of the window (recomputed, not slid: a running
  // float sum would drift), two rows per pass.
  const auto ring_at = [&](const std::vector<float>& ring, int k) {
    return ConstRow(ring.data() + ring_row(y + k), wp_);
  };
  va = ring_at(ring_, 0);
  vb = ring_at(ring_sq_, 0);
  vc = ring_at(ring_ref_, 0);
  for (int k = 1; k + 1 < side; k += 2) {
    va += ring_at(ring_, k) + ring_at(ring_, k + 1);
    vb += ring_at(ring_sq_, k) + ring_at(ring_sq_, k + 1);
    vc += ring_at(ring_ref_, k) + ring_at(ring_ref_, k + 1);
  }
  // Horizontal window sums.
  Row sa(sum_h_[0].data(), w_);
  Row sb(sum_h_[1].data(), w_);
  Row sc(sum_h_[2].data(), w_);
  sa = va.head(w_);
  sb = vb.head(w_);
  sc = vc.head(w_);
  for (int k = 1; k + 1 < side; k += 2) {
    sa += va.segment(k, w_) + va.segment(k + 1, w_);
    sb += vb.segment(k, w_) + vb.segment(k + 1, w_);
    sc += vc.segment(k, w_) + vc.segment(k + 1, w_);
  }
  // zncc = (S_rw - S_r S_w / n) / sqrt((var_r + floor)(var_w + floor)), cost (1 - zncc)/2;
  // kNoCost where the window centre is outside the source (inside is 0 or 1).
  const std::size_t out = static_cast<std::size_t>(y) * static_cast<std::size_t>(w_);
  const ConstRow ref_sum(ref_sum_.data() + out, w_);
  const ConstRow ref_inv_std(ref_inv_std_.data() + out, w_);
  const ConstRow inside(ring_inside_.data() + ring_row(y + r_) + static_cast<std::size_t>(r_), w_);
  Row c(cost, w_);
  c = inside * (0.5F - 0.5F * (sc - sa * ref_sum * inv_n) * ref_inv_std *
                           ((sb - sa.square() * inv_n).max(0.0F) + floor_n).rsqrt())
                   .max(0.0F)
                   .min(1.0F) +
      (1.0F - inside) * kNoCost;
}

void PlaneSweepStereo::cost_row_census(int y, float* cost) {
  const int side = 2 * r_ + 1;
  const float inv_bits = 1.0F / static_cast<float>(side * side - 1);
  const auto eps = static_cast<float>(opts_.census_epsilon);
  const auto wp = static_cast<std::size_t>(wp_);
  const auto w = static_cast<std::size_t>(w_);
  float* mismatches = sum_h_[0].data();
  std::fill_n(mismatches, w, 0.0F);
  const auto r = static_cast<std::size_t>(r_);
  const float* wc = ring_.data() + ring_row(y + r_) + r;
  const float* rc = ref_pad_.data() + static_cast<std::size_t>(y + r_) * wp + r;
  for (int dy = 0; dy < side; ++dy) {
    for (int dx = 0; dx < side; ++dx) {
      if (dy == r_ && dx == r_) continue;
      const float* wn = ring_.data() + ring_row(y + dy) + static_cast<std::size_t>(dx);
      const float* rn =
          ref_pad_.data() + static_cast<std::size_t>(y + dy) * wp + static_cast<std::size_t>(dx);
      for (std::size_t x = 0; x < w; ++x) {
        const int ws =
            static_cast<int>(wn[x] > wc[x] + eps) - static_cast<int>(wn[x] < wc[x] - eps);
        const int rs =
            static_cast<int>(rn[x] > rc[x] + eps) - static_cast<int>(rn[x] < rc[x] - eps);
        mismatches[x] += static_cast<float>(ws != rs);
      }
    }
  }
  const float* in = ring_inside_.data() + ring_row(y + r_) + r;
  for (std::size_t x = 0; x < w; ++x) cost[x] = in[x] > 0.5F ? mismatches[x] * inv_bits : kNoCost;
}

void PlaneSweepStereo::sweep_source(int source, float rho, float plane, bool zncc,
                                    std::size_t k_best) {
  const auto si = static_cast<std::size_t>(source);
  const auto wp = static_cast<std::size_t>(wp_);
  const auto w = static_cast<std::size_t>(w_);
  float* c = cost_one_.data();
  for (int yp = 0; yp < hp_; ++yp) {
    const std::size_t slot = ring_row(yp);
    float* warped = ring_.data() + slot;
    warp_row(src_[si].data(), geo_[si], rho, yp, warped, ring_inside_.data() + slot);
    if (zncc) {
      const Eigen::Map<const Eigen::ArrayXf> wr(warped, wp_);
      const Eigen::Map<const Eigen::ArrayXf> ref(
          ref_pad_.data() + static_cast<std::size_t>(yp) * wp, wp_);
      Eigen::Map<Eigen::ArrayXf>(ring_sq_.data() + slot, wp_) = wr.square();
      Eigen::Map<Eigen::ArrayXf>(ring_ref_.data() + slot, wp_) = wr * ref;
    }
    if (yp < 2 * r_) continue;  // the first window is not complete yet
    const int y = yp - 2 * r_;
    if (zncc) {
      cost_row_zncc(y, c);
    } else {
      cost_row_census(y, c);
    }
    // This source's own best plane, then insertion into the sorted best-K lists.
    const std::size_t o = static_cast<std::size_t>(y) * w;
    float* own_cost = src_best_cost_[si].data() + o;
    float* own_plane = src_best_plane_[si].data() + o;
    for (std::size_t x = 0; x < w; ++x) {
      own_plane[x] = c[x] < own_cost[x] ? plane : own_plane[x];
      own_cost[x] = std::min(own_cost[x], c[x]);
    }
    if (source == 0) {  // the lists start with this source's cost alone
      std::copy_n(c, w, best_[0].data() + o);
      for (std::size_t j = 1; j < k_best; ++j) std::fill_n(best_[j].data() + o, w, kNoCost);
      continue;
    }
    for (std::size_t j = 0; j < k_best; ++j) {
      float* b = best_[j].data() + o;
      for (std::size_t x = 0; x < w; ++x) {
        const float lo = std::min(b[x], c[x]);
        c[x] = std::max(b[x], c[x]);
        b[x] = lo;
      }
    }
  }
}

void PlaneSweepStereo::aggregate_sgm(bool reversed, bool diagonals) {
  const int planes = planes_;
  const std::size_t stride = static_cast<std::size_t>(planes) + 2;
  const auto n = static_cast<std::size_t>(w_) * static_cast<std::size_t>(h_);
  const auto p1 = static_cast<std::int16_t>(std::lround(opts_.sgm_p1 * kCostUnits));
  const auto p2 = static_cast<std::int16_t>(std::lround(opts_.sgm_p2 * kCostUnits));
  // Directions in scan order (x then y; the reversed pass scans the image backwards):
  // 0: from the left (same row), 1: from above, 2: from above-left, 3: from above-right.
  const int row_dirs = diagonals ? 3 : 1;
  std::fill(path_prev_.begin(), path_prev_.end(), kPathSentinel);
  std::fill(path_cur_.begin(), path_cur_.end(), kPathSentinel);
  // Slot of direction `dir` (1..3) at column x in a row buffer; slot 0 is the horizontal one.
  const auto slot = [&](int dir, int x) {
    return (1 + static_cast<std::size_t>(dir - 1) * static_cast<std::size_t>(w_) +
            static_cast<std::size_t>(x));
  };
  std::int16_t* hprev = path_prev_.data() + 1;  // horizontal: previous pixel (plane 0)
  std::int16_t* hcur = path_cur_.data() + 1;
  std::int16_t hmin_prev = 0;
  for (int y = 0; y < h_; ++y) {
    for (int x = 0; x < w_; ++x) {
      const std::size_t scan =
          static_cast<std::size_t>(y) * static_cast<std::size_t>(w_) + static_cast<std::size_t>(x);
      const std::size_t p = reversed ? n - 1 - scan : scan;
      const std::int16_t* c = cost_.data() + p * static_cast<std::size_t>(planes);
      std::int16_t* sum = agg_.data() + p * static_cast<std::size_t>(planes);
      // From the left.
      hmin_prev = x == 0 ? path_start(c, hcur, sum, planes)
                         : path_step(c, hprev, hmin_prev, p1, p2, hcur, sum, planes);
      std::swap(hprev, hcur);
      // From the previous row: above (dx = 0), above-left (-1), above-right (+1).
      for (int dir = 1; dir <= row_dirs; ++dir) {
        const int dx = dir == 1 ? 0 : (dir == 2 ? -1 : 1);
        const int xs = x + dx;
        std::int16_t* l = path_cur_.data() + slot(dir, x) * stride + 1;
        std::int16_t& m = path_min_cur_[slot(dir, x)];
        if (y == 0 || xs < 0 || xs >= w_) {
          m = path_start(c, l, sum, planes);
        } else {
          const std::int16_t* lp = path_prev_.data() + slot(dir, xs) * stride + 1;
          m = path_step(c, lp, path_min_prev_[slot(dir, xs)], p1, p2, l, sum, planes);
        }
      }
    }
    std::swap(path_prev_, path_cur_);
    std::swap(path_min_prev_, path_min_cur_);
    // The horizontal buffers live in slot 0 of the swapped vectors: re-point them.
    hprev = path_prev_.data() + 1;
    hcur = path_cur_.data() + 1;
  }
}

void PlaneSweepStereo::select_and_score(const std::int16_t* costs, int num_sources) {
  const int planes = planes_;
  const int views_needed = std::min(opts_.consistent_views, num_sources);
  const auto tol = static_cast<float>(opts_.consistency_tolerance_px);
  const auto full = static_cast<float>(opts_.uniqueness_full);
  const auto radius_px = static_cast<float>(opts_.uniqueness_radius_px);
  const auto min_conf = static_cast<float>(opts_.min_confidence);
  const auto sources = static_cast<std::size_t>(num_sources);
  for (int y = 0; y < h_; ++y) {
    auto* depth = depth_.ptr<float>(y);
    auto* conf = confidence_.ptr<float>(y);
    for (int x = 0; x < w_; ++x) {
      depth[x] = 0.0F;
      conf[x] = 0.0F;
      const std::size_t p =
          static_cast<std::size_t>(y) * static_cast<std::size_t>(w_) + static_cast<std::size_t>(x);
      const std::int16_t* s = costs + p * static_cast<std::size_t>(planes);
      const int best = static_cast<int>(std::min_element(s, s + planes) - s);
      // A minimum on the first or last plane is (probably) outside the bounds.
      if (best == 0 || best == planes - 1) continue;
      float offset = 0.0F;
      if (opts_.subsample) {
        // Equiangular (V-shaped) fit through the winner and its neighbours: the aggregated
        // cost is V-shaped near its minimum (SGM's P1 term is linear in the plane step),
        // and a parabola there locks the vertex towards whole planes.
        const float c0 = s[best - 1];
        const float c1 = s[best];
        const float c2 = s[best + 1];
        const float slope = std::max(c0, c2) - c1;
        if (slope > 0.0F) offset = std::clamp(0.5F * (c0 - c2) / slope, -0.5F, 0.5F);
      }
      const float rho = rho_far_ + (static_cast<float>(best) + offset) * rho_step_;
      // Per source: image motion per unit inverse depth here, d(pixel)/d(rho) of h / h_z
      // with dh/drho = b; multi-view consistency: the source's own (unaggregated) best
      // plane projects within `tol` pixels of the final depth's projection.
      const auto u = static_cast<float>(x);
      const auto v = static_cast<float>(y);
      float max_motion = 0.0F;
      int agree = 0;
      for (std::size_t i = 0; i < sources; ++i) {
        const auto& g = geo_[i];
        const auto& A = g.A;
        const float hx = A[0] * u + A[1] * v + A[2] + rho * g.b[0];
        const float hy = A[3] * u + A[4] * v + A[5] + rho * g.b[1];
        const float hz = A[6] * u + A[7] * v + A[8] + rho * g.b[2];
        if (hz <= kMinHomogeneousZ) continue;
        const float dx = (g.b[0] * hz - hx * g.b[2]) / (hz * hz);
        const float dy = (g.b[1] * hz - hy * g.b[2]) / (hz * hz);
        const float motion = std::sqrt(dx * dx + dy * dy);
        max_motion = std::max(max_motion, motion);
        const float own = src_best_plane_[i][p];
        if (own >= 0.0F && std::abs(rho_far_ + own * rho_step_ - rho) * motion <= tol) ++agree;
      }
      // Uniqueness: the best cost against the best one at least `radius_px` away in the
      // widest-baseline source (planes closer than that are the same match, sub-pixel).
      const float planes_per_px = 1.0F / std::max(max_motion * rho_step_, 1e-6F);
      const int exclude =
          std::clamp(static_cast<int>(std::ceil(radius_px * planes_per_px)), 1, planes);
      int second = std::numeric_limits<int>::max();
      for (int d = 0; d < planes; ++d) {
        if (d < best - exclude || d > best + exclude) {
          second = std::min(second, static_cast<int>(s[d]));
        }
      }
      if (second == std::numeric_limits<int>::max()) continue;  // the whole sweep is < 1 px
      const float uniqueness =
          second > 0 ? 1.0F - static_cast<float>(s[best]) / static_cast<float>(second) : 0.0F;
      const float c_unique = std::clamp(uniqueness / full, 0.0F, 1.0F);
      const float c_views =
          std::min(1.0F, static_cast<float>(agree) / static_cast<float>(views_needed));
      conf[x] = c_unique * c_views;
      if (conf[x] >= min_conf && rho > 0.0F) depth[x] = 1.0F / rho;
    }
  }
}

}  // namespace mer::depth
