#pragma once
/// @file relocalizer.h
/// Relocalization: the tracker lost the map (occlusion, fast motion, kidnap); find where a
/// frame is from the map alone, with no pose prior.
///
///  1. Retrieval: the frame's descriptors query the KeyframeDatabase for the
///     `max_candidates` best-scoring live keyframes (keyframe_database.h).
///  2. For each candidate, best first, until one succeeds or `max_time_ms` is spent: the map
///     points of the candidate and of its `match_neighbours` most covisible keyframes are
///     matched to the frame's keypoints by descriptor (the point's representative descriptor;
///     nearest keypoint within `max_descriptor_distance`, best / second best <= `ratio`, one
///     point per keypoint). With `min_matches`, P3P-RANSAC (geometry::PnpRansac, the front
///     end's solver, `pnp`) finds T_c_w.
///  3. Refinement: the points of the local map (the candidate and its `local_keyframes` most
///     covisible keyframes) are projected with that pose; each is matched to the keypoints
///     within `search_radius_px` x the keypoint's level scale (Hamming <=
///     `max_projection_distance`, one point per keypoint), the pose is re-solved by robust
///     Gauss-Newton on those matches (geometry::refine_pose) and the inliers counted (chi-square
///     2 dof 95 % at the keypoint's sigma), twice (the second pass on the inliers of the
///     first). Success needs `min_inliers` refined inliers; otherwise the next candidate.
///
/// A frame of a place the map does not hold finds too few matches or inliers: success = false
/// and no pose (T_c_w is only meaningful when success is true).
///
/// Real time: every buffer is sized in the constructor from the options and the map's
/// capacities; spin_once() does not allocate, lock or block. Its work is bounded by
/// max_candidates x (match + RANSAC + projection) and it stops starting candidates once
/// max_time_ms has passed (a started candidate finishes: its cost is bounded by the options;
/// in lockstep the budget is not applied, so replays do not depend on the machine's load).
///
/// Threading contract: the relocalizer reads the map only through the lock-free reader group
/// (descriptors, keypoint -> point associations, read_point, covisible_keyframes), never
/// keypoint positions or writer-side state, so it can run on any thread without the writer
/// lock. Threaded: give it a map reader handle (Map::register_reader(), a setup call); it
/// announces a quiescent point at the start of each spin_once. Lockstep: call it inline with
/// map_reader = -1. The KeyframeDatabase it queries (the loop closer's) is refreshed by
/// spin_once (new keyframes keyed, reused slots re-keyed) under the database's lock, so the
/// loop closer may use it from another thread. One Relocalizer per thread (scratch buffers).

#include <cstdint>
#include <memory>
#include <span>
#include <vector>

#include <Eigen/Core>

#include "core/options.h"
#include "core/pose.h"
#include "features/keypoint.h"
#include "geometry/camera_model.h"
#include "geometry/pnp.h"
#include "loop/keyframe_database.h"
#include "map/map.h"

namespace mer::loop {

/// Options of relocalization (config section `relocalization`).
struct RelocalizerOptions {
  bool enabled = true;
  int max_candidates = 5;
  int match_neighbours = 2;
  int local_keyframes = 8;
  int max_descriptor_distance = 50;
  double ratio = 0.8;
  int min_matches = 15;
  int max_projection_distance = 60;
  double search_radius_px = 8.0;
  int min_inliers = 30;
  int max_keypoints = 2000;
  double max_time_ms = 50.0;
  geometry::PnpOptions pnp;

  template <class V>
  void visit(V& v) {
    v.field("enabled", enabled,
            "relocalize when tracking is lost: frames the tracker has failed on for "
            "tracking.relocalize_after_lost_frames are matched against keyframes retrieved by "
            "their descriptors (lockstep: inline after tracking; threaded: on the low-priority "
            "depth thread, never on the tracking thread)");
    v.field("max_candidates", max_candidates,
            "keyframes retrieved from the keyframe database and checked, best score first",
            options::Range<int>{1, 64});
    v.field("match_neighbours", match_neighbours,
            "most covisible keyframes of a candidate whose map points are matched to the frame "
            "by descriptor together with the candidate's",
            options::Range<int>{0, 32});
    v.field("local_keyframes", local_keyframes,
            "most covisible keyframes of a candidate whose points are projected with the PnP "
            "pose to find more matches before the pose is refined",
            options::Range<int>{0, 64});
    v.field("max_descriptor_distance", max_descriptor_distance,
            "Hamming distance of a descriptor match (frame keypoint - map point), at most",
            options::Range<int>{0, 256});
    v.field("ratio", ratio, "best / second-best descriptor distance of a match, at most",
            options::Range<double>{0.1, 1.0});
    v.field("min_matches", min_matches, "descriptor matches needed before PnP-RANSAC",
            options::Range<int>{4, 100000});
    v.field("max_projection_distance", max_projection_distance,
            "Hamming distance of a match found by projecting a local map point, at most",
            options::Range<int>{0, 256});
    v.field("search_radius_px", search_radius_px,
            "projection search radius around a projected point, px at level 0 x the keypoint's "
            "level scale",
            options::Range<double>{0.5, 200.0});
    v.field("min_inliers", min_inliers,
            "inliers of the refined pose (chi-square 2 dof 95 % at the keypoint sigma) a "
            "relocalization needs",
            options::Range<int>{6, 100000});
    v.field("max_keypoints", max_keypoints,
            "frame keypoints used, at most (the first ones; sizes the scratch buffers)",
            options::Range<int>{16, 100000});
    v.field("max_time_ms", max_time_ms,
            "time after which no further candidate is started (a started one finishes; not "
            "applied in lockstep: results stay deterministic)",
            options::Range<double>{0.0, 60000.0});
    v.section("pnp", pnp, "P3P-RANSAC on the descriptor matches");
  }
};

/// One frame to relocalize (views into the caller's arrays, valid during spin_once).
struct RelocQuery {
  std::uint64_t seq = 0;                              ///< frame sequence number
  std::int64_t t_ns = 0;                              ///< capture time, ns
  std::span<const features::Keypoint> keypoints;      ///< level-0 px
  std::span<const features::Descriptor> descriptors;  ///< one per keypoint
  geometry::Pinhole K;                                ///< intrinsics of the frame
};

/// Outcome of one relocalization attempt.
struct RelocResult {
  bool success = false;                   ///< a pose with min_inliers refined inliers was found
  SE3d T_c_w = SE3d::Identity();          ///< world-to-camera pose of the frame (valid on success)
  map::KeyframeId keyframe = map::kNoId;  ///< the candidate it relocalized against
  map::Generation generation = map::kNoGeneration;  ///< that keyframe's occupant
  int retrieved = 0;                                ///< candidates the database returned
  int candidates_tried = 0;                         ///< candidates checked
  int matches = 0;         ///< descriptor matches with the successful (or last) candidate
  int pnp_inliers = 0;     ///< PnP-RANSAC inliers among them
  int inliers = 0;         ///< refined inliers (projection matches that agree)
  bool timed_out = false;  ///< candidates were left unchecked by max_time_ms
  double ms = 0.0;         ///< wall time of spin_once
};

/// Relocalization stage: `spin_once(RelocQuery) -> RelocResult`.
class Relocalizer {
 public:
  /// `db` indexes `map`'s keyframes and must outlive the relocalizer. `map_reader`: the
  /// handle of a registered map reader (announced at each spin_once), or -1 (lockstep, tests).
  /// `deterministic` (lockstep replay) drops the `max_time_ms` budget: every retrieved
  /// candidate is checked, so the result does not depend on the machine's load.
  /// Preallocates every buffer (options.max_keypoints, map capacities).
  Relocalizer(const RelocalizerOptions& opts, map::Map& map, KeyframeDatabase& db,
              int map_reader = -1, bool deterministic = false);
  ~Relocalizer();
  Relocalizer(const Relocalizer&) = delete;
  Relocalizer& operator=(const Relocalizer&) = delete;

  /// Tries to relocalize one frame (file comment for the steps). No heap allocation.
  RelocResult spin_once(const RelocQuery& q);

  /// Steps 2-4 against one given keyframe (no retrieval, no time budget): the frame is placed
  /// in the world frame of `kf`'s segment or not at all. Used to place the keyframes of one
  /// map segment in another's local map (loop merges). No heap allocation.
  RelocResult localize_against(const RelocQuery& q, map::KeyframeId kf);

  const RelocalizerOptions& options() const { return opts_; }

  /// After a successful spin_once or localize_against: its refined inliers, as the frame's
  /// keypoint indices, the matched map-points' world positions and (when given) their ids
  /// (appended; the caller's vectors may allocate). Returns how many.
  std::size_t last_inliers(std::vector<std::uint32_t>& keypoints, std::vector<Eigen::Vector3d>& X_w,
                           std::vector<map::PointId>* points = nullptr) const;

 private:
  /// Steps 2-4 for the candidate keyframe `id` (result fields into r); true on success.
  bool try_keyframe(const RelocQuery& frame, map::KeyframeId id, RelocResult& r);
  /// Local map points of keyframes kfs_ (each once): appended to pts_*; returns the count.
  std::size_t gather_points(std::size_t num_kfs);
  /// Descriptor matches between the frame and pts_[0, n): fills corr_*; returns the count.
  int match_descriptors(const RelocQuery& q, std::size_t n);
  /// Projection matches of pts_[0, n) under T_c_w: fills corr_*; returns the count.
  int match_projection(const RelocQuery& q, std::size_t n, const SE3d& T_c_w);
  /// Correspondences corr_* from kp_point_ (keypoint -> point index); returns the count.
  int collect_correspondences(const RelocQuery& q);
  /// Refines T_c_w on corr_[0, m) (two robust passes); returns the inliers.
  int refine(const RelocQuery& q, int m, SE3d& T_c_w);
  /// Keypoint grid of the frame for the projection search.
  void build_grid(const RelocQuery& q, std::size_t n);

  RelocalizerOptions opts_;
  map::Map& map_;
  KeyframeDatabase& db_;
  int reader_;
  bool deterministic_;  ///< lockstep: no wall-time budget
  std::unique_ptr<geometry::PnpRansac> pnp_;
  std::vector<RetrievalHit> hits_;
  std::vector<map::CovisibleKeyframe> covis_;
  std::vector<map::KeyframeId> kfs_;
  // Local map points.
  std::vector<std::uint32_t> point_stamp_;  ///< per map point slot: stamp_ when gathered
  std::uint32_t stamp_ = 0;
  std::vector<Eigen::Vector3d> pts_p_w_;
  std::vector<features::Descriptor> pts_desc_;
  std::vector<map::PointId> pts_id_;
  // Per frame keypoint: best point so far (distance, point index).
  std::vector<int> kp_best_;
  std::vector<std::int32_t> kp_point_;
  // Correspondences.
  std::vector<Eigen::Vector3d> corr_X_;
  std::vector<Eigen::Vector2d> corr_uv_;
  std::vector<std::uint32_t> corr_kp_;  ///< the frame keypoint of each correspondence
  std::vector<map::PointId> corr_pid_;  ///< and its map-point
  std::size_t last_corr_ = 0;           ///< correspondences of the last successful refinement
  std::vector<float> corr_sigma_;
  std::vector<std::uint8_t> corr_mask_;
  // Keypoint grid (counting sort of keypoints into cells).
  std::vector<std::uint32_t> cell_start_;
  std::vector<std::uint32_t> cell_kp_;
  std::vector<std::uint32_t> kp_cell_;
  int grid_cols_ = 0;
  int grid_rows_ = 0;
  double cell_w_ = 1.0;
  double cell_h_ = 1.0;
  double grid_x0_ = 0.0;
  double grid_y0_ = 0.0;
};

}  // namespace mer::loop
