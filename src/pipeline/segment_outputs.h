#pragma once
/// @file segment_outputs.h
/// After a run whose map segments merged (loop.merge_segments), the per-segment trajectory
/// files are joined like the map was: the frames of a merged segment move into the frame of
/// the segment it joined and are written with its frames, in time order. They move by the
/// similarity that best takes the segment's keyframes as tracked onto their final poses in
/// the main segment (a least-squares fit over them: the merge's similarity holds where the
/// loop was found, the fit over the whole segment after the map's optimization), when that
/// fit explains the keyframes' positions and orientations no worse than the merges' own
/// similarities; otherwise by the merges' similarities. `trajectory.txt` / `keyframes.txt` then
/// hold the main segment (the one with the most frames after merging; segment 0 on a tie), each
/// segment that never merged keeps its own `trajectory_segment_N.txt` (segment 0, when it is not
/// the main one, `..._segment_0.txt`) and the files of merged segments are removed. Runs after the
/// output stage closed its files; without a merge nothing is rewritten. A discarded segment (a
/// failed start) is never the main one and its files are removed (segment 0's: trajectory.txt then
/// holds the main segment, or nothing when no segment was kept).

#include <cstdint>
#include <functional>
#include <span>
#include <string>
#include <vector>

#include "core/status.h"
#include "geometry/sim3.h"
#include "pipeline/final_trajectory.h"

namespace mer::pipeline {

/// One merge, as the loop closer reported it.
struct SegmentMergeRecord {
  std::uint16_t from = 0;         ///< the segment that moved
  std::uint16_t into = 0;         ///< the segment it joined
  std::uint64_t seq = 0;          ///< frame whose keyframe found the other segment
  geometry::Sim3d sim_into_from;  ///< world of `from` -> world of `into`
};

/// A segment's frames after merging (SegmentStats gets these fields).
struct SegmentOutput {
  std::uint16_t id = 0;
  std::uint64_t frames = 0;         ///< frames tracked in it (by id, as run)
  int merged_into = -1;             ///< the segment it finally joined, -1 if none
  std::uint64_t merged_at_seq = 0;  ///< frame of its (first) merge
  bool discarded = false;           ///< a failed start: its frames are not written
  std::string trajectory;           ///< file holding its frames after merging ("" if discarded)
  int fit_keyframes = 0;            ///< merged: keyframes its similarity was fitted to (0: it
                                    ///< moved by the merges' similarities)
};

/// The final poses of the main segment's keyframes (live ones and culled ones resolved
/// through their lineage, final_trajectory.h), sorted by time, given the main segment's id.
using FinalKeyframesOf = std::function<std::vector<FinalKeyframePose>(std::uint16_t main)>;

/// Keyframes a merged segment needs in the final map for its frames to move by a fitted
/// similarity.
inline constexpr std::size_t kMinFitKeyframes = 3;

/// File names a segment's frames are written to during the run (`trajectory`: trajectory or
/// keyframes files).
std::string segment_file_name(std::uint16_t segment, bool keyframes);

/// Joins the segment files of `dir` along `merges` (in the order they happened). `segments`
/// lists every segment that tracked a frame (id and frames set); on return each says where
/// its frames are and which segment it merged into. `main` gets the main segment.
/// `final_keyframes` (empty: none) gives the keyframes the fitted similarities are fitted to.
/// Error (naming the file) when a file cannot be read or written; files are replaced
/// atomically (written beside, then renamed), so a failure loses nothing already written.
Status join_segment_files(const std::string& dir, std::span<const SegmentMergeRecord> merges,
                          std::vector<SegmentOutput>& segments, std::uint16_t& main,
                          const FinalKeyframesOf& final_keyframes = {});

/// Per segment id (`segments` of them), the scale from that segment's units into those of
/// segment `main` along `merges` (in the order they happened): 1 for `main`, the product of
/// the merges' scales for a segment that joined it (directly or through others), 0 for a
/// segment that did not.
std::vector<double> segment_scales_into(std::span<const SegmentMergeRecord> merges,
                                        std::uint16_t main, std::size_t segments);

}  // namespace mer::pipeline
