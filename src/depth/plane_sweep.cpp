#include "depth/plane_sweep.h"

#include <algorithm>
#include <cmath>
#include <limits>

#include <Eigen/Core>

#include "depth/plane_sweep_internal.h"

namespace mer::depth {
namespace {

using plane_sweep_detail::kCostUnits;
using plane_sweep_detail::kNoCost;

// Pixels per cache-friendly block of the plane-major to pixel-major transposition.
constexpr int kTransposeBlock = 64;

// Separable area-resampling table of one axis: output i covers inputs [i s, (i+1) s).
void build_area_table(int in_size, int out_size, std::vector<int>& first, std::vector<int>& count,
                      std::vector<int>& offset, std::vector<float>& weight) {
  const double s = static_cast<double>(in_size) / out_size;
  first.resize(static_cast<std::size_t>(out_size));
  count.resize(static_cast<std::size_t>(out_size));
  offset.resize(static_cast<std::size_t>(out_size));
  weight.clear();
  for (int i = 0; i < out_size; ++i) {
    const double a = i * s;
    const double b = std::min<double>(in_size, (i + 1) * s);
    const int j0 = std::min(in_size - 1, static_cast<int>(std::floor(a)));
    const int j1 = std::max(j0 + 1, std::min(in_size, static_cast<int>(std::ceil(b))));
    first[static_cast<std::size_t>(i)] = j0;
    count[static_cast<std::size_t>(i)] = j1 - j0;
    offset[static_cast<std::size_t>(i)] = static_cast<int>(weight.size());
    for (int j = j0; j < j1; ++j) {
      const double overlap = std::min<double>(b, j + 1) - std::max<double>(a, j);
      weight.push_back(static_cast<float>(std::max(0.0, overlap) / (b - a)));
    }
  }
}

bool finite_pose(const SE3d& T) {
  return T.matrix().allFinite();
}

}  // namespace

PlaneSweepStereo::PlaneSweepStereo(const PlaneSweepOptions& opts) : opts_(opts) {
  options_status_ = options::validate(opts_);
  if (!options_status_.is_ok()) {
    options_status_ = invalid_argument("plane sweep options: " + options_status_.message());
    return;
  }
  w_ = opts_.width;
  h_ = opts_.height;
  r_ = opts_.patch_radius;
  wp_ = w_ + 2 * r_;
  hp_ = h_ + 2 * r_;
  planes_ = opts_.num_planes;
  const auto n = static_cast<std::size_t>(w_) * static_cast<std::size_t>(h_);
  const auto np = static_cast<std::size_t>(wp_) * static_cast<std::size_t>(hp_);
  const auto sources = static_cast<std::size_t>(opts_.max_sources);
  const auto k = static_cast<std::size_t>(std::min(opts_.best_k, opts_.max_sources));
  const auto planes = static_cast<std::size_t>(planes_);
  const auto row = static_cast<std::size_t>(wp_);

  ref_.resize(n);
  ref_pad_.resize(np);
  ref_sum_.resize(n);
  ref_inv_std_.resize(n);
  src_.assign(sources, std::vector<float>(n));
  geo_.resize(sources);
  const auto ring = static_cast<std::size_t>(2 * r_ + 1) * row;
  ring_.resize(ring);
  ring_sq_.resize(ring);
  ring_ref_.resize(ring);
  ring_inside_.resize(ring);
  warp_index_.resize(row);
  warp_y0_.resize(row);
  warp_inv_z_.resize(row);
  column_u_.resize(row);
  for (int x = 0; x < wp_; ++x) column_u_[static_cast<std::size_t>(x)] = static_cast<float>(x - r_);
  warp_ax_.resize(row);
  warp_ay_.resize(row);
  for (auto& v : sum_v_) v.resize(row);
  for (auto& v : sum_h_) v.resize(static_cast<std::size_t>(w_));
  count_.resize(n);
  cost_one_.resize(n);
  best_.assign(k, std::vector<float>(n));
  src_best_cost_.assign(sources, std::vector<float>(n));
  src_best_plane_.assign(sources, std::vector<float>(n));
  cost_planes_.resize(n * planes);
  cost_.resize(n * planes);
  agg_.resize(n * planes);
  // SGM rows: up to 3 directions that look at the previous row, plus the horizontal one.
  constexpr std::size_t kRowDirections = 3;
  const std::size_t stride = planes + 2;
  path_prev_.resize((kRowDirections * static_cast<std::size_t>(w_) + 1) * stride);
  path_cur_.resize(path_prev_.size());
  path_min_prev_.resize(kRowDirections * static_cast<std::size_t>(w_) + 1);
  path_min_cur_.resize(path_min_prev_.size());
  depth_ = cv::Mat::zeros(h_, w_, CV_32F);
  confidence_ = cv::Mat::zeros(h_, w_, CV_32F);
}

Status PlaneSweepStereo::check_input(const PlaneSweepInput& in) const {
  if (!options_status_.is_ok()) return options_status_;
  const auto image_error = [](const cv::Mat* m) -> const char* {
    if (m == nullptr || m->empty()) return "is missing";
    if (m->type() != CV_8UC1) return "is not 8-bit grey (CV_8UC1)";
    if (m->cols < 2 || m->rows < 2) return "is smaller than 2x2";
    return nullptr;
  };
  if (const char* e = image_error(in.gray)) {
    return invalid_argument(std::string("plane sweep: reference image ") + e);
  }
  if (in.sources.empty()) return invalid_argument("plane sweep: no source views");
  if (in.sources.size() > static_cast<std::size_t>(opts_.max_sources)) {
    return invalid_argument("plane sweep: " + std::to_string(in.sources.size()) +
                            " source views, max_sources is " + std::to_string(opts_.max_sources));
  }
  for (std::size_t i = 0; i < in.sources.size(); ++i) {
    const auto& s = in.sources[i];
    if (const char* e = image_error(s.gray)) {
      return invalid_argument("plane sweep: source " + std::to_string(i) + " image " + e);
    }
    if (s.gray->size() != in.gray->size()) {
      return invalid_argument("plane sweep: source " + std::to_string(i) +
                              " image size differs from the reference's");
    }
    if (!finite_pose(s.T_w_c)) {
      return invalid_argument("plane sweep: source " + std::to_string(i) + " pose not finite");
    }
  }
  if (!finite_pose(in.T_w_c)) return invalid_argument("plane sweep: reference pose not finite");
  if (!(in.K.fx > 0.0 && in.K.fy > 0.0 && std::isfinite(in.K.fx) && std::isfinite(in.K.fy) &&
        std::isfinite(in.K.cx) && std::isfinite(in.K.cy))) {
    return invalid_argument("plane sweep: intrinsics need finite fx, fy > 0");
  }
  if (!(in.min_depth > 0.0 && in.max_depth > in.min_depth && std::isfinite(in.max_depth))) {
    return invalid_argument(
        "plane sweep: depth bounds must satisfy 0 < min_depth < max_depth "
        "(found " +
        std::to_string(in.min_depth) + ", " + std::to_string(in.max_depth) + ")");
  }
  return Status::ok();
}

void PlaneSweepStereo::prepare_tables(int in_width, int in_height) {
  if (table_x_.in_size != in_width) {
    build_area_table(in_width, w_, table_x_.first, table_x_.count, table_x_.offset,
                     table_x_.weight);
    table_x_.in_size = in_width;
  }
  if (table_y_.in_size != in_height) {
    build_area_table(in_height, h_, table_y_.first, table_y_.count, table_y_.offset,
                     table_y_.weight);
    table_y_.in_size = in_height;
  }
  resample_tmp_.resize(static_cast<std::size_t>(in_height) * static_cast<std::size_t>(w_));
}

void PlaneSweepStereo::resample(const cv::Mat& gray, float* out) {
  const auto w = static_cast<std::size_t>(w_);
  // Horizontal pass: every input row to the working width.
  for (int y = 0; y < gray.rows; ++y) {
    const std::uint8_t* in = gray.ptr<std::uint8_t>(y);
    float* t = resample_tmp_.data() + static_cast<std::size_t>(y) * w;
    for (int x = 0; x < w_; ++x) {
      const auto xi = static_cast<std::size_t>(x);
      const float* wt = table_x_.weight.data() + table_x_.offset[xi];
      const std::uint8_t* src = in + table_x_.first[xi];
      float acc = 0.0F;
      for (int j = 0; j < table_x_.count[xi]; ++j) acc += wt[j] * static_cast<float>(src[j]);
      t[x] = acc;
    }
  }
  // Vertical pass, vectorised over the row.
  for (int y = 0; y < h_; ++y) {
    const auto yi = static_cast<std::size_t>(y);
    float* o = out + yi * w;
    std::fill(o, o + w, 0.0F);
    const float* wt = table_y_.weight.data() + table_y_.offset[yi];
    for (int j = 0; j < table_y_.count[yi]; ++j) {
      const float* t = resample_tmp_.data() + static_cast<std::size_t>(table_y_.first[yi] + j) * w;
      const float a = wt[j];
      for (std::size_t x = 0; x < w; ++x) o[x] += a * t[x];
    }
  }
}

void PlaneSweepStereo::pad_reference() {
  for (int y = 0; y < hp_; ++y) {
    const int ys = std::clamp(y - r_, 0, h_ - 1);
    const float* in = ref_.data() + static_cast<std::size_t>(ys) * static_cast<std::size_t>(w_);
    float* o = ref_pad_.data() + static_cast<std::size_t>(y) * static_cast<std::size_t>(wp_);
    for (int x = 0; x < wp_; ++x) o[x] = in[std::clamp(x - r_, 0, w_ - 1)];
  }
}

void PlaneSweepStereo::prepare_reference_stats() {
  const int side = 2 * r_ + 1;
  const double n = side * side;
  const double floor_n = n * opts_.zncc_variance_floor;
  for (int y = 0; y < h_; ++y) {
    for (int x = 0; x < w_; ++x) {
      double s = 0.0;
      double ss = 0.0;
      for (int dy = 0; dy < side; ++dy) {
        const float* p = ref_pad_.data() + static_cast<std::size_t>(y + dy) * wp_ + x;
        for (int dx = 0; dx < side; ++dx) {
          s += p[dx];
          ss += static_cast<double>(p[dx]) * p[dx];
        }
      }
      const std::size_t i = static_cast<std::size_t>(y) * w_ + static_cast<std::size_t>(x);
      ref_sum_[i] = static_cast<float>(s);
      ref_inv_std_[i] =
          static_cast<float>(1.0 / std::sqrt(std::max(0.0, ss - s * s / n) + floor_n));
    }
  }
}

void PlaneSweepStereo::clear_output() {
  if (depth_.empty()) return;
  depth_.setTo(0.0F);
  confidence_.setTo(0.0F);
}

Status PlaneSweepStereo::compute(const PlaneSweepInput& in) {
  if (Status s = check_input(in); !s.is_ok()) {
    clear_output();
    return s;
  }
  full_w_ = in.gray->cols;
  full_h_ = in.gray->rows;
  prepare_tables(full_w_, full_h_);
  const double sx = static_cast<double>(w_) / full_w_;
  const double sy = static_cast<double>(h_) / full_h_;
  working_intrinsics_ = {in.K.fx * sx, in.K.fy * sy, (in.K.cx + 0.5) * sx - 0.5,
                         (in.K.cy + 0.5) * sy - 0.5};

  resample(*in.gray, ref_.data());
  pad_reference();
  const bool zncc = opts_.cost == PlaneSweepCost::kZncc;
  if (zncc) prepare_reference_stats();

  Eigen::Matrix3d K = Eigen::Matrix3d::Identity();
  K(0, 0) = working_intrinsics_.fx;
  K(1, 1) = working_intrinsics_.fy;
  K(0, 2) = working_intrinsics_.cx;
  K(1, 2) = working_intrinsics_.cy;
  const Eigen::Matrix3d K_inv = K.inverse();
  const int num_sources = static_cast<int>(in.sources.size());
  for (int i = 0; i < num_sources; ++i) {
    const auto si = static_cast<std::size_t>(i);
    resample(*in.sources[si].gray, src_[si].data());
    const SE3d T_s_r = in.sources[si].T_w_c.inverse() * in.T_w_c;
    const Eigen::Matrix3d A = K * T_s_r.linear() * K_inv;
    const Eigen::Vector3d b = K * T_s_r.translation();
    for (int r = 0; r < 3; ++r) {
      for (int c = 0; c < 3; ++c)
        geo_[si].A[static_cast<std::size_t>(3 * r + c)] = static_cast<float>(A(r, c));
      geo_[si].b[static_cast<std::size_t>(r)] = static_cast<float>(b(r));
    }
    std::fill(src_best_cost_[si].begin(), src_best_cost_[si].end(), kNoCost);
    std::fill(src_best_plane_[si].begin(), src_best_plane_[si].end(), -1.0F);
  }
  rho_far_ = static_cast<float>(1.0 / in.max_depth);
  rho_step_ =
      static_cast<float>(1.0 / in.min_depth - 1.0 / in.max_depth) / static_cast<float>(planes_ - 1);

  // Sweep: per plane, every source's cost, the per-source best and the best-K average.
  const auto n = static_cast<std::size_t>(w_) * static_cast<std::size_t>(h_);
  const std::size_t k_best = std::min(best_.size(), static_cast<std::size_t>(num_sources));
  float* c = cost_one_.data();
  for (int k = 0; k < planes_; ++k) {
    const float rho = rho_far_ + static_cast<float>(k) * rho_step_;
    const auto plane = static_cast<float>(k);
    for (int i = 0; i < num_sources; ++i) {
      sweep_source(i, rho, plane, zncc, k_best);
    }
    // Average of the valid best-K costs; no valid source: the worst cost (1). Branch-free:
    // a best-K entry is either a real cost in [0, 1] or kNoCost, so min(kNoCost - b, 1) is
    // 1 for a real cost and 0 for none.
    Eigen::Map<Eigen::ArrayXf> sum(c, static_cast<Eigen::Index>(n));
    Eigen::Map<Eigen::ArrayXf> count(count_.data(), static_cast<Eigen::Index>(n));
    sum.setZero();
    count.setZero();
    for (std::size_t j = 0; j < k_best; ++j) {
      const Eigen::Map<const Eigen::ArrayXf> b(best_[j].data(), static_cast<Eigen::Index>(n));
      sum += b * (kNoCost - b).min(1.0F);
      count += (kNoCost - b).min(1.0F);
    }
    sum = (sum + (1.0F - count).max(0.0F)) / count.max(1.0F) * kCostUnits + 0.5F;
    std::int16_t* __restrict slice = cost_planes_.data() + static_cast<std::size_t>(k) * n;
    const float* __restrict avg = c;
    for (std::size_t p = 0; p < n; ++p) slice[p] = static_cast<std::int16_t>(avg[p]);
  }

  // Plane-major to pixel-major, in cache-sized blocks of pixels.
  const auto planes = static_cast<std::size_t>(planes_);
  for (std::size_t p0 = 0; p0 < n; p0 += kTransposeBlock) {
    const std::size_t p1 = std::min(n, p0 + kTransposeBlock);
    for (std::size_t k = 0; k < planes; ++k) {
      const std::int16_t* src = cost_planes_.data() + k * n;
      for (std::size_t p = p0; p < p1; ++p) cost_[p * planes + k] = src[p];
    }
  }

  const std::int16_t* final_costs = cost_.data();
  if (opts_.aggregation != PlaneSweepAggregation::kNone) {
    std::fill(agg_.begin(), agg_.end(), std::int16_t{0});
    const bool diagonals = opts_.aggregation == PlaneSweepAggregation::kSgm8;
    aggregate_sgm(false, diagonals);
    aggregate_sgm(true, diagonals);
    final_costs = agg_.data();
  }
  select_and_score(final_costs, num_sources);
  return Status::ok();
}

bool PlaneSweepStereo::to_working(double u_full, double v_full, int* u, int* v) const {
  if (full_w_ <= 0 || full_h_ <= 0 || !std::isfinite(u_full) || !std::isfinite(v_full)) {
    return false;
  }
  const double uw = (u_full + 0.5) * w_ / full_w_ - 0.5;
  const double vw = (v_full + 0.5) * h_ / full_h_ - 0.5;
  *u = static_cast<int>(std::lround(uw));
  *v = static_cast<int>(std::lround(vw));
  return *u >= 0 && *u < w_ && *v >= 0 && *v < h_;
}

float PlaneSweepStereo::depth_at(double u_full, double v_full) const {
  int u = 0;
  int v = 0;
  return to_working(u_full, v_full, &u, &v) ? depth_.at<float>(v, u) : 0.0F;
}

float PlaneSweepStereo::confidence_at(double u_full, double v_full) const {
  int u = 0;
  int v = 0;
  return to_working(u_full, v_full, &u, &v) ? confidence_.at<float>(v, u) : 0.0F;
}

}  // namespace mer::depth
