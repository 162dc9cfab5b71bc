#pragma once
/// @file plane_sweep.h
/// Dense plane-sweep multi-view stereo for one reference keyframe and a few source frames
/// with known poses (a standalone module: depth maps for densification or meshing).
///
/// Pipeline, all at a fixed working resolution (images are area-resampled to it):
/// 1. Hypotheses: `num_planes` fronto-parallel planes z = d in the reference camera, evenly
///    spaced in inverse depth rho = 1/d between 1/max_depth and 1/min_depth.
/// 2. Warp: for the plane of inverse depth rho, a reference pixel x maps into source s by the
///    plane-induced homography H = K_s (R + t n^T rho) K_r^-1 with n = (0, 0, 1),
///    (R, t) = T_s_r. Since n^T K_r^-1 x = 1 for a homogeneous pixel, H x = A x + rho K_s t
///    with A = K_s R K_r^-1: one multiply-add per plane on top of a per-source constant.
/// 3. Cost: per source, ZNCC over a (2r+1)^2 window (invariant to the exposure gain and
///    offset of the camera), as (1 - zncc) / 2 in [0, 1]; or a ternary census (the fraction
///    of window neighbours whose brighter / equal within `census_epsilon` / darker relation
///    to the centre differs).
/// 4. Multi-view: the average of the best `best_k` of the N source costs (a pixel occluded
///    or out of view in some sources still matches in the others).
/// 5. Aggregation: semi-global matching along 4 or 8 image paths, penalties P1 (one plane
///    step) and P2 (larger jumps).
/// 6. Winner-take-all per pixel, refined to a sub-plane inverse depth by an equiangular
///    (V-shaped) fit through the aggregated costs of the winner and its two neighbouring
///    planes (SGM costs are V-shaped at their minimum; a parabola locks onto whole planes).
/// 7. Confidence in [0, 1]: uniqueness of the minimum, 1 - best / second-best aggregated
///    cost with the second best taken at least `uniqueness_radius_px` away (in pixels of the
///    widest-baseline source: closer planes are the same match), scaled by
///    `uniqueness_full`; times multi-view consistency, the fraction of `consistent_views`
///    sources whose own best match (alone, unaggregated) lands within
///    `consistency_tolerance_px` of the final depth's projection (it rejects occlusions and
///    mismatches in sources with a baseline long enough to tell).
///
/// Single-threaded. All buffers are allocated in the constructor for the working resolution;
/// compute() allocates only when the full-resolution input size changes (resampling
/// weights).
///
/// Measured on the synthetic room (tests/unit/depth/plane_sweep_test.cpp, 640x480 frames,
/// 4 past sources 0.1 - 0.4 s back): median relative depth error 1.6 % over the 64 % of
/// the pixels that get a depth with the default 24 planes (1.56 % over 66 % with 32, at
/// 1.33x the time: p50 158 vs 119 ms in one run of tests/bench/plane_sweep_bench.cpp).

#include <array>
#include <cstdint>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include <opencv2/core/mat.hpp>

#include "core/options.h"
#include "core/pose.h"
#include "core/status.h"
#include "geometry/camera_model.h"

namespace mer::depth {

/// Photometric cost of the sweep (`depth.plane_sweep.cost`).
enum class PlaneSweepCost : std::uint8_t {
  kZncc,    ///< zero-mean normalized cross-correlation
  kCensus,  ///< ternary census transform
};
/// Names of PlaneSweepCost in config, by value.
inline constexpr std::array<std::string_view, 2> kPlaneSweepCostNames{"zncc", "census"};
/// Cost aggregation of the sweep (`depth.plane_sweep.aggregation`).
enum class PlaneSweepAggregation : std::uint8_t {
  kNone,  ///< per-pixel costs as they are
  kSgm4,  ///< semi-global, 4 paths
  kSgm8,  ///< semi-global, 8 paths (diagonals too)
};
/// Names of PlaneSweepAggregation in config, by value.
inline constexpr std::array<std::string_view, 3> kPlaneSweepAggregationNames{"none", "sgm4",
                                                                             "sgm8"};

/// Options of the plane-sweep stereo (config section `depth.plane_sweep`).
struct PlaneSweepOptions {
  int width = 320;
  int height = 240;
  int num_planes = 24;
  int max_sources = 8;
  int patch_radius = 2;
  PlaneSweepCost cost = PlaneSweepCost::kZncc;
  double zncc_variance_floor = 4.0;
  double census_epsilon = 8.0;
  int best_k = 3;
  PlaneSweepAggregation aggregation = PlaneSweepAggregation::kSgm8;
  double sgm_p1 = 0.03;
  double sgm_p2 = 0.3;
  bool subsample = true;
  double uniqueness_full = 0.25;
  double uniqueness_radius_px = 1.0;
  int consistent_views = 2;
  double consistency_tolerance_px = 1.0;
  double min_confidence = 0.5;

  template <class V>
  void visit(V& v) {
    v.field("width", width, "working width, px (inputs are resampled to it)",
            options::Range<int>{16, 4096});
    v.field("height", height, "working height, px", options::Range<int>{16, 4096});
    v.field("num_planes", num_planes, "inverse-depth hypotheses between the depth bounds",
            options::Range<int>{3, 1024});
    v.field("max_sources", max_sources, "most source views a keyframe may use",
            options::Range<int>{1, 32});
    v.field("patch_radius", patch_radius, "cost window half-size: (2r+1)^2 pixels",
            options::Range<int>{1, 3});
    v.field("cost", cost, "photometric cost: zncc or census",
            options::Names<PlaneSweepCost>{kPlaneSweepCostNames});
    v.field("zncc_variance_floor", zncc_variance_floor,
            "grey levels^2 added to both window variances (flat windows score zncc ~ 0)",
            options::Range<double>{0.0, 10000.0});
    v.field("census_epsilon", census_epsilon,
            "census: a neighbour within this many grey levels of the centre counts as equal "
            "(ternary census: flat windows match each other instead of noise)",
            options::Range<double>{0.0, 255.0});
    v.field("best_k", best_k, "cost of a plane: average of the best K source costs",
            options::Range<int>{1, 32});
    v.field("aggregation", aggregation, "cost aggregation: none, sgm4 or sgm8 (semi-global)",
            options::Names<PlaneSweepAggregation>{kPlaneSweepAggregationNames});
    v.field("sgm_p1", sgm_p1, "SGM penalty of a one-plane step, in cost units [0, 1]",
            options::Range<double>{0.0, 1.0});
    v.field("sgm_p2", sgm_p2, "SGM penalty of a jump of more than one plane, cost units",
            options::Range<double>{0.0, 1.0});
    v.field("subsample", subsample,
            "sub-plane refinement of the inverse depth (equiangular fit of the costs)");
    v.field("uniqueness_full", uniqueness_full,
            "1 - best/second-best aggregated cost giving full uniqueness confidence",
            options::Range<double>{1e-3, 1.0});
    v.field("uniqueness_radius_px", uniqueness_radius_px,
            "the second-best cost is taken at least this far from the best, in pixels of "
            "the widest-baseline source (working resolution)",
            options::Range<double>{0.0, 100.0});
    v.field("consistent_views", consistent_views,
            "sources whose own best match must agree for full consistency confidence",
            options::Range<int>{1, 32});
    v.field("consistency_tolerance_px", consistency_tolerance_px,
            "a source agrees when its own best match is this close to the final depth's "
            "projection, px (working resolution)",
            options::Range<double>{0.0, 100.0});
    v.field("min_confidence", min_confidence, "depth() is 0 where confidence is below this",
            options::Range<double>{0.0, 1.0});
  }
};

/// A source frame: an 8-bit grey image (full resolution, same size as the reference) and
/// its camera-to-world pose.
struct PlaneSweepView {
  const cv::Mat* gray = nullptr;  ///< CV_8UC1
  SE3d T_w_c = SE3d::Identity();  ///< camera-to-world
};

/// The reference keyframe, its sources and the depth range to sweep.
struct PlaneSweepInput {
  const cv::Mat* gray = nullptr;            ///< reference image, CV_8UC1, full resolution
  SE3d T_w_c = SE3d::Identity();            ///< reference camera-to-world
  geometry::Pinhole K;                      ///< intrinsics at full resolution
  std::span<const PlaneSweepView> sources;  ///< frames with poses (same size and K)
  double min_depth = 0.0;                   ///< nearest plane, map units (> 0)
  double max_depth = 0.0;                   ///< farthest plane, map units (> min_depth)
};

/// Plane-sweep stereo with preallocated buffers; one instance per thread.
class PlaneSweepStereo {
 public:
  /// Allocates every buffer for opts.width x opts.height. Invalid options are reported by
  /// status() and by every compute().
  explicit PlaneSweepStereo(const PlaneSweepOptions& opts);

  /// Ok, or why the options are invalid.
  const Status& status() const { return options_status_; }

  /// Computes the depth and confidence of the reference view. An error (bad input) leaves
  /// depth() and confidence() all zero.
  Status compute(const PlaneSweepInput& in);

  /// Camera z at the working resolution, CV_32F; 0 where invalid or below min_confidence.
  const cv::Mat& depth() const { return depth_; }
  /// Confidence in [0, 1] at the working resolution, CV_32F (0 where no depth was found).
  const cv::Mat& confidence() const { return confidence_; }

  /// depth() at a full-resolution pixel of the last compute() (nearest working pixel; no
  /// interpolation across depth edges). 0 when invalid or outside the image.
  float depth_at(double u_full, double v_full) const;
  /// confidence() at a full-resolution pixel of the last compute(); 0 outside the image.
  float confidence_at(double u_full, double v_full) const;

  /// Intrinsics of the last compute() scaled to the working resolution (pixel-centre
  /// correct: fx' = fx s, cx' = (cx + 0.5) s - 0.5).
  geometry::Pinhole working_intrinsics() const { return working_intrinsics_; }

  /// The options in use.
  const PlaneSweepOptions& options() const { return opts_; }

 private:
  /// Separable area-resampling table of one axis: output i averages inputs
  /// [first[i], first[i] + count[i]) with weights starting at offset[i].
  struct AreaTable {
    int in_size = 0;
    std::vector<int> first;
    std::vector<int> count;
    std::vector<int> offset;
    std::vector<float> weight;
  };
  /// A source prepared for one compute(): H x = A x + rho b (working pixels).
  struct SourceGeometry {
    std::array<float, 9> A{};  ///< row-major K_s R K_r^-1
    std::array<float, 3> b{};  ///< K_s t
  };

  Status check_input(const PlaneSweepInput& in) const;
  void prepare_tables(int in_width, int in_height);
  void resample(const cv::Mat& gray, float* out);
  void pad_reference();
  void prepare_reference_stats();
  void sweep_source(int source, float rho, float plane, bool zncc, std::size_t k_best);
  void warp_row(const float* src, const SourceGeometry& g, float rho, int yp, float* out,
                float* inside);
  void cost_row_zncc(int y, float* cost);
  void cost_row_census(int y, float* cost);
  std::size_t ring_row(int yp) const;
  void aggregate_sgm(bool reversed, bool diagonals);
  void select_and_score(const std::int16_t* costs, int num_sources);
  void clear_output();
  bool to_working(double u_full, double v_full, int* u, int* v) const;

  PlaneSweepOptions opts_;
  Status options_status_;
  int w_ = 0, h_ = 0;    // working size
  int r_ = 0;            // patch radius
  int wp_ = 0, hp_ = 0;  // padded working size (r_ on each side)
  int planes_ = 0;
  int full_w_ = 0, full_h_ = 0;  // full-resolution size of the last compute()
  geometry::Pinhole working_intrinsics_;
  float rho_far_ = 0.0F, rho_step_ = 0.0F;  // inverse depth of plane 0, plane spacing

  AreaTable table_x_, table_y_;
  std::vector<float> resample_tmp_;  // input rows x working width

  std::vector<float> ref_;               // working reference, w x h
  std::vector<float> ref_pad_;           // replicate-padded reference, wp x hp
  std::vector<float> ref_sum_;           // ZNCC: window sum of the reference, w x h
  std::vector<float> ref_inv_std_;       // ZNCC: 1 / sqrt(window variance sum + floor), w x h
  std::vector<std::vector<float>> src_;  // working sources, w x h each
  std::vector<SourceGeometry> geo_;

  // One source at one plane is streamed row by row: the last 2r+1 warped rows of the padded
  // reference grid (one window) live in rings, row yp in slot yp mod (2r+1).
  std::vector<float> ring_;                  // warped source rows, (2r+1) x wp
  std::vector<float> ring_sq_;               // their squares (zncc)
  std::vector<float> ring_ref_;              // warped source times reference (zncc)
  std::vector<float> ring_inside_;           // 1 where the warped pixel is inside the source
  std::vector<float> column_u_;              // per padded column: its working x coordinate
  std::vector<int> warp_index_;              // per padded column: top-left source sample
  std::vector<int> warp_y0_;                 // per padded column: its source row
  std::vector<float> warp_inv_z_;            // per padded column: 1 / homogeneous z
  std::vector<float> warp_ax_, warp_ay_;     // per padded column: position, then bilinear weights
  std::array<std::vector<float>, 3> sum_v_;  // vertical window sums of one row, wp
  std::array<std::vector<float>, 3> sum_h_;  // full window sums of one row, w
  std::vector<float> count_;                 // valid best-K costs per pixel, w x h
  std::vector<float> cost_one_;              // one source's cost row, then best-K sums, w x h
  std::vector<std::vector<float>> best_;     // best_k smallest source costs so far, w x h each
  std::vector<std::vector<float>> src_best_cost_;   // per source: its own best cost, w x h
  std::vector<std::vector<float>> src_best_plane_;  // per source: plane of that cost, w x h

  std::vector<std::int16_t> cost_planes_;  // plane-major costs, planes x (w h)
  std::vector<std::int16_t> cost_;         // pixel-major costs, (w h) x planes
  std::vector<std::int16_t> agg_;          // pixel-major aggregated costs, (w h) x planes
  std::vector<std::int16_t> path_prev_;    // SGM: previous row, per direction, w x (planes+2)
  std::vector<std::int16_t> path_cur_;     // SGM: current row, per direction
  std::vector<std::int16_t> path_min_prev_, path_min_cur_;  // SGM: row minima per direction

  cv::Mat depth_;       // CV_32F, h x w
  cv::Mat confidence_;  // CV_32F, h x w
};

}  // namespace mer::depth
