#pragma once
/// @file keyframe_builder.h
/// The keyframe-creation stage, `spin_once(KeyframeJob) -> KeyframeBuildReport`: picks the
/// neighbouring keyframes (those sharing the most tracked points), runs depth inference on
/// the new keyframe, aligns the depth's scale to the map with the keyframe's 3D-2D matches
/// (robust median ratio) when the backend is not already in map units, inserts the keyframe,
/// its observations of tracked map-points (3D-2D edges), new map-points from confident depth
/// where no map-point is associated (3D-3D local points), and refreshes the covisibility
/// (keyframe-keyframe edges). With depth.align_keypoints it first moves the keypoints of
/// tracked points onto the points' anchor patches (features/patch_align.h) and gives points
/// without one an anchor from the new keyframe. spin_once holds the map's writer lock (map.h) for
/// the whole pass, depth inference included. Runs on its own low-priority thread in threaded mode
/// (the local BA and culling run on the back-end thread); tracking never waits for it.

#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include <Eigen/Geometry>
#include <opencv2/core/mat.hpp>

#include "core/sensor_mode.h"
#include "core/status.h"
#include "depth/depth_inference.h"
#include "depth/depth_map_source.h"
#include "depth/depth_options.h"
#include "features/patch_align.h"
#include "map/keyframe_job.h"
#include "map/map.h"

namespace mer::depth {

/// What one keyframe creation did.
struct KeyframeBuildReport {
  bool ok = false;             ///< a tracked keyframe was inserted (local BA and culling follow)
  bool segment_start = false;  ///< the job was a segment's start (inserted as initialization
                               ///< made it; no local BA or culling follows)
  std::uint32_t keyframe = 0xFFFFFFFFu;  ///< new keyframe id
  int tracked_observations = 0;          ///< 3D-2D edges from tracked map-points
  int fused_observations = 0;            ///< of these, found by projecting covisible points
  int merged_points = 0;                 ///< duplicate points merged (depth.fuse_merge_duplicates)
  int depth_valid = 0;                   ///< keypoints that got a depth
  int new_points = 0;                    ///< map-points created
  int view_observations = 0;       ///< observations of new points in other agreeing neighbours
  int aligned_keypoints = 0;       ///< keypoints moved onto their point's anchor (align_keypoints)
  int align_refused = 0;           ///< alignments tried and refused (detection kept); of these:
  int align_refused_residual = 0;  ///< not converged or above depth.align_max_rms
  int align_refused_shift = 0;     ///< moved farther than depth.align_max_shift_px
  int neighbours = 0;              ///< views given to depth inference
  int scale_samples = 0;           ///< 3D-2D matches used for the scale ratio
  double scale_ratio = 1.0;        ///< map depth / inferred depth (median)
  bool scale_applied = false;      ///< the ratio was applied to the depth
  KeypointFates fates;             ///< what became of the keypoints that were not map-points
};

/// Totals over the run (summary.json `mapping`).
struct KeyframeBuildTotals {
  std::uint64_t keyframes = 0;
  std::uint64_t failures = 0;  ///< jobs that could not be inserted (map full, ...)
  std::uint64_t new_points = 0;
  std::uint64_t observations = 0;
  std::uint64_t fused_observations = 0;  ///< of these, found by projection (depth.fuse_keyframes)
  std::uint64_t merged_points = 0;       ///< duplicates merged (depth.fuse_merge_duplicates)
  std::uint64_t view_observations = 0;   ///< of new points, beyond their first two views
  std::uint64_t aligned_keypoints = 0;   ///< keypoints aligned to their point's anchor patch
  std::uint64_t align_refused = 0;       ///< alignments refused (detection kept); of these:
  std::uint64_t align_refused_residual = 0;  ///< not converged or above align_max_rms
  std::uint64_t align_refused_shift = 0;     ///< moved farther than align_max_shift_px
  std::uint64_t depth_valid = 0;
  std::uint64_t depth_missing = 0;        ///< keyframes the backend had no input for (no depth map)
  std::uint64_t depth_errors = 0;         ///< keyframes whose depth inference failed otherwise
  std::uint64_t merged_segment_jobs = 0;  ///< tracked in a segment merged since: moved first
  std::uint64_t segment_starts = 0;       ///< segments' first keyframes and points inserted
  std::uint64_t start_points = 0;         ///< points those starts brought
  BasicKeypointFates<std::uint64_t> fates;  ///< what became of the free keypoints (new_points:
                                            ///< those that became map-points)
  double total_ms = 0.0;
  double max_ms = 0.0;
};

/// Keyframe creation + depth inference.
class KeyframeBuilder {
 public:
  /// `level_sigma2` is the keypoint variance per pyramid level.
  /// `metric_depth_sigma_rel` > 0: with metric (sensor) depth, structure refinement also fits
  /// each observing keyframe's depth, with this sigma as a fraction of the depth at
  /// confidence 1 (the back end's 3D-3D edge sigma, so both weigh depth alike).
  /// `depth_maps`: the maps of the `external` backend (must outlive the builder; may be null
  /// for the other backends).
  KeyframeBuilder(const DepthOptions& opts, SensorMode mode, map::Map& map,
                  std::vector<float> level_sigma2, double metric_depth_sigma_rel = 0.0,
                  DepthMapSource* depth_maps = nullptr);

  /// Creates the backend; error when the option names a backend the mode cannot run, or
  /// `external` without a depth map source.
  Status init();

  /// Creates one keyframe, or inserts a segment's start (KeyframeJobKind::kSegmentStart: its
  /// keyframes and points as given, then Map::publish_segment_start). Takes the map's writer
  /// lock (the caller must not hold it).
  KeyframeBuildReport spin_once(const map::KeyframeJob& tracked);

  const KeyframeBuildTotals& totals() const { return totals_; }
  std::string_view backend_name() const { return backend_ ? backend_->name() : "none"; }
  /// The backend in use (`auto` resolved by the mode); kAuto before init().
  DepthBackend backend() const { return backend_kind_; }
  /// Keyframe depth is metric sensor depth in a metric (RGB-D) map: the back end may use it
  /// as is (3D-3D edges without a per-keyframe scale).
  bool metric_map_depth() const {
    return backend_ && backend_->scale() == DepthScale::kMetric && rgbd_;
  }

 private:
  /// `tracked`, or when its segment merged into another since it was tracked, a copy (merged_job_)
  /// in the frame and segment it joined. Writer-lock holders only.
  const map::KeyframeJob& resolve_merged_segment(const map::KeyframeJob& tracked);
  /// Writes a segment's start (kind kSegmentStart) and publishes it. Writer-lock holders only.
  KeyframeBuildReport insert_segment_start(const map::KeyframeJob& job);
  // The steps of spin_once, in order (keyframe_builder.cpp).
  /// The job's keypoints and tracked points into kps_ / ids_ (points culled since: none).
  void load_job(const map::KeyframeJob& job);
  /// The neighbours as depth views, the request and the backend's depth (depth_, confidence_,
  /// supports); rep gets the neighbours, valid depths and keypoint fates.
  DepthResult infer_depth(const map::KeyframeJob& job, KeyframeBuildReport& rep);
  /// Scales depth_ into map units by the tracked points (a backend of unknown scale).
  void align_depth_scale(const map::KeyframeJob& job, KeyframeBuildReport& rep);
  /// Adds the keyframe with its local depth; kNoId (counted, logged) when the map refuses.
  map::KeyframeId insert_keyframe(const map::KeyframeJob& job);
  /// The tracked points' observations, new points from confident depth, their refinement
  /// and covisibility, the photometric anchors.
  void add_structure(const map::KeyframeJob& job, map::KeyframeId kf, const DepthResult& out,
                     KeyframeBuildReport& rep);
  void add_to_totals(const KeyframeBuildReport& rep, double ms);
  /// The newest live keyframe of `segment` (kNoId when it has none yet).
  map::KeyframeId newest_in_segment(std::uint16_t segment) const;
  void pick_neighbours(const map::KeyframeJob& job);
  void refine_point(std::uint32_t p, const geometry::Pinhole& K);
  int fuse_local_points(const map::KeyframeJob& job);
  // Keypoint position variance at pyramid `level` (clamped to the known levels; 1 without).
  double level_sigma2(int level) const;
  // Whether point keep's position reprojects within the chi2 gate onto every keypoint that
  // observes point drop (a merge must not bend any observation).
  bool explains_observations(std::uint32_t keep, std::uint32_t drop, const geometry::Pinhole& K);
  // depth.align_keypoints (keyframe_alignment.cpp). The new keyframe's pyramid goes into the
  // ring of recent keyframe
  // images; its keypoints of points with an anchor are aligned to the anchor before
  // insertion; after it every point of the keyframe without an anchor (new points among
  // them) gets one here, and the new points' observations in older keyframes still in the
  // ring are aligned to it.
  struct Anchor;
  // kRefused: the geometry (point behind a view, warp too anisotropic or leaving the anchor,
  // patch leaving the image or without texture).
  enum class AlignOutcome : std::uint8_t { kAligned, kRefused, kRefusedResidual, kRefusedShift };
  void build_pyramid(const cv::Mat& gray);
  const std::vector<cv::Mat>* keyframe_levels(map::KeyframeId kf) const;
  // Keypoint position in pixels of pyramid level l of the keyframe images.
  Eigen::Vector2f to_level(const features::Keypoint& kp, std::size_t l) const;
  bool sample_anchor(const std::vector<cv::Mat>& levels, const features::Keypoint& kp,
                     const SE3d& T_w_a, const Eigen::Vector3d& p_w, double fx, Anchor& out) const;
  AlignOutcome align_to_anchor(const Anchor& a, const std::vector<cv::Mat>& levels,
                               const Eigen::Vector3d& p_w, const SE3d& T_c_w,
                               const geometry::Pinhole& K, features::Keypoint& kp) const;
  static void count(AlignOutcome o, KeyframeBuildReport& rep);
  void align_tracked(const map::KeyframeJob& job, KeyframeBuildReport& rep);
  void set_anchors(const map::KeyframeJob& job, map::KeyframeId kf);
  void align_new_observations(const geometry::Pinhole& K, KeyframeBuildReport& rep);

  // A point's appearance where a keyframe first observed it (depth.align_keypoints).
  struct Anchor {
    features::AnchorPixels pixels{};
    Eigen::Vector2f centre = Eigen::Vector2f::Zero();           // the keypoint in patch coordinates
    Eigen::Quaternionf q_w_a = Eigen::Quaternionf::Identity();  // anchor camera rotation
    float m_px = 0.0F;  // world size of an anchor pixel at the point (fronto-parallel plane)
    map::KeyframeId kf = map::kNoId;                 // the anchor keyframe
    map::Generation kf_gen = map::kNoGeneration;     // its occupant
    map::Generation point_gen = map::kNoGeneration;  // the point the anchor belongs to
    std::int8_t level = 0;                           // pyramid level sampled
  };

  DepthOptions opts_;
  bool rgbd_;              ///< sensor mode is rgbd
  bool merge_duplicates_;  ///< fuse_merge_duplicates resolved for the mode
  DepthBackend backend_kind_ = DepthBackend::kAuto;  ///< backend in use (set by init())
  map::Map& map_;
  std::vector<float> level_sigma2_;
  double metric_depth_sigma_rel_;
  DepthMapSource* depth_maps_;
  bool fit_depth_ = false;  // refinement fits metric keyframe depth
  std::unique_ptr<DepthInference> backend_;
  KeyframeBuildTotals totals_;
  map::KeyframeJob merged_job_;  // resolve_merged_segment's copy (buffers reused)
  // scratch
  std::vector<std::uint32_t> neighbour_ids_;
  std::vector<std::vector<std::uint32_t>> neighbour_points_;
  std::vector<DepthView> views_;
  std::vector<RecentView> recent_;
  std::vector<float> depth_;
  std::vector<float> confidence_;
  std::vector<std::uint32_t> support_view_;
  std::vector<std::uint32_t> support_kp_;
  std::vector<std::uint32_t> view_kp_;  // agreeing keypoint per [keypoint][view]
  std::vector<double> ratios_;
  std::vector<std::uint32_t> touched_;
  std::vector<std::pair<std::uint32_t, std::uint32_t>> obs_;
  std::vector<SE3d> obs_pose_;
  std::vector<Eigen::Vector2d> obs_uv_;
  std::vector<double> obs_w_;
  std::vector<double> obs_depth_;           // keyframe depth of the observation (0: none)
  std::vector<double> obs_depth_w_;         // 1 / depth sigma^2
  std::vector<std::uint32_t> ids_;          // job.point_ids plus the fused associations
  std::vector<int> fuse_dist_;              // descriptor distance of a fused association
  int merged_ = 0;                          // duplicates merged by the last fuse_local_points
  std::vector<std::uint32_t> fuse_points_;  // candidate points of the projection
  std::vector<std::uint32_t> fuse_kfs_;     // keyframes they come from
  std::vector<features::Keypoint> kps_;     // the job's keypoints, aligned
  std::vector<Anchor> anchors_;             // per point slot (align_keypoints)
  // A recent keyframe's image pyramid (align_keypoints).
  struct KeyframeImage {
    std::vector<cv::Mat> levels;
    map::KeyframeId kf = map::kNoId;
    map::Generation gen = map::kNoGeneration;
  };
  std::vector<KeyframeImage> images_;  // ring; images_[image_next_]: the new keyframe
  std::size_t image_next_ = 0;
  struct NewObservation {
    std::uint32_t point;
    map::KeyframeId kf;
    std::uint32_t kp;
  };
  std::vector<NewObservation> new_obs_;  // new points' observations in older keyframes
  std::vector<double> level_to_x0_;      // level px -> level-0 px, per level
  std::vector<double> level_to_y0_;
};

}  // namespace mer::depth
