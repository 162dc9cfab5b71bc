#pragma once
/// @file tracker.h
/// The localization front end, `spin_once(Frame) -> TrackingResult`, for every frame:
/// 1. extract ORB keypoints and descriptors;
/// 2. query map-points: Q_T = points of the keyframes tracked in the last B frames, and
///    Q_S = points in the 3D cells visible from the constant-velocity prediction;
/// 3. match Q_T u Q_S by projection (radius search, Hamming distance + ratio test; a wider
///    radius when the prediction is poor);
/// 4. P3P LO-RANSAC + robust refinement, then a second tight search with the estimated
///    pose and a final refinement (with `focal: auto`, the focal length is estimated
///    jointly until it is stable, then fixed to the running median);
/// 5. keyframe decision (inlier count, spread, KL jump of the tracked-point histogram).
/// Before a map exists its Initializer (initializer.h) decides: two-view reconstruction
/// (monocular) or one frame with depth (RGB-D). Lost frames are reported and, after
/// `relocalize_after_lost_frames`, offered to the relocalizer (which runs outside tracking);
/// a pose it finds is the prediction of the next frame (TrackerState: the state machine),
/// trusted at once within the motion bound of a short loss, refused outside it, and after a
/// longer loss only once the following frames confirm it, on more of them at a place refused
/// earlier in the lost spell (tracking.relocalization_check; frames reported lost meanwhile).
/// Lost for `new_segment_after_s`, it initializes a new map segment (as at the start) and
/// queries only that segment's points; a relocalization returns to the segment it found.
///
/// Threading: reads the map lock-free as a registered reader (map.h, slot reclamation): each
/// spin_once() starts with a quiescent point, and the ids it keeps across frames are either
/// re-checked (recent keyframes) or handed on with their generation (keyframe jobs). Its map
/// writes are the per-point visible / found statistics (relaxed atomic adds); it never takes
/// the map's writer lock. An initialization hands the segment's first keyframes and points to
/// keyframe creation as a job (KeyframeJobKind::kSegmentStart), as every other keyframe, and
/// tracking resumes with the first frame that finds them in the map (Map::segment_start; in
/// lockstep, the next frame; threaded, frames before it have no pose).
/// After init, spin_once() does not allocate.

#include <array>
#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "core/sensor_mode.h"
#include "features/extractor.h"
#include "frontend/focal_estimator.h"
#include "frontend/initializer.h"
#include "frontend/keyframe_policy.h"
#include "frontend/keypoint_grid.h"
#include "frontend/tracking_options.h"
#include "frontend/tracking_result.h"
#include "geometry/camera_model.h"
#include "geometry/pnp.h"
#include "geometry/sim3.h"
#include "hal/camera.h"
#include "map/keyframe_job.h"
#include "map/map.h"

namespace mer::frontend {

/// A lost frame's features, handed to the relocalizer (filled by
/// Tracker::fill_relocalization_request; sized once by Tracker::reserve_relocalization_request,
/// so filling it does not allocate).
struct RelocalizationRequest {
  std::uint64_t seq = 0;                          ///< frame sequence number
  std::int64_t t_ns = 0;                          ///< capture time, ns
  geometry::Pinhole K;                            ///< intrinsics the frame was tracked with
  std::vector<features::Keypoint> keypoints;      ///< [0, count): level-0 px
  std::vector<features::Descriptor> descriptors;  ///< [0, count)
  std::size_t count = 0;                          ///< keypoints in use
};

/// A relocalizer's pose for a frame of the lost spell: the prediction the tracker searches the
/// next frame from (Tracker::set_relocalization_hint).
struct RelocalizationHint {
  bool valid = false;
  std::uint64_t seq = 0;                            ///< frame it was found for
  SE3d T_c_w = SE3d::Identity();                    ///< world-to-camera pose of that frame
  map::KeyframeId keyframe = map::kNoId;            ///< keyframe it relocalized against
  map::Generation generation = map::kNoGeneration;  ///< that keyframe's occupant
};

/// Counters of the tracker (summary.json `tracking`).
struct TrackerCounters {
  std::uint64_t init_attempts = 0;          ///< two-view reconstructions tried
  std::uint64_t init_refusals = 0;          ///< of which refused (degenerate)
  std::uint64_t frames_oriented = 0;        ///< frames before a map with a known orientation (pure
                                            ///< rotations of the initializer's reference)
  std::uint64_t initialized_seq = 0;        ///< frame the map was initialized at
  std::uint64_t reference_seq = 0;          ///< its reference frame (the world frame in mono)
  std::uint64_t segment_reference_seq = 0;  ///< reference frame of the latest segment's start
  std::uint64_t failed_starts = 0;          ///< starts lost within init.failed_start_window_s
                                            ///< with at most failed_start_max_keyframes
  std::uint64_t discarded_starts = 0;  ///< of these, segments discarded (discard_failed_starts)
  /// Ground-truth audit of the initializer's matches (sources with true poses and depth):
  /// matches checked on every frame matched to a reference, and those further than
  /// kGtWrongMatchPx from the true pixel; then the same for the frames that started a segment.
  std::uint64_t init_gt_matches = 0;
  std::uint64_t init_gt_wrong = 0;
  std::uint64_t start_gt_matches = 0;
  std::uint64_t start_gt_wrong = 0;
  bool initialized = false;
  std::uint64_t tracked = 0;
  std::uint64_t lost = 0;
  std::uint64_t wide_searches = 0;  ///< frames that needed the wide radius
  std::uint64_t keyframes_decided = 0;
  std::uint64_t keyframe_reasons[7] = {};     ///< per KeyframeReason
  std::uint64_t relocalization_requests = 0;  ///< lost frames offered to the relocalizer
  std::uint64_t relocalization_hints = 0;     ///< poses the relocalizer found
  std::uint64_t relocalized = 0;              ///< of those, tracked again from the pose
  std::uint64_t lost_spells = 0;              ///< times tracking went from tracked to lost
  std::uint64_t max_lost_frames = 0;          ///< longest lost spell, frames
  std::uint64_t new_segments = 0;             ///< map segments started after a lost spell
  std::uint64_t segment_returns = 0;  ///< relocalized into another segment than the one tracked
  std::uint64_t segment_merges_followed = 0;    ///< the tracked segment merged into another one
  std::uint64_t relocalization_trusted = 0;     ///< poses within the motion bound, trusted at once
  std::uint64_t relocalization_candidates = 0;  ///< poses that needed confirmation
  std::uint64_t relocalization_confirmed = 0;   ///< of those, confirmed
  std::uint64_t relocalization_rejected_lost = 0;       ///< refused: a confirming frame was lost
  std::uint64_t relocalization_rejected_found = 0;      ///< refused: a confirming frame found too
                                                        ///< few of the map-points in its view
  std::uint64_t relocalization_rejected_bound = 0;      ///< refused: after a short loss, outside
                                                        ///< the motion bound
  std::uint64_t relocalization_rejected_long_loss = 0;  ///< refused: after a long loss
                                                        ///< (relocalization_check.after_long_loss:
                                                        ///< merge)
  std::uint64_t relocalization_longer_checks = 0;       ///< candidates at a place refused earlier
                                                        ///< in the spell (more frames to confirm)
  std::uint64_t segment_start_waits = 0;  ///< frames without a pose: the start not in the map yet
  std::uint64_t segment_starts_not_queued = 0;  ///< starts that found no free keyframe job
  std::uint64_t segment_starts_refused = 0;     ///< starts the map could not take (full)
  std::uint64_t sum_query_temporal = 0;
  std::uint64_t sum_query_spatial = 0;
  std::uint64_t sum_query_total = 0;
  std::uint64_t sum_inliers = 0;
  const char* last_init_refusal = "";  ///< reason of the last refused two-view reconstruction
  /// Frames that did not start a segment, by InitRefusal (kNone unused).
  std::array<std::uint64_t, kInitRefusalCount> init_frame_refusals{};
  /// Two-view reconstructions refused, by geometry::TwoViewRefusal (kNone unused).
  std::array<std::uint64_t, geometry::kTwoViewRefusalCount> init_two_view_refusals{};
};

/// The tracking stage.
class Tracker {
 public:
  /// `focal_auto` estimates the focal length from `K.fx` as a guess.
  Tracker(const TrackingOptions& opts, map::Map& map, const geometry::Pinhole& K, int width,
          int height, SensorMode mode, bool focal_auto);
  ~Tracker();

  /// Builds the extractor and buffers; error on bad options.
  Status init();

  /// Localizes one frame.
  TrackingResult spin_once(const hal::Frame& frame);

  /// Copies the frame the last spin_once() decided is a keyframe into `job` (call while the
  /// frame is still valid). No allocation.
  void fill_keyframe_job(const hal::Frame& frame, map::KeyframeJob& job) const;
  /// The keyframe decided last could not be queued (no free job): decide again next frame.
  void keyframe_not_queued();
  /// The tracking thread is done with the map (end of its loop): its reader registration is
  /// released, so slots freed by the keyframes still queued can be reused. No spin_once after.
  void stop_reading();

  /// Sizes `req` for this tracker's keypoints (setup: allocates).
  void reserve_relocalization_request(RelocalizationRequest& req) const;
  /// Copies the features of the frame the last spin_once() processed into `req` (call when
  /// its result asked for relocalization). No allocation once reserved.
  void fill_relocalization_request(const hal::Frame& frame, RelocalizationRequest& req) const;
  /// A relocalizer's pose: the next spin_once() searches from it (wide radius, the pose's
  /// keyframe joining the temporal query) instead of the last tracked pose, and a frame
  /// tracked that way becomes a keyframe (reason relocalization). Ignored once tracking has
  /// come back on its own.
  void set_relocalization_hint(const RelocalizationHint& hint);
  /// A relocalizer answers this tracker's requests (setup call; without one, lost frames stay
  /// in state lost and ask for nothing).
  void enable_relocalization(bool on) { relocalization_available_ = on; }
  TrackerState state() const { return state_; }

  /// Keypoint variance per pyramid level (for depth inference).
  std::vector<float> level_sigma2() const;
  int max_keypoints() const;
  /// Keeps the images and poses of the last `count` tracked frames, at least `spacing_s`
  /// apart, for keyframe jobs (dense multi-view depth); fill_keyframe_job copies them into
  /// KeyframeJob::recent_*. Call before the first frame (allocates the ring).
  void keep_recent_frames(int count, double spacing_s);
  const FocalReport& focal() const { return focal_.report(); }
  const TrackerCounters& counters() const { return counters_; }
  const geometry::Pinhole& intrinsics() const { return K_; }
  /// The per-frame motion (world-to-camera) the next frame's prediction applies.
  const SE3d& velocity() const { return velocity_; }

 private:
  void gather_queries(const SE3d& T_c_w, TrackingResult& r);
  int project_and_match(const SE3d& T_c_w, double radius_px, bool tight);
  int collect_correspondences();
  bool estimate_pose(const SE3d& T_c_w_pred, bool wide, TrackingResult& r);
  /// Moves the poses this tracker keeps (last pose, motion, recent frames) by the map
  /// corrections published since the last frame (loop closure), so that the prediction
  /// lands where the corrected map is.
  void follow_map_correction();
  /// Moves every pose the tracker keeps in the tracked segment by the world correction D.
  void apply_correction(const geometry::Sim3d& D);
  /// Fills r's anchor: its pose relative to the map's newest keyframe when that is of the
  /// tracked segment, else to the last keyframe of the segment anchored to (after a return to
  /// an earlier segment: the keyframe relocalized against); none when neither is live.
  void set_anchor(TrackingResult& r);
  bool track(const hal::Frame& frame, TrackingResult& r);
  /// Asks the initializer with the frame; a start becomes the frame's pose and the segment's
  /// start (begin_segment_start).
  void initialize(const hal::Frame& frame, TrackingResult& r);
  /// Hands the segment's start (the initializer's last) to keyframe creation: r asks for a
  /// keyframe job, which fill_keyframe_job fills from it.
  void begin_segment_start(TrackingResult& r);
  enum class StartPoll : std::uint8_t { kPending, kInserted, kRefused };
  /// Whether keyframe creation has written the segment's start: kInserted (tracking resumes
  /// from it), kPending, or kRefused (the next segment is initialized).
  StartPoll poll_segment_start();
  /// Updates the state machine after a frame (tracked or not) and fills r's state fields.
  void advance_state(TrackingResult& r);
  /// Takes a pending relocalizer's pose (tracking.relocalization_check): trusted within the
  /// motion bound, else a candidate the following frames must confirm, refused outside the
  /// bound after a short loss. True when the frame is searched from it.
  bool take_hint(const hal::Frame& frame);
  /// A frame tracked from a relocalization candidate: refuses it when the frame finds too
  /// small a share of the points in view (`found`), holds it until enough frames confirmed
  /// it (false: the frame is reported lost) and then sets `confirmed`.
  bool confirm_candidate(const hal::Frame& frame, double found, TrackingResult& r, bool& confirmed);
  /// The keyframe decision of a tracked frame (a relocalization's frame is one).
  void decide_keyframe(const hal::Frame& frame, bool from_hint, bool confirmed, TrackingResult& r);
  /// At the first lost frame of a spell: counts a failed start (TrackerCounters) when the
  /// latest start's segment is lost within init.failed_start_window_s of it with at most
  /// init.failed_start_max_keyframes keyframes; true for such a failed start.
  bool count_failed_start(const TrackingResult& r);
  /// With init.discard_failed_starts: discards the failed start's segment (Map::
  /// discard_segment; r says which) and initializes the next segment from the next frame.
  /// Nothing done when no segment id is left or the segment is merging.
  void discard_failed_start(TrackingResult& r);
  /// Whether a segment other than the one tracked (or initialized) holds a map that was
  /// not discarded: else initializing is the first map's (state initializing).
  bool other_segment_kept() const { return segments_started_ - segments_discarded_ > 1; }
  /// Forgets the current segment's tracking state and initializes the next segment from the
  /// next frames (tracking.new_segments).
  void start_new_segment(std::uint64_t seq);
  // Forgets the tracked segment's state; the next frames initialize segment segments_started_.
  void begin_next_segment();
  /// Where a relocalizer's pose stands against the motion bound of the last tracked pose.
  enum class MotionBound : std::uint8_t {
    kWithin,   ///< a short loss, the pose within the bound: trusted at once
    kOutside,  ///< a short loss, the pose outside the bound: refused
    kNone,     ///< a long loss, or another segment: no bound, confirmed on following frames
  };
  /// Where a relocalizer's pose `T_c_w` at `t_ns`, in `segment`, stands against the motion
  /// bound of the last tracked pose (tracking.relocalization_check).
  MotionBound motion_bound(const SE3d& T_c_w, std::int64_t t_ns, std::uint16_t segment) const;
  /// relocalization_check.after_long_loss is merge and the loss at `t_ns` is long (or a new
  /// segment is starting): no relocalization, a new segment and a merge bring the camera back.
  bool long_loss_merges(std::int64_t t_ns) const;
  /// Drops the pending relocalization candidate (it failed to confirm): back to the last
  /// tracked pose (and to the new segment it was returning from); its place counts a refusal.
  void reject_candidate();
  /// Offers refused at the place of keyframe kf earlier in this lost spell (kf's own and
  /// those of keyframes that share map-points with it).
  int place_refusals(map::KeyframeId kf) const;
  /// Counts one refused offer at the place of keyframe kf (generation gen).
  void count_place_refusal(map::KeyframeId kf, map::Generation gen);
  /// In state new_segment with a relocalizer's pose: back to that keyframe's segment (its
  /// median keyframe depth as the query range). False when the keyframe is gone.
  bool return_to_segment_of_hint();
  void update_focal(double f, std::uint64_t seq);

  TrackingOptions opts_;
  map::Map& map_;
  int map_reader_ = -1;  // registration for slot reclamation
  geometry::Pinhole K_;
  int width_;
  int height_;
  FocalEstimator focal_;
  TrackerCounters counters_;
  std::unique_ptr<features::Extractor> extractor_;
  std::unique_ptr<geometry::PnpRansac> pnp_;
  KeyframePolicy policy_;
  Initializer initializer_;

  // Frame state.
  std::span<const features::Keypoint> kps_;
  std::span<const features::Descriptor> descs_;
  KeypointGrid grid_;

  // Query and match buffers.
  std::vector<std::uint32_t> stamp_;  // per map-point: frame stamp it was last queried in
  std::uint32_t frame_stamp_ = 0;
  std::vector<std::uint32_t> query_buf_;
  std::vector<std::uint32_t> cand_id_;
  std::vector<Eigen::Vector3d> cand_p_w_;
  std::vector<features::Descriptor> cand_desc_;
  std::vector<Eigen::Vector3f> cand_normal_;
  std::vector<float> cand_max_dist_;
  std::vector<std::uint32_t> cand_kf_;
  std::vector<std::uint32_t> cand_gen_;     // generation of the candidate point
  std::vector<std::uint8_t> cand_in_view_;  // projected into the image in the last search
  std::vector<std::int32_t> cand_match_;    // keypoint index or -1
  int num_cand_ = 0;
  std::vector<std::int32_t> kp_cand_;  // per keypoint: candidate index or -1
  std::vector<std::int32_t> kp_dist_;  // per keypoint: descriptor distance of its match
  std::vector<Eigen::Vector3d> corr_X_;
  std::vector<Eigen::Vector2d> corr_uv_;
  std::vector<float> corr_sigma_;
  std::vector<std::int32_t> corr_kp_;
  std::vector<std::uint8_t> corr_mask_;
  std::vector<float> inlier_x_;
  std::vector<float> inlier_y_;
  std::vector<std::uint32_t> kp_point_;      // per keypoint: tracked (inlier) map-point or kNoId
  std::vector<std::uint32_t> kp_point_gen_;  // its generation
  KeyframeHistogram histogram_;
  std::vector<KeyframeHistogram> recent_;  // histograms of the last B localized frames
  std::size_t recent_next_ = 0;
  std::vector<std::uint32_t> qt_keyframes_;

  // Loop corrections of the map followed so far (Map::publish_correction): all segments'
  // count, and the tracked segment's cumulative correction and count.
  std::uint32_t correction_count_seen_ = 0;
  std::uint16_t correction_segment_ = 0;
  geometry::Sim3d correction_seen_;
  std::uint32_t correction_segment_count_ = 0;

  std::int64_t spatial_max_age_ns_ = 0;  // Q_S: older reference keyframes skipped (0: none)
  std::int64_t frame_t_ns_ = 0;          // timestamp of the frame being tracked

  // Motion.
  bool have_pose_ = false;
  SE3d T_c_w_ = SE3d::Identity();
  SE3d velocity_ = SE3d::Identity();  // T_c(k)_c(k-1)
  bool poor_prediction_ = true;
  double median_depth_ = 1.0;
  std::vector<double> depth_scratch_;
  std::uint64_t frames_since_init_ = 0;

  // Initialization (the segment's start is the initializer's last).
  bool initialized_ = false;
  bool start_to_queue_ = false;  // the frame just tracked asks for the start's job
  bool start_pending_ = false;   // the start is not in the map yet

  // Keyframe decided last (for fill_keyframe_job).
  SE3d last_T_w_c_ = SE3d::Identity();
  // Recent tracked frames (keep_recent_frames): a ring, newest at recent_head_ - 1.
  std::vector<cv::Mat> recent_gray_;
  std::vector<SE3d> recent_T_w_c_;
  std::vector<std::int64_t> recent_t_ns_;
  std::size_t recent_head_ = 0;
  std::size_t recent_valid_ = 0;
  std::int64_t recent_spacing_ns_ = 0;
  std::uint8_t last_reason_ = 0;
  bool force_keyframe_ = false;

  // State machine and relocalization.
  TrackerState state_ = TrackerState::kInitializing;
  std::uint64_t lost_frames_ = 0;      // consecutive lost frames
  std::int64_t start_t_ns_ = 0;        // the latest start's frame time
  std::uint16_t start_segment_ = 0;    // the segment it started
  std::uint32_t start_keyframes_ = 0;  // keyframes made in that segment since
  bool relocalization_available_ = false;
  RelocalizationHint hint_;                      // pending pose from the relocalizer
  map::KeyframeId reloc_keyframe_ = map::kNoId;  // joins Q_T for the frame searched from a hint
  map::Generation reloc_generation_ = map::kNoGeneration;
  // Map segments (tracking.new_segments).
  std::uint16_t segment_ = 0;             // segment of the map tracked in (or being initialized)
  std::uint16_t segments_started_ = 1;    // segments this run has started
  std::uint16_t segments_discarded_ = 0;  // of them, discarded as failed starts
  std::int64_t last_tracked_t_ns_ = 0;    // capture time of the last tracked frame
  SE3d last_tracked_T_c_w_ = SE3d::Identity();  // and its pose, segment and median depth
  std::uint16_t last_tracked_segment_ = 0;
  double last_tracked_median_depth_ = 1.0;
  Eigen::Vector3d last_tracked_omega_ = Eigen::Vector3d::Zero();     // turn rate, rad/s (left)
  Eigen::Vector3d last_tracked_velocity_ = Eigen::Vector3d::Zero();  // centre, map units / s
  // A relocalization being confirmed (tracking.relocalization_check).
  bool candidate_ = false;                     // a candidate pose is being confirmed
  int candidate_frames_ = 0;                   // frames it has been confirmed in so far
  double candidate_min_ratio_ = 0.0;           // lowest found share / usual share over those frames
  int candidate_required_ = 0;                 // frames it must be confirmed in (place_refusals)
  map::KeyframeId candidate_kf_ = map::kNoId;  // the keyframe it was found against
  map::Generation candidate_generation_ = map::kNoGeneration;
  // Places refused in this lost spell (forgotten when a frame is tracked): a fixed table;
  // when it is full, a new place replaces the least refused one.
  struct SpellPlace {
    map::KeyframeId kf = map::kNoId;
    map::Generation generation = map::kNoGeneration;
    int refusals = 0;
  };
  static constexpr std::size_t kSpellPlaces = 16;
  std::array<SpellPlace, kSpellPlaces> spell_places_{};
  std::size_t spell_places_used_ = 0;
  bool candidate_returning_ = false;            // it returns from another segment (set_anchor)
  std::uint16_t candidate_segment_before_ = 0;  // the segment it returns from
  bool candidate_initialized_before_ = false;   // whether that segment was initialized
  std::uint64_t hint_frames_ = 1;               // frames between the relocalizer's pose and its use
  map::KeyframeId anchor_kf_ = map::kNoId;      // keyframe of segment_ anchored to (set_anchor)
  map::Generation anchor_generation_ = map::kNoGeneration;
  int last_in_view_ = 0;  // map-points the last estimate_pose projected into view
  // Found share (inliers / map-points in view) of the last tracked frames: a ring.
  static constexpr std::size_t kFoundHistory = 16;
  std::array<float, kFoundHistory> found_share_{};
  std::size_t found_next_ = 0;
  std::size_t found_valid_ = 0;
  /// The median found share of the last tracked frames (0: none yet).
  double recent_found_share() const;
};

}  // namespace mer::frontend
