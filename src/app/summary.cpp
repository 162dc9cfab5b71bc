#include "app/summary.h"

#include <cerrno>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <iomanip>
#include <sstream>

namespace mer::app {
namespace {

std::string json_string(const std::string& s) {
  std::string out = "\"";
  for (const char c : s) {
    switch (c) {
      case '"':
        out += "\\\"";
        break;
      case '\\':
        out += "\\\\";
        break;
      case '\n':
        out += "\\n";
        break;
      case '\t':
        out += "\\t";
        break;
      default:
        if (static_cast<unsigned char>(c) < 0x20) {
          char buf[8];
          std::snprintf(buf, sizeof buf, "\\u%04x", c);
          out += buf;
        } else {
          out += c;
        }
    }
  }
  return out + "\"";
}

std::string num(double v) {
  std::ostringstream os;
  os << std::setprecision(6) << v;
  return os.str();
}

/// `"key": {...},` of one accuracy report (or its note when it is not available).
void write_accuracy(std::ostream& j, const char* key, const AccuracyReport& a) {
  if (a.available) {
    j << "  \"" << key << "\": {\"align\": " << json_string(a.alignment)
      << ", \"pairs\": " << a.pairs << ", \"gt_frames\": " << a.gt_frames
      << ", \"scale\": " << num(a.scale) << ", \"ate_rmse_m\": " << num(a.ate_rmse_m)
      << ", \"ate_mean_m\": " << num(a.ate_mean_m) << ", \"ate_median_m\": " << num(a.ate_median_m)
      << ", \"ate_max_m\": " << num(a.ate_max_m) << ", \"path_length_m\": " << num(a.path_length_m)
      << ", \"ate_pct_of_path\": " << num(a.ate_pct_of_path)
      << ", \"tracked_after_init_pct\": " << num(a.tracked_after_init_pct)
      << ", \"first_5s_pairs\": " << a.start_pairs
      << ", \"first_5s_ate_rmse_m\": " << num(a.start_ate_rmse_m)
      << ", \"first_5s_path_length_m\": " << num(a.start_path_length_m)
      << ", \"first_5s_ate_pct_of_path\": " << num(a.start_ate_pct_of_path) << "},\n";
  } else {
    j << "  \"" << key << "\": {\"note\": " << json_string(a.note) << "},\n";
  }
}

/// CPU per frame (whole process, and without the source's work) and in total.
void write_cpu(std::ostream& j, const pipeline::CpuStats& c) {
  auto dist = [&j](const pipeline::StageLatency& l) {
    j << "{\"p50\": " << num(l.p50_ms) << ", \"p90\": " << num(l.p90_ms)
      << ", \"p99\": " << num(l.p99_ms) << ", \"max\": " << num(l.max_ms)
      << ", \"mean\": " << num(l.mean_ms) << ", \"count\": " << l.count << "}";
  };
  j << "  \"cpu\": {\"process_s\": " << num(c.process_s) << ", \"source_s\": " << num(c.source_s)
    << ",\n    \"per_frame_ms\": {\"process\": ";
  dist(c.process);
  j << ",\n      \"slam\": ";
  dist(c.slam);
  j << "}},\n";
}

/// Frame counts, latency, budgets and allocations.
void write_frames(std::ostream& j, const pipeline::PipelineStats& st) {
  j << "  \"frames_in\": " << st.frames_in << ",\n";
  j << "  \"frames_processed\": " << st.frames_processed << ",\n";
  j << "  \"frames_dropped\": " << st.frames_dropped << ",\n";
  j << "  \"frames_lost\": " << st.frames_lost << ",\n";
  j << "  \"frames_discarded\": " << st.frames_discarded << ",\n";
  j << "  \"first_pose_seq\": " << st.first_pose_seq << ",\n";
  j << "  \"keyframes\": " << st.keyframes << ",\n";
  j << "  \"map_points\": " << st.map_points << ",\n";
  j << "  \"wall_time_s\": " << num(st.wall_time_s) << ",\n";
  j << "  \"latency_ms\": {";
  for (std::size_t i = 0; i < st.latency.size(); ++i) {
    const auto& l = st.latency[i];
    j << (i ? "," : "") << "\n    " << json_string(l.name) << ": {\"p50\": " << num(l.p50_ms)
      << ", \"p90\": " << num(l.p90_ms) << ", \"p99\": " << num(l.p99_ms)
      << ", \"max\": " << num(l.max_ms) << ", \"mean\": " << num(l.mean_ms)
      << ", \"count\": " << l.count << ", \"budget\": " << num(l.budget_ms) << "}";
  }
  j << "\n  },\n";
  j << "  \"budget_overruns\": {";
  for (std::size_t i = 0; i < st.latency.size(); ++i) {
    j << (i ? ", " : "") << json_string(st.latency[i].name) << ": " << st.latency[i].overruns;
  }
  j << "},\n";
  write_cpu(j, st.cpu);
  j << "  \"allocs_per_frame\": {";
  for (std::size_t i = 0; i < st.allocs.size(); ++i) {
    j << (i ? ", " : "") << json_string(st.allocs[i].thread) << ": "
      << num(st.allocs[i].per_frame());
  }
  j << "},\n";
  j << "  \"tracking_allocs_by_state\": {";
  for (std::size_t i = 0; i < st.tracking_allocs_by_state.size(); ++i) {
    const auto& a = st.tracking_allocs_by_state[i];
    j << (i ? ", " : "") << json_string(a.thread) << ": {\"frames\": " << a.frames
      << ", \"allocations\": " << a.allocations << ", \"per_frame\": " << num(a.per_frame()) << "}";
  }
  j << "},\n";
  j << "  \"steady_state_frames\": {";
  for (std::size_t i = 0; i < st.allocs.size(); ++i) {
    j << (i ? ", " : "") << json_string(st.allocs[i].thread) << ": " << st.allocs[i].frames;
  }
  j << "},\n";
}

/// The input, modes and intrinsics of the run.
void write_run(std::ostream& j, const pipeline::PipelineStats& st, const RunInfo& info) {
  j << "  \"input\": " << json_string(info.input) << ",\n";
  j << "  \"source\": " << json_string(info.source) << ",\n";
  j << "  \"sensor_mode\": " << json_string(std::string(to_string(info.sensor_mode))) << ",\n";
  j << "  \"run_mode\": " << json_string(st.mode) << ",\n";
  const auto& k = info.intrinsics;
  j << "  \"intrinsics\": {\"width\": " << k.width << ", \"height\": " << k.height
    << ", \"fx\": " << num(k.fx) << ", \"fy\": " << num(k.fy) << ", \"cx\": " << num(k.cx)
    << ", \"cy\": " << num(k.cy) << "},\n";
  j << "  \"pose_source\": " << json_string(st.pose_source) << ",\n";
}

/// The accuracy of trajectory.txt and the map segments.
void write_segments(std::ostream& j, const pipeline::PipelineStats& st, const RunInfo& info) {
  write_accuracy(j, "accuracy", info.accuracy);
  // Map segments: each in its own world frame until merged into another (merged_into, -1:
  // never); `trajectory` is the file holding its frames, trajectory.txt for the main one.
  j << "  \"segments\": [";
  for (std::size_t i = 0; i < st.segments.size(); ++i) {
    const pipeline::SegmentStats& g = st.segments[i];
    j << (i ? ", " : "") << "{\"id\": " << g.id << ", \"frames\": " << g.frames
      << ", \"keyframes\": " << g.keyframes << ", \"first_seq\": " << g.first_seq
      << ", \"last_seq\": " << g.last_seq << ", \"trajectory\": " << json_string(g.trajectory)
      << ", \"main\": " << (g.main ? "true" : "false")
      << ", \"discarded\": " << (g.discarded ? "true" : "false")
      << ", \"merged_into\": " << g.merged_into;
    if (g.merged_into >= 0) {
      j << ", \"merged_at_seq\": " << g.merged_at_seq << ", \"fit_keyframes\": " << g.fit_keyframes;
    }
    if (i < info.accuracy_segments.size() && info.accuracy_segments[i].available) {
      const AccuracyReport& a = info.accuracy_segments[i];
      j << ", \"ate_rmse_m\": " << num(a.ate_rmse_m)
        << ", \"ate_pct_of_path\": " << num(a.ate_pct_of_path);
    }
    if (i < info.accuracy_segments_own.size() && info.accuracy_segments_own[i].available) {
      j << ", \"own_ate_rmse_m\": " << num(info.accuracy_segments_own[i].ate_rmse_m)
        << ", \"own_pairs\": " << info.accuracy_segments_own[i].pairs;
    }
    j << "}";
  }
  j << "],\n";
}

/// The final map's accuracy, the ground-truth check and the final BA.
void write_final_and_gt_check(std::ostream& j, const pipeline::PipelineStats& st,
                              const RunInfo& info) {
  write_accuracy(j, "accuracy_keyframes", info.accuracy_keyframes);
  if (info.final_trajectory_written) {
    const pipeline::FinalTrajectoryStats& f = info.final_trajectory;
    j << "  \"final_trajectory\": {\"frames\": " << f.frames << ", \"reanchored\": " << f.reanchored
      << ", \"via_lineage\": " << f.via_lineage << ", \"interpolated\": " << f.interpolated
      << ", \"unresolved\": " << f.unresolved << "},\n";
    write_accuracy(j, "accuracy_final", info.accuracy_final);
    // Kept for readers of earlier summaries: the final BA's trajectory is trajectory_final.txt.
    if (st.final_ba.ran) write_accuracy(j, "accuracy_final_ba", info.accuracy_final);
  }
  if (info.gt_check_requested) {
    const eval::GroundTruthCheckReport& g = info.gt_check;
    if (g.ran) {
      j << "  \"gt_check\": {\"keyframes\": " << g.keyframes << ", \"points\": " << g.points
        << ", \"refit_rejected\": " << g.refit_rejected << ", \"observations\": " << g.observations
        << ", \"unprojected\": " << g.unprojected << ", \"scale\": " << num(g.scale)
        << ", \"beyond_1_level_px\": " << num(g.beyond_1_level_px)
        << ", \"beyond_2_level_px\": " << num(g.beyond_2_level_px) << ", \"rms_level_px\": [";
      for (std::size_t l = 0; l < g.levels.size(); ++l) {
        j << (l > 0 ? ", " : "") << num(g.levels[l].rms_level_px);
      }
      j << "], \"observations_per_level\": [";
      for (std::size_t l = 0; l < g.levels.size(); ++l) {
        j << (l > 0 ? ", " : "") << g.levels[l].observations;
      }
      j << "], \"anchored_observations\": " << g.anchored_observations
        << ", \"anchored_rms_level_px\": " << num(g.anchored_rms_level_px)
        << ", \"detected_rms_level_px\": " << num(g.detected_rms_level_px)
        << ", \"iterations_converged\": " << g.iterations_converged
        << ", \"iterations_shuffled\": " << g.iterations_shuffled
        << ", \"iterations_shuffled_detected\": " << g.iterations_shuffled_detected << "},\n";
      write_accuracy(j, "accuracy_gt_converged", info.accuracy_gt_converged);
      write_accuracy(j, "accuracy_gt_shuffled", info.accuracy_gt_shuffled);
      write_accuracy(j, "accuracy_gt_shuffled_detected", info.accuracy_gt_shuffled_detected);
    } else {
      j << "  \"gt_check\": {\"note\": " << json_string(g.note) << "},\n";
    }
  }
  if (st.final_ba.ran) {
    const pipeline::FinalBaStats& f = st.final_ba;
    j << "  \"final_ba\": {\"keyframes\": " << f.keyframes << ", \"points\": " << f.points
      << ", \"observations\": " << f.observations << ", \"iterations\": " << f.iterations
      << ", \"ms\": " << num(f.ms) << "},\n";
  }
}

/// Tracking counters and the tracking steps' latency.
void write_tracking(std::ostream& j, const pipeline::PipelineStats& st) {
  const frontend::TrackerCounters& tc = st.tracker;
  j << "  \"tracking\": {\"initialized\": " << (tc.initialized ? "true" : "false")
    << ", \"initialized_seq\": " << tc.initialized_seq
    << ", \"reference_seq\": " << tc.reference_seq << ", \"init_attempts\": " << tc.init_attempts
    << ", \"init_refusals\": " << tc.init_refusals
    << ", \"frames_oriented\": " << tc.frames_oriented
    << ", \"failed_starts\": " << tc.failed_starts
    << ", \"discarded_starts\": " << tc.discarded_starts
    << ", \"init_match_audit\": {\"matches\": " << tc.init_gt_matches
    << ", \"wrong\": " << tc.init_gt_wrong << ", \"start_matches\": " << tc.start_gt_matches
    << ", \"start_wrong\": " << tc.start_gt_wrong << "}"
    << ", \"last_init_refusal\": " << json_string(tc.last_init_refusal) << ", \"init_refused\": {";
  for (std::size_t i = 1; i < tc.init_frame_refusals.size(); ++i) {
    j << (i > 1 ? ", " : "")
      << json_string(frontend::to_string(static_cast<frontend::InitRefusal>(i))) << ": "
      << tc.init_frame_refusals[i];
  }
  j << "}, \"init_two_view_refused\": {";
  for (std::size_t i = 1; i < tc.init_two_view_refusals.size(); ++i) {
    j << (i > 1 ? ", " : "")
      << json_string(geometry::to_string(static_cast<geometry::TwoViewRefusal>(i))) << ": "
      << tc.init_two_view_refusals[i];
  }
  j << "}"
    << ", \"tracked\": " << tc.tracked << ", \"lost\": " << tc.lost
    << ", \"wide_searches\": " << tc.wide_searches
    << ", \"segment_start_waits\": " << tc.segment_start_waits
    << ", \"segment_starts_not_queued\": " << tc.segment_starts_not_queued
    << ", \"segment_starts_refused\": " << tc.segment_starts_refused;
  const double nt = tc.tracked > 0 ? static_cast<double>(tc.tracked) : 1.0;
  j << ", \"mean_inliers\": " << num(static_cast<double>(tc.sum_inliers) / nt)
    << ", \"mean_query_temporal\": " << num(static_cast<double>(tc.sum_query_temporal) / nt)
    << ", \"mean_query_spatial\": " << num(static_cast<double>(tc.sum_query_spatial) / nt)
    << ", \"mean_query_total\": " << num(static_cast<double>(tc.sum_query_total) / nt)
    << ", \"keyframe_reasons\": {";
  for (std::size_t i = 1; i < std::size(tc.keyframe_reasons); ++i) {
    j << (i > 1 ? ", " : "")
      << json_string(frontend::to_string(static_cast<frontend::KeyframeReason>(i))) << ": "
      << tc.keyframe_reasons[i];
  }
  j << "}},\n";
  j << "  \"tracking_steps_ms\": {";
  for (std::size_t i = 0; i < st.tracking_steps.size(); ++i) {
    const auto& l = st.tracking_steps[i];
    j << (i ? ", " : "") << json_string(l.name) << ": {\"p50\": " << num(l.p50_ms)
      << ", \"p99\": " << num(l.p99_ms) << ", \"mean\": " << num(l.mean_ms) << "}";
  }
  j << "},\n";
  const frontend::FocalReport& f = st.focal;
  j << "  \"focal\": {\"estimated\": " << (f.estimated ? "true" : "false")
    << ", \"initial\": " << num(f.initial) << ", \"value\": " << num(f.value)
    << ", \"fixed\": " << (f.fixed ? "true" : "false") << ", \"fixed_at_seq\": " << f.fixed_at_seq
    << ", \"estimates\": " << f.estimates << "},\n";
}

/// The focal length and keyframe creation, culling and map counters.
void write_focal_and_map(std::ostream& j, const pipeline::PipelineStats& st) {
  const depth::KeyframeBuildTotals& m = st.mapping;
  j << "  \"map\": {\"keyframes\": " << st.keyframes << ", \"points\": " << st.map_points
    << ", \"keyframes_deferred\": " << st.keyframes_deferred
    << ", \"depth_backend\": " << json_string(st.depth_backend)
    << ", \"keyframe_jobs\": " << m.keyframes << ", \"keyframe_failures\": " << m.failures
    << ", \"segment_starts\": " << m.segment_starts << ", \"start_points\": " << m.start_points
    << ", \"new_points\": " << m.new_points << ", \"observations\": " << m.observations
    << ", \"fused_observations\": " << m.fused_observations
    << ", \"merged_points\": " << m.merged_points
    << ", \"view_observations\": " << m.view_observations
    << ", \"aligned_keypoints\": " << m.aligned_keypoints
    << ", \"align_refused\": " << m.align_refused
    << ", \"align_refused_residual\": " << m.align_refused_residual
    << ", \"align_refused_shift\": " << m.align_refused_shift
    << ", \"depth_valid\": " << m.depth_valid << ", \"depth_missing\": " << m.depth_missing
    << ", \"depth_errors\": " << m.depth_errors
    << ", \"keypoint_fates\": {\"free\": " << m.fates.free << ", \"no_match\": " << m.fates.no_match
    << ", \"low_parallax\": " << m.fates.low_parallax << ", \"few_views\": " << m.fates.few_views
    << ", \"rejected\": " << m.fates.rejected << ", \"depth\": " << m.fates.depth
    << ", \"new_points\": " << m.new_points << "}"
    << ", \"live_keyframes\": " << st.map.live_keyframes
    << ", \"live_points\": " << st.map.live_points
    << ", \"keyframe_slots_used\": " << st.map.keyframe_slots_used
    << ", \"point_slots_used\": " << st.map.point_slots_used
    << ", \"culled_keyframes\": " << st.culling.culled_keyframes
    << ", \"culled_points\": " << st.culling.culled_points
    << ", \"culled_keyframes_at_capacity\": " << st.culling.capacity_keyframes
    << ", \"culled_points_at_capacity\": " << st.culling.capacity_points
    << ", \"discarded_keyframes\": " << st.culling.discarded_keyframes
    << ", \"bad_points\": " << st.map.bad_points
    << ", \"reused_keyframe_slots\": " << st.map.reused_keyframe_slots
    << ", \"reused_point_slots\": " << st.map.reused_point_slots << ", \"culling_mean_ms\": "
    << num(st.culling.runs ? st.culling.total_ms / static_cast<double>(st.culling.runs) : 0.0)
    << ", \"culling_max_ms\": " << num(st.culling.max_ms) << "},\n";
}

/// Local BA, loop closure and relocalization.
void write_backend_loop_relocalization(std::ostream& j, const pipeline::PipelineStats& st) {
  const frontend::TrackerCounters& tc = st.tracker;
  const backend::LocalBaTotals& ba = st.backend;
  j << "  \"backend\": {\"local_ba_runs\": " << ba.runs
    << ", \"culled_points\": " << ba.culled_points << ", \"outliers\": " << ba.outliers
    << ", \"depth_edge_mode\": " << json_string(st.backend_depth_edges)
    << ", \"depth_edges\": " << ba.depth_edges << ", \"aborted\": " << ba.aborted
    << ", \"timed_out\": " << ba.timed_out << ", \"overruns\": " << ba.overruns
    << ", \"resolves\": " << ba.resolves << ", \"resolves_skipped\": " << ba.resolves_skipped
    << ", \"mean_ms\": " << num(ba.runs ? ba.total_ms / static_cast<double>(ba.runs) : 0.0)
    << ", \"max_ms\": " << num(ba.max_ms) << ", \"stale_writes\": " << ba.stale_writes
    << ", \"lock_wait_mean_ms\": "
    << num(ba.runs ? ba.lock_wait_ms / static_cast<double>(ba.runs) : 0.0)
    << ", \"lock_wait_max_ms\": " << num(ba.max_lock_wait_ms)
    << ", \"coalesced_keyframes\": " << st.backend_coalesced;
  const auto nk = static_cast<double>(ba.new_keyframe_runs);
  j << ", \"new_keyframe_runs\": " << ba.new_keyframe_runs << ", \"new_keyframe_step_ratio\": "
    << num(ba.new_keyframe_runs ? std::exp(ba.sum_log_step_ratio / nk) : 1.0)
    << ", \"new_keyframe_shift\": " << num(ba.new_keyframe_runs ? ba.sum_shift_fraction / nk : 0.0)
    << ", \"new_keyframe_turn_deg\": " << num(ba.new_keyframe_runs ? ba.sum_rotation_deg / nk : 0.0)
    << "},\n";
  const loop::LoopTotals& lp = st.loop;
  j << "  \"loop\": {\"keyframes_checked\": " << lp.keyframes_checked
    << ", \"candidates_checked\": " << lp.candidates_checked
    << ", \"queue_full\": " << st.loop_queue_full << ", \"loops_closed\": " << lp.loops_closed
    << ", \"segments_merged\": " << lp.segments_merged
    << ", \"merges_by_relocalization\": " << lp.merges_by_relocalization
    << ", \"merged_points\": " << lp.merged_points << ", \"max_ms\": " << num(lp.max_ms)
    << ", \"max_full_ba_ms\": " << num(lp.max_full_ba_ms)
    << ", \"last_loop_seq\": " << lp.last_loop.loop_seq
    << ", \"last_inliers\": " << lp.last_loop.inliers
    << ", \"last_scale\": " << num(lp.last_loop.scale)
    << ", \"last_shift\": " << num(lp.last_loop.shift)
    << ", \"excluded_connected\": " << lp.excluded_connected
    << ", \"rejected\": {\"few_matches\": " << lp.rejected.few_matches
    << ", \"few_inliers\": " << lp.rejected.few_inliers << ", \"drift\": " << lp.rejected.drift
    << ", \"not_found\": " << lp.rejected.not_found << ", \"ambiguous\": " << lp.rejected.ambiguous
    << ", \"inconsistent\": " << lp.rejected.inconsistent
    << ", \"merge_refused\": " << lp.rejected.merge_refused
    << ", \"relocalized_fit\": " << lp.rejected.relocalized_fit << "}},\n";
  const pipeline::RelocalizationStats& rl = st.relocalization;
  j << "  \"relocalization\": {\"enabled\": " << (rl.enabled ? "true" : "false")
    << ", \"lost_spells\": " << tc.lost_spells << ", \"max_lost_frames\": " << tc.max_lost_frames
    << ", \"new_segments\": " << tc.new_segments << ", \"segment_returns\": " << tc.segment_returns
    << ", \"requests\": " << tc.relocalization_requests << ", \"attempts\": " << rl.attempts
    << ", \"successes\": " << rl.successes << ", \"resumed\": " << tc.relocalized
    << ", \"skipped_busy\": " << rl.skipped_busy << ", \"timed_out\": " << rl.timed_out
    << ", \"candidates\": " << rl.candidates << ", \"mean_ms\": "
    << num(rl.attempts > 0 ? rl.sum_ms / static_cast<double>(rl.attempts) : 0.0)
    << ", \"max_ms\": " << num(rl.max_ms) << ", \"last_success_seq\": " << rl.last_success_seq
    << ", \"trusted_at_once\": " << tc.relocalization_trusted
    << ", \"to_confirm\": " << tc.relocalization_candidates
    << ", \"confirmed\": " << tc.relocalization_confirmed
    << ", \"longer_checks\": " << tc.relocalization_longer_checks
    << ", \"rejected\": {\"lost_while_confirming\": " << tc.relocalization_rejected_lost
    << ", \"few_found_in_view\": " << tc.relocalization_rejected_found
    << ", \"outside_motion_bound\": " << tc.relocalization_rejected_bound
    << ", \"after_long_loss\": " << tc.relocalization_rejected_long_loss << "}},\n";
}

/// The ground-truth audit of relocalizations and loops.
void write_gt_audit(std::ostream& j, const RunInfo& info) {
  // Ground-truth audit of relocalizations and loops (when the source had ground truth).
  if (info.events.available) {
    const EventAuditReport& ev = info.events;
    j << "  \"gt_audit\": {\"wrong_relocalization_m\": " << num(kWrongRelocalizationM)
      << ", \"wrong_loop_m\": " << num(kWrongLoopM)
      << ", \"relocalizations\": " << ev.relocalizations
      << ", \"relocalizations_wrong\": " << ev.relocalizations_wrong << ", \"loops\": " << ev.loops
      << ", \"loops_wrong\": " << ev.loops_wrong << ", \"events\": [";
    for (std::size_t i = 0; i < ev.events.size(); ++i) {
      const EventAudit& e = ev.events[i];
      j << (i ? "," : "") << "\n    {\"kind\": " << json_string(e.kind) << ", \"seq\": " << e.seq
        << ", \"t_s\": " << num(e.t_s) << ", \"other_t_s\": " << num(e.other_t_s)
        << ", \"segment\": " << e.segment << ", \"scored\": " << (e.scored ? "true" : "false")
        << ", \"gt_distance_m\": " << num(e.gt_distance_m) << ", \"error_m\": " << num(e.error_m)
        << ", \"error_deg\": " << num(e.error_deg)
        << ", \"wrong\": " << (e.wrong ? "true" : "false");
      if (e.kind == "relocalization") {
        j << ", \"confirmed\": " << (e.confirmed ? "true" : "false")
          << ", \"found_ratio\": " << num(e.found_ratio);
      }
      if (e.kind == "loop") {
        j << ", \"found_new\": " << num(e.found_new) << ", \"found_old\": " << num(e.found_old)
          << ", \"found_usual\": " << num(e.found_usual) << ", \"inliers\": " << e.inliers
          << ", \"rival_inliers\": " << e.rival_inliers << ", \"drift\": " << num(e.drift)
          << ", \"connected\": " << (e.connected ? "true" : "false");
      }
      j << "}";
    }
    j << (ev.events.empty() ? "" : "\n  ") << "]},\n";
  }
}

/// How the run ended, the source's counters and the threads.
void write_run_end(std::ostream& j, const pipeline::PipelineStats& st, const RunInfo& info) {
  j << "  \"end_reason\": " << json_string(st.end_reason) << ",\n";
  j << "  \"stopped_by_signal\": " << (info.stopped_by_signal ? "true" : "false") << ",\n";
  j << "  \"pool_exhausted\": " << st.pool_exhausted << ",\n";
  j << "  \"output_overflows\": " << st.output_overflows << ",\n";
  j << "  \"acquire_timeouts\": " << st.acquire_timeouts << ",\n";
  j << "  \"source_counters\": {\"skipped\": " << st.source.skipped
    << ", \"error_frames\": " << st.source.error_frames << ", \"seq_gaps\": " << st.source.seq_gaps
    << ", \"restarts\": " << st.source.restarts << ", \"damage\": " << json_string(st.source.damage)
    << "},\n";
  j << "  \"threads\": [";
  for (std::size_t i = 0; i < st.threads.size(); ++i) {
    const auto& t = st.threads[i];
    j << (i ? "," : "") << "\n    {\"name\": " << json_string(t.thread) << ", \"core\": " << t.core
      << ", \"priority\": " << t.priority << ", \"applied\": " << (t.applied ? "true" : "false")
      << ", \"note\": " << json_string(t.note) << ", \"cpu_s\": " << num(t.cpu_s) << "}";
  }
  j << (st.threads.empty() ? "" : "\n  ") << "],\n";
  j << "  \"error\": " << json_string(info.error) << "\n";
}

}  // namespace

std::string summary_json(const pipeline::PipelineStats& st, const RunInfo& info) {
  std::ostringstream j;
  j << "{\n";
  write_frames(j, st);
  write_run(j, st, info);
  write_segments(j, st, info);
  write_final_and_gt_check(j, st, info);
  write_tracking(j, st);
  write_focal_and_map(j, st);
  write_backend_loop_relocalization(j, st);
  write_gt_audit(j, info);
  write_run_end(j, st, info);
  j << "}\n";
  return j.str();
}

Status write_file_atomic(const std::string& path, const std::string& text) {
  const std::string tmp = path + ".tmp";
  std::FILE* f = std::fopen(tmp.c_str(), "w");
  if (f == nullptr) return runtime_error("cannot write '" + tmp + "': " + std::strerror(errno));
  const bool ok = std::fwrite(text.data(), 1, text.size(), f) == text.size();
  if (std::fclose(f) != 0 || !ok) return runtime_error("error writing '" + tmp + "'");
  std::error_code ec;
  std::filesystem::rename(tmp, path, ec);
  if (ec) return runtime_error("cannot rename '" + tmp + "' to '" + path + "': " + ec.message());
  return Status::ok();
}

void print_summary(std::ostream& os, const pipeline::PipelineStats& st, const RunInfo& info) {
  os << "mer_slam: " << info.source << " [" << st.mode << ", " << to_string(info.sensor_mode)
     << "]\n";
  os << "  frames: in " << st.frames_in << ", processed " << st.frames_processed << ", dropped "
     << st.frames_dropped << ", lost " << st.frames_lost << ", keyframes " << st.keyframes << "  ("
     << st.end_reason << ", " << std::fixed << std::setprecision(2) << st.wall_time_s << " s)\n";
  os << "  poses: " << st.pose_source << "; map: " << st.keyframes << " keyframes, "
     << st.map_points << " points";
  if (st.focal.estimated) os << "; focal " << std::setprecision(2) << st.focal.value << " px";
  os << "\n";
  if (st.mapping.depth_missing > 0 || st.mapping.depth_errors > 0) {
    os << "  keyframe depth (" << st.depth_backend << "): " << st.mapping.depth_missing
       << " keyframes without input, " << st.mapping.depth_errors << " failed (see warnings)\n";
  }
  if (info.accuracy.available) {
    const AccuracyReport& a = info.accuracy;
    os << "  ATE (" << a.alignment << ", " << a.pairs << " poses): rmse " << std::setprecision(4)
       << a.ate_rmse_m << " m = " << std::setprecision(3) << a.ate_pct_of_path << " % of "
       << std::setprecision(2) << a.path_length_m << " m path; tracked " << std::setprecision(1)
       << a.tracked_after_init_pct << " % after init\n";
    if (a.start_pairs > 0) {
      os << "  ATE of the first " << std::setprecision(2) << kStartWindowS << " s ("
         << a.start_pairs << " poses, aligned on their own): rmse " << std::setprecision(4)
         << a.start_ate_rmse_m << " m = " << std::setprecision(3) << a.start_ate_pct_of_path
         << " % of " << std::setprecision(2) << a.start_path_length_m << " m path\n";
    }
  } else {
    os << "  ATE: " << info.accuracy.note << "\n";
  }
  if (st.segments.size() > 1 || (st.segments.size() == 1 && st.segments[0].id != 0)) {
    os << "  map segments:";
    for (const pipeline::SegmentStats& g : st.segments) {
      os << " " << g.id << ": " << g.frames << " frames";
      if (g.discarded) {
        os << " (discarded: a failed start)";
      } else if (g.merged_into >= 0) {
        os << " (merged into " << g.merged_into << " at frame " << g.merged_at_seq << ")";
      } else {
        os << " (" << g.trajectory << ")";
      }
    }
    os << "\n";
  }
  if (info.accuracy_keyframes.available) {
    const AccuracyReport& a = info.accuracy_keyframes;
    os << "  keyframe ATE (final map, " << a.pairs << " keyframes): rmse " << std::setprecision(4)
       << a.ate_rmse_m << " m = " << std::setprecision(3) << a.ate_pct_of_path << " % of path\n";
  }
  if (st.relocalization.attempts > 0) {
    os << "  relocalization: " << st.relocalization.attempts << " attempts, "
       << st.relocalization.successes << " found a pose, " << st.tracker.relocalized
       << " resumed tracking\n";
  }
  if (st.loop.loops_closed > 0) {
    os << "  loops closed: " << st.loop.loops_closed << " (last onto frame "
       << st.loop.last_loop.loop_seq << ", scale " << std::setprecision(4)
       << st.loop.last_loop.scale << ", " << st.loop.merged_points << " points merged)\n";
  }
  if (info.events.available && !info.events.events.empty()) {
    const EventAuditReport& ev = info.events;
    os << "  against the ground truth: " << ev.relocalizations_wrong << " of " << ev.relocalizations
       << " relocalizations more than " << kWrongRelocalizationM << " m off, " << ev.loops_wrong
       << " of " << ev.loops << " loops more than " << kWrongLoopM << " m off\n";
  }
  if (info.accuracy_final.available) {
    const AccuracyReport& a = info.accuracy_final;
    os << "  ATE (final map, every frame re-anchored" << (st.final_ba.ran ? ", after final BA" : "")
       << "): rmse " << std::setprecision(4) << a.ate_rmse_m << " m = " << std::setprecision(3)
       << a.ate_pct_of_path << " % of path\n";
  }
  if (info.gt_check_requested) {
    const eval::GroundTruthCheckReport& g = info.gt_check;
    if (!g.ran) {
      os << "  ground-truth check: " << g.note << "\n";
    } else {
      os << "  ground-truth check (" << g.observations << " observations of " << g.points
         << " points): keypoint error RMS per level";
      for (const auto& l : g.levels) os << " " << std::setprecision(2) << l.rms_level_px;
      os << " level px; " << std::setprecision(1) << 100.0 * g.beyond_1_level_px << " % beyond 1, "
         << 100.0 * g.beyond_2_level_px << " % beyond 2\n"
         << "    anchored keypoints: " << g.anchored_observations << " observations, RMS "
         << std::setprecision(2) << g.anchored_rms_level_px << " level px (the others "
         << g.detected_rms_level_px << ")\n";
      const AccuracyReport& c = info.accuracy_gt_converged;
      const AccuracyReport& s = info.accuracy_gt_shuffled;
      if (c.available && s.available) {
        os << "    full BA from the truth: keyframe ATE " << std::setprecision(3)
           << c.ate_pct_of_path << " % of path; keypoint errors shuffled: " << s.ate_pct_of_path
           << " %";
        const AccuracyReport& sd = info.accuracy_gt_shuffled_detected;
        if (sd.available) os << "; only detected ones shuffled: " << sd.ate_pct_of_path << " %";
        os << "\n";
      }
    }
  }
  os << "  latency ms      p50      p90      p99      max   budget  overruns\n";
  for (const auto& l : st.latency) {
    os << "  " << std::left << std::setw(12) << l.name << std::right << std::fixed
       << std::setprecision(3) << std::setw(9) << l.p50_ms << std::setw(9) << l.p90_ms
       << std::setw(9) << l.p99_ms << std::setw(9) << l.max_ms << std::setw(9) << l.budget_ms
       << std::setw(10) << l.overruns << "\n";
  }
  os << "  heap allocations per frame (steady state):";
  for (const auto& a : st.allocs) {
    os << " " << a.thread << " " << std::setprecision(2) << a.per_frame();
  }
  os << "\n";
  const pipeline::CpuStats& cpu = st.cpu;
  if (cpu.process.count > 0) {
    os << "  CPU ms per frame: p50 " << std::setprecision(1) << cpu.slam.p50_ms << ", mean "
       << cpu.slam.mean_ms << " (with the source's own work: p50 " << cpu.process.p50_ms
       << ", mean " << cpu.process.mean_ms << ")\n";
  }
  const hal::SourceCounters& sc = st.source;
  if (sc.skipped || sc.error_frames || sc.seq_gaps || sc.restarts) {
    os << "  source: skipped " << sc.skipped << ", error frames " << sc.error_frames
       << ", sequence gaps " << sc.seq_gaps << ", restarts " << sc.restarts << "\n";
  }
  if (!sc.damage.empty()) os << "  input damage: " << sc.damage << "\n";
  if (st.pool_exhausted || st.output_overflows) {
    os << "  pool exhausted " << st.pool_exhausted << ", output overflows " << st.output_overflows
       << "\n";
  }
  for (const auto& t : st.threads) {
    if (!t.applied) os << "  note: thread '" << t.thread << "': " << t.note << "\n";
  }
  if (!info.error.empty()) os << "  error: " << info.error << "\n";
}

}  // namespace mer::app
