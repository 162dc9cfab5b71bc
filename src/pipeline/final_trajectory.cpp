#include "pipeline/final_trajectory.h"

#include <algorithm>
#include <unordered_map>

namespace mer::pipeline {

std::vector<FinalKeyframePose> resolve_keyframe_poses(
    std::span<const StampedPose> live, std::span<const backend::CulledKeyframe> lineage,
    std::span<const double> segment_scale) {
  std::unordered_map<std::int64_t, FinalKeyframePose> known;
  known.reserve(live.size() + lineage.size());
  for (const StampedPose& p : live) known.emplace(p.t_ns, FinalKeyframePose{p.t_ns, p.T_w_c});
  // A record's offset in the units of `live`: 0 when its segment did not join it.
  auto scale_of = [&](const backend::CulledKeyframe& c) {
    if (segment_scale.empty()) return 1.0;
    return c.segment < segment_scale.size() ? segment_scale[c.segment] : 0.0;
  };
  std::unordered_map<std::int64_t, const backend::CulledKeyframe*> parent_of;
  parent_of.reserve(lineage.size());
  for (const backend::CulledKeyframe& c : lineage) {
    if (scale_of(c) > 0.0) parent_of.emplace(c.t_ns, &c);
  }

  // Walk each removed keyframe up its lineage to a known pose, then compose back down.
  // A chain is at most lineage.size() long (each record names a keyframe that was live
  // when its child was removed, so there is no cycle; the bound guards a corrupt input).
  std::vector<const backend::CulledKeyframe*> chain;
  for (const backend::CulledKeyframe& c : lineage) {
    if (known.contains(c.t_ns) || !(scale_of(c) > 0.0)) continue;
    chain.clear();
    const backend::CulledKeyframe* at = &c;
    while (at != nullptr && !known.contains(at->parent_t_ns) && chain.size() < lineage.size()) {
      chain.push_back(at);
      const auto it = parent_of.find(at->parent_t_ns);
      at = it == parent_of.end() ? nullptr : it->second;
    }
    if (at == nullptr || !known.contains(at->parent_t_ns)) continue;  // lineage forgotten
    chain.push_back(at);
    for (auto it = chain.rbegin(); it != chain.rend(); ++it) {
      const FinalKeyframePose& parent = known.at((*it)->parent_t_ns);
      SE3d T_parent_kf = (*it)->T_parent_kf;
      T_parent_kf.translation() *= scale_of(**it);
      known.emplace((*it)->t_ns, FinalKeyframePose{(*it)->t_ns, parent.T_w_c * T_parent_kf, true});
    }
  }
  std::vector<FinalKeyframePose> out;
  out.reserve(known.size());
  for (const auto& kv : known) out.push_back(kv.second);
  std::sort(out.begin(), out.end(),
            [](const FinalKeyframePose& a, const FinalKeyframePose& b) { return a.t_ns < b.t_ns; });
  return out;
}

namespace {

/// D^alpha for a small SE(3) correction: rotation angle and translation scaled by alpha.
SE3d fraction_of(const SE3d& D, double alpha) {
  const Eigen::AngleAxisd aa(D.linear());
  SE3d out = SE3d::Identity();
  out.linear() = Eigen::AngleAxisd(alpha * aa.angle(), aa.axis()).toRotationMatrix();
  out.translation() = alpha * D.translation();
  return out;
}

}  // namespace

std::vector<StampedPose> reanchor_frames(std::span<const AnchoredFrame> frames,
                                         std::span<const FinalKeyframePose> keyframes,
                                         FinalTrajectoryStats& stats) {
  auto find_kf = [&](std::int64_t t) -> const FinalKeyframePose* {
    const auto it =
        std::lower_bound(keyframes.begin(), keyframes.end(), t,
                         [](const FinalKeyframePose& k, std::int64_t x) { return k.t_ns < x; });
    return it != keyframes.end() && it->t_ns == t ? &*it : nullptr;
  };
  // The back end also moves an anchor's next keyframe B relative to it: D, in the anchor's
  // frame, takes B's offset as tracked to B's final pose. A frame between the two gets the
  // fraction of D its time is of the way to B (the whole of it past B), so the re-anchored
  // trajectory runs on into B's final pose instead of jumping there.
  std::unordered_map<std::int64_t, SE3d> to_next;  // anchor stamp -> D
  for (const AnchoredFrame& f : frames) {
    if (!f.has_anchor) continue;
    const FinalKeyframePose* a = find_kf(f.anchor_t_ns);
    const FinalKeyframePose* b = find_kf(f.t_ns);  // the frame that became keyframe B
    if (a == nullptr || b == nullptr || b != a + 1) continue;
    to_next.emplace(a->t_ns, a->T_w_c.inverse() * b->T_w_c * f.T_kf_c.inverse());
  }
  std::vector<StampedPose> out;
  out.reserve(frames.size());
  SE3d correction = SE3d::Identity();  // final pose * tracked pose^-1 of the last anchored frame
  for (const AnchoredFrame& f : frames) {
    const FinalKeyframePose* kf = f.has_anchor ? find_kf(f.anchor_t_ns) : nullptr;
    SE3d T = correction * f.T_w_c;
    if (kf != nullptr) {
      SE3d D = SE3d::Identity();
      if (const auto it = to_next.find(kf->t_ns); it != to_next.end()) {
        const std::int64_t span = (kf + 1)->t_ns - kf->t_ns;
        const double alpha = std::clamp(
            static_cast<double>(f.t_ns - kf->t_ns) / static_cast<double>(span), 0.0, 1.0);
        D = fraction_of(it->second, alpha);
        ++stats.interpolated;
      }
      T = kf->T_w_c * D * f.T_kf_c;
      correction = T * f.T_w_c.inverse();
      ++stats.reanchored;
      if (kf->from_lineage) ++stats.via_lineage;
    } else {
      ++stats.unresolved;
    }
    out.push_back(StampedPose{f.t_ns, T});
    ++stats.frames;
  }
  return out;
}

}  // namespace mer::pipeline
