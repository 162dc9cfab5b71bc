#pragma once
/// @file plane_sweep_depth.h
/// The `plane_sweep` depth-inference backend: dense plane-sweep stereo (plane_sweep.h) of the
/// keyframe against recent tracked frames, sampled at the keyframe's keypoints. The swept
/// depth range comes from the tracked map-points (DepthRequest::depth_hint_*, widened by
/// `range_margin`); without it (or without recent frames) the keyframe gets no depth. The
/// dense depth of the last keyframe stays available (dense_depth()).

#include <vector>

#include "depth/depth_inference.h"
#include "depth/plane_sweep.h"

namespace mer::depth {

/// Options of the `plane_sweep` backend (config section `depth.plane_sweep`).
struct PlaneSweepDepthOptions {
  PlaneSweepOptions stereo;
  int sources = 4;
  double source_spacing_s = 0.1;
  double range_margin = 2.0;
  double min_baseline_ratio = 0.02;

  template <class V>
  void visit(V& v) {
    v.field("sources", sources, "recent tracked frames the keyframe is swept against",
            options::Range<int>{1, 16});
    v.field("source_spacing_s", source_spacing_s,
            "time between the recent frames kept for the sweep, s",
            options::Range<double>{0.0, 10.0});
    v.field("range_margin", range_margin,
            "swept depth range: the tracked points' range divided / multiplied by this",
            options::Range<double>{1.0, 100.0});
    v.field("min_baseline_ratio", min_baseline_ratio,
            "a recent frame is a source only if its distance to the keyframe is at least this "
            "fraction of the tracked points' median depth (no source: no depth)",
            options::Range<double>{0.0, 10.0});
    v.section("stereo", stereo, "plane-sweep stereo");
  }
};

/// Plane-sweep depth at the keypoints.
class PlaneSweepDepth final : public DepthInference {
 public:
  explicit PlaneSweepDepth(const PlaneSweepDepthOptions& opts);
  std::string_view name() const override { return "plane_sweep"; }
  DepthScale scale() const override { return DepthScale::kMap; }
  Status infer(const DepthRequest& req, DepthResult& out) override;
  /// Dense depth / confidence of the last keyframe (working resolution).
  const PlaneSweepStereo& stereo() const { return stereo_; }

 private:
  PlaneSweepDepthOptions opts_;
  PlaneSweepStereo stereo_;
  std::vector<PlaneSweepView> sources_;
};

}  // namespace mer::depth
