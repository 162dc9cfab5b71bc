#pragma once
/// @file output_stage.h
/// The output stage: `spin_once(TrackingResult)` appends one frame's records to the output
/// files. Files are opened before start (so errors surface early) and flushed every
/// `flush_every` frames and at close, so a stop loses nothing already processed. The stage
/// only appends; after the run the pipeline rewrites the segment files once
/// (segment_outputs.h: merged segments joined, discarded ones removed).
///
/// Files (in the --output directory):
/// - trajectory.txt  TUM `t tx ty tz qx qy qz qw`, camera-to-world, every frame tracked in
///                   map segment 0 (the first map)
/// - keyframes.txt   same format, keyframes only (segment 0)
/// - trajectory_segment_N.txt, keyframes_segment_N.txt: the same for map segment N >= 1
///                   (tracking.new_segments), each in that segment's own world frame; created
///                   when the segment tracks its first frame (files of an earlier run removed)
/// - groundtruth.txt same format, the true pose of every frame whose source knew it
/// - frame_anchors.txt `t kf_t segment tx ty tz qx qy qz qw`: every tracked frame's pose
///                   (any segment) relative to the keyframe (stamp kf_t) it was anchored to,
///                   T_kf_c, in the units of the segment it was tracked in; kf_t is `-` and
///                   the pose T_w_c for a frame tracked before any keyframe existed. mer_slam
///                   re-anchors those of trajectory.txt to the final map (final_trajectory.h).
/// - frames.csv      `seq,t_s,state,keyframe,features,feature_hash,matches,inliers,query_t,
///                   query_s,query_total,keyframe_reason,kl,focal,tracker_state,segment` for every
///                   processed frame
/// - latency.csv     `seq,t_s,capture_ms,queue_ms,tracking_ms,end_to_end_ms,output_ms`
/// - orientation.txt TUM lines, translation 0, of the frames with a known orientation before a
///                   map (tracker_state initializing_rotation: pure rotations of the
///                   initializer's reference; TrackingResult::has_orientation), camera-to-world
///                   in the world of their chain of references. A `# chain N` line opens each
///                   chain: chains do not share a world. Their positions are not known.
/// (keyframes.csv, one line per keyframe created, is written by the pipeline from the
/// keyframe thread: `seq,t_s,segment,keypoints,tracked,free,no_match,low_parallax,few_views,
/// rejected,depth,new_points,neighbours`, depth/depth_inference.h KeypointFates.)

#include <cstdint>
#include <cstdio>
#include <string>
#include <vector>

#include "core/status.h"
#include "frontend/tracking_result.h"
#include "pipeline/pipeline_options.h"

namespace mer::pipeline {

/// Writes per-frame results. Single thread; the files are plain stdio with large buffers.
class OutputStage {
 public:
  OutputStage() = default;
  OutputStage(const OutputStage&) = delete;
  OutputStage& operator=(const OutputStage&) = delete;
  ~OutputStage();

  /// Opens (truncates) the files in `dir`; an empty `dir` makes the stage a no-op sink.
  Status open(const std::string& dir, const OutputOptions& opts);

  /// Appends one frame. `end_to_end_ns` is frame-ready to tracking-result latency.
  /// Returns the time spent writing, ns.
  std::int64_t spin_once(const frontend::TrackingResult& r, std::int64_t end_to_end_ns);

  /// Flushes and closes every file; reports the first write error (disk full, ...).
  Status close();

  /// Frames written so far.
  std::uint64_t frames_written() const { return frames_; }

 private:
  struct File {
    std::FILE* f = nullptr;
    std::string path;
  };
  Status open_file(File& file, const std::string& path, const char* header);
  // The trajectory and keyframe files of segment s >= 1 (opened on first use; null on error).
  File* segment_file(std::uint16_t s, bool keyframes);
  void flush_all();

  OutputOptions opts_;
  File trajectory_;
  File keyframes_;
  File ground_truth_;  // true poses of the frames whose source knew them
  File anchors_;       // tracked frames relative to their anchor keyframe
  File frames_csv_;
  File latency_csv_;
  File orientation_;                     // frames of known orientation before a map
  std::uint32_t orientation_chain_ = 0;  // chain of the last orientation line
  bool orientation_written_ = false;     // a chain line has been written
  std::string dir_;
  std::vector<File> segment_files_;  // [2 (s - 1)]: trajectory, [2 (s - 1) + 1]: keyframes
  std::uint64_t frames_ = 0;
  bool write_error_ = false;
};

/// Seconds with 9 decimals from integer nanoseconds, exact at any epoch (a double holds only
/// ~0.2 us at 1.4e9 s). Writes into `buf` (no allocation); returns the length.
int format_seconds(char* buf, std::size_t size, std::int64_t t_ns);
/// Formats a pose line in TUM format into `buf` (no allocation); returns its length.
int format_tum_line(char* buf, std::size_t size, std::int64_t t_ns, const SE3d& T_w_c);
/// Formats a frame_anchors.txt line of a frame tracked in `segment` (`anchor_t_ns` null: no
/// anchor, `T` is T_w_c).
int format_anchor_line(char* buf, std::size_t size, std::int64_t t_ns,
                       const std::int64_t* anchor_t_ns, std::uint16_t segment, const SE3d& T);

}  // namespace mer::pipeline
