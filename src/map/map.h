#pragma once
/// @file map.h
/// The SLAM map: keyframes, map points, the 3D cell grid (spatial hash) and the covisibility
/// graph, in storage preallocated by the constructor. No method allocates afterwards (error
/// results carry a message string: only failing calls allocate).
///
/// Threading contract
/// ------------------
///  - One writer at a time (the writer lock): a thread calls methods of the "writer" group
///    only while it holds writer_lock(), a priority-inheritance mutex (platform/pi_mutex.h).
///    Writers are the keyframe builder (depth thread, low priority), the local bundle
///    adjustment and culling (back-end thread, high priority) and offline steps (final BA).
///    The lock orders them: each writer sees everything earlier holders wrote, so writer-side
///    state needs no atomics. The writer methods themselves never block. The tracking thread
///    NEVER takes the lock: it only reads (below); even a segment's first keyframes and points
///    are written by the keyframe builder (publish_segment_start tells the tracker they are
///    in). A program with one writer thread only (unit tests, offline tools) need not take
///    the lock.
///  - A writer that drops the lock in the middle of its work (local BA releases it while
///    Ceres solves) holds only ids with their generations across the gap and revalidates
///    them when it takes the lock again: another writer may have added, moved or freed
///    items meanwhile.
///  - Any number of reader threads (the real-time tracker) call the "reader" group, which is
///    lock-free with bounded work: it never waits for the writer.
///  - Every slot has a state word (generation << 1 | live). The writer fills a slot while it
///    is not live, then publishes it with a release store of the live state; every reader
///    method loads that state with acquire and returns false / empty / kNoId / 0 for a slot
///    that is not live (never used, or freed). num_keyframes() / num_points() are the slot
///    high-water marks (ids below them have been used; check liveness).
///  - Immutable while a slot is live (plain memory, no synchronization cost): keyframe
///    descriptors, seq, t_ns, the number of keypoints and each keypoint's level, scale,
///    angle and response.
///  - Writer-side data (plain memory, writer-lock holders only): keypoint positions. The
///    writer may move a keypoint (set_keypoint_position: keypoint alignment); every reader of
///    positions (keyframe creation, local BA, culling, loop closure) holds the writer lock,
///    and lock-free readers use keyframe_keypoints() for its size only.
///  - Mutable after publication, read through a per-slot seqlock whose payload is stored in
///    std::atomic words (seqlock.h; ThreadSanitizer-clean): keyframe pose + scale, point
///    position, representative descriptor, normal and distance range, reference keyframe /
///    keypoint and the point's state (so read_point returns a payload and the generation it
///    belongs to, together), and each keyframe's covisibility list. A reader that cannot get
///    a consistent snapshot in kSeqlockReadAttempts tries (the writer was preempted inside its
///    short write section) gets false / 0 and skips the item.
///  - Single atomic words (no seqlock needed): keypoint->point associations, per-keypoint
///    depth and confidence, the state words, the newest keyframe id.
///  - Reader-side statistics: note_visible() / note_found() add to per-point atomic counters
///    (relaxed); the writer reads them to cull points and resets them when a slot is reused.
///  - point_observations(), point_num_observations(), point_stats(), keyframe_serial(),
///    relative_pose() and counters() read writer-side state: writer-lock holders only (or a
///    thread that is the only writer left, after the others are joined). Readers use
///    keyframe_point() / keyframe_pose() instead.
///  - Consistency between items is not promised: a reader may see a point's new position with
///    the old cell, a new observation before the descriptor update, etc. Each individual
///    value read is one the writer wrote as a whole.
///
/// Slot reclamation (quiescent-state-based)
/// ----------------------------------------
///  - A reader thread registers once (register_reader(), a setup call made before it and the
///    writer run concurrently) and calls reader_quiescent(r) at the start of each unit of
///    work (the tracker: each frame), a point where it holds no reference into the map except
///    ids it will validate. Between two quiescent points is its read section. A quiescent
///    point is one acquire load of the map epoch and one release store of it into the
///    reader's own cache line: no allocation, no lock, no wait.
///  - Freeing a slot (set_point_bad, remove_keyframe): the writer marks it not live with the
///    generation incremented, unlinks it from everything readers reach (cells, keypoint
///    associations, covisibility lists), then advances the epoch to E (release) and queues
///    the slot tagged E. It reuses the slot (oldest freed first, after the never-used slots
///    are exhausted) only once every registered reader has announced an epoch >= E.
///  - Why a reader never sees a slot rewritten under it: a read section that announced
///    A < E may still hold the old occupant, but the slot is not rewritten before that reader
///    announces again; its release store of the announcement orders all its earlier reads
///    before the writer's acquire load of it, and so before the rewrite. A read section that
///    announced A >= E read the epoch after the writer stored E, so it sees the slot not live
///    (or already live again with its new occupant, published with release), and that new
///    occupant cannot be freed and reused before the reader's next announcement. So every
///    plain read of slot memory is ordered against every write of it.
///  - Ids a reader keeps across quiescent points (the tracker's recent keyframes, the point
///    ids it hands to keyframe creation) may name a newer occupant: compare the generation
///    saved with them (PointView::generation, keyframe_generation()) to detect that.
///  - A registered reader that stops announcing keeps every slot freed after its last
///    announcement from being reused: add_* then report the map full (bounded, never a
///    wait). A thread that reads without registering is safe only while nothing it reads is
///    reused concurrently (tests, offline tools).
///  - In lockstep mode the tracker announces at every frame, so a slot freed while a
///    keyframe is created is reusable from the next frame on.
///
/// Design notes (why not exactly the first sketch):
///  - Ids are reused, with a generation per slot (above): max_points and max_keyframes bound
///    the live map, not what a run can ever create, so culling keeps a long run going.
///    add_* return an error naming the option only when every slot is live or still waits
///    for a reader.
///  - The seqlock is fence-free (release payload stores / acquire payload loads) because GCC's
///    ThreadSanitizer does not support std::atomic_thread_fence (-Wtsan); see seqlock.h.
///  - Cells use swap-with-last removal under a per-cell seqlock (dense cells, no tombstones);
///    a query overlapping a point move de-duplicates its output, so ids are always distinct.
///  - query_visible marches cell layers front to back (nearest first, bounded by the
///    frustum) or, when the frustum covers more cells than a table scan costs, scans the
///    table once: its work is bounded by the table size whatever near / far are.
///  - Observation lists (keyframe, keypoint) of points are writer-side data (the writer is
///    the one that needs them: covisibility, descriptors, culling); readers see the same
///    relation from the keyframe side through keyframe_point().
///  - Memory with default options: ~86 MiB (memory_bytes()): keyframes 39 MiB (400 x 1500
///    keypoints x 68 B: keypoint, descriptor, association, depth, confidence), points 33 MiB
///    (150000 x 233 B: seqlocked payload and state, 24 packed 32-bit observations, cell key,
///    visible / found counters, creation serial, free-list entry), cells 13 MiB (65536
///    entries x 48 ids), covisibility 0.2 MiB. Every array is written once by the
///    constructor, so its pages are resident (no page faults on the real-time path), and
///    reusing slots keeps it the whole memory of the map however long the run.
///  - Covisibility edges are refreshed by update_covisibility(kf) for kf and, symmetrically,
///    in the lists of all keyframes sharing points with it; an edge between two keyframes
///    that are both never updated again keeps its last weight. remove_keyframe() removes
///    every edge to the removed keyframe.

#include <atomic>
#include <cstdint>
#include <memory>
#include <span>
#include <utility>
#include <vector>

#include <Eigen/Core>

#include "core/pose.h"
#include "core/status.h"
#include "features/keypoint.h"
#include "geometry/camera_model.h"
#include "geometry/sim3.h"
#include "map/cell_grid.h"
#include "map/map_options.h"
#include "map/map_types.h"
#include "map/seqlock.h"
#include "platform/cache_line.h"
#include "platform/pi_mutex.h"

namespace mer::map {

/// Reader threads that can register for slot reclamation (the tracker is one).
inline constexpr int kMaxMapReaders = 4;

/// What the front end hands to add_keyframe (spans are copied).
struct KeyframeInput {
  std::uint64_t seq = 0;          ///< frame sequence number
  std::int64_t t_ns = 0;          ///< capture time, ns
  SE3d T_w_c = SE3d::Identity();  ///< camera-to-world pose
  std::span<const features::Keypoint> keypoints;
  std::span<const features::Descriptor> descriptors;  ///< one per keypoint
  std::span<const float> depth;             ///< per keypoint camera z (0: unknown); may be empty
  std::span<const float> depth_confidence;  ///< per keypoint, may be empty (0)
  std::uint16_t segment = 0;  ///< map segment (frontend: a new one after a long lost spell)
};

/// Where a map segment's start (its first keyframes and points, made by the tracker's
/// initialization and inserted by keyframe creation) stands (Map::segment_start).
enum class SegmentStartState : std::uint8_t {
  kPending,   ///< not inserted yet (or never asked for)
  kInserted,  ///< in the map: `first` .. `last` are its keyframes
  kRefused,   ///< could not be inserted (map full); the segment holds nothing
};

/// A segment's start as keyframe creation published it.
struct SegmentStartRecord {
  SegmentStartState state = SegmentStartState::kPending;
  KeyframeId first = kNoId;  ///< its first keyframe (the world frame)
  KeyframeId last = kNoId;   ///< its last keyframe (the initialization's frame)
};

/// A map segment that joined another (Map::merge_segment): immutable once recorded.
struct SegmentMerge {
  std::uint16_t into = kNoSegment;  ///< the segment it joined
  geometry::Sim3d sim_into_from;    ///< its world frame -> that of `into` (map units scale)
  geometry::Sim3d into_correction;  ///< the cumulative correction of `into` at the merge
  std::uint32_t into_count = 0;     ///< and the number of corrections of `into` it includes
  std::uint32_t from_count = 0;     ///< corrections of the merged segment, the merge included
};

/// A consistent snapshot of a map point.
struct PointView {
  Eigen::Vector3d p_w = Eigen::Vector3d::Zero();     ///< world position
  features::Descriptor descriptor{};                 ///< representative descriptor (medoid)
  Eigen::Vector3f normal = Eigen::Vector3f::Zero();  ///< mean unit viewing direction
  KeyframeId ref_keyframe = kNoId;  ///< reference keyframe (creator, or an observer of it once
                                    ///< the creator was removed)
  std::uint32_t ref_keypoint = 0;   ///< its keypoint in ref_keyframe
  float min_distance = 0.0F;        ///< scale invariance: closest distance it can be matched at
  float max_distance = 0.0F;        ///< farthest distance it can be matched at
  Generation generation = kNoGeneration;  ///< occupant of the slot this snapshot belongs to
};

/// An edge of the covisibility graph.
struct CovisibleKeyframe {
  KeyframeId id = kNoId;     ///< the other keyframe
  std::uint32_t weight = 0;  ///< map points both observe
};

/// Writer-side facts about a live point (culling rules).
struct PointStats {
  std::uint32_t observations = 0;    ///< keyframes observing it
  std::uint32_t visible = 0;         ///< frames it projected into (note_visible)
  std::uint32_t found = 0;           ///< frames it was a tracked inlier in (note_found)
  std::uint64_t created_serial = 0;  ///< keyframes_added() when it was created
};

/// Counters of the map (writer-lock holder).
struct MapCounters {
  std::uint32_t live_keyframes = 0;
  std::uint32_t live_points = 0;
  std::uint32_t keyframe_slots_used = 0;  ///< high-water mark (num_keyframes())
  std::uint32_t point_slots_used = 0;     ///< high-water mark (num_points())
  std::uint64_t removed_keyframes = 0;    ///< remove_keyframe() calls that removed one
  std::uint64_t bad_points = 0;           ///< points freed (set_point_bad), all causes
  std::uint64_t merged_points = 0;        ///< of these, duplicates merged (merge_points)
  std::uint64_t reused_keyframe_slots = 0;
  std::uint64_t reused_point_slots = 0;
  std::uint32_t keyframe_slots_waiting = 0;  ///< freed, not reusable yet (or not needed yet)
  std::uint32_t point_slots_waiting = 0;
};

/// The map (see the file comment for the threading contract).
class Map {
 public:
  /// keyframe_serial() of an id that is not live.
  static constexpr std::uint64_t kNoSerial = ~std::uint64_t{0};

  /// Preallocates everything. Options are used as effective_options(opts) (validate() them
  /// first to report bad values to the user; the constructor never fails).
  explicit Map(const MapOptions& opts);
  Map(const Map&) = delete;
  Map& operator=(const Map&) = delete;

  // ------------------------------------------------ writer group: hold writer_lock() --
  /// The writer lock (file comment): held by whoever calls the writer group; never taken by
  /// the tracking thread. Priority inheritance bounds how long the high-priority back end
  /// waits for the low-priority keyframe builder.
  platform::PiMutex& writer_lock() noexcept { return writer_lock_; }
  /// Copies a keyframe into a free slot and publishes it as the newest keyframe. Errors: map
  /// full (names map.max_keyframes), too many keypoints (names
  /// map.max_keypoints_per_keyframe), span sizes that disagree.
  Result<KeyframeId> add_keyframe(const KeyframeInput& in);
  /// Creates a point at p_w observed by keypoint ref_kp of ref_kf: descriptor from that
  /// keypoint, normal / distances from that keyframe's pose, inserted into its cell (a full
  /// cell is counted in cell_insert_failures(); the point still exists). Its visible / found
  /// counters start at 1 (the creating keyframe saw and found it). Errors: map full (names
  /// map.max_points), unknown keyframe / keypoint, keypoint already associated, non-finite
  /// position.
  Result<PointId> add_point(const Eigen::Vector3d& p_w, KeyframeId ref_kf, std::uint32_t ref_kp);
  /// Associates keypoint kp of kf with point p. False when an id is invalid, the point is bad,
  /// the keypoint already has a point, the point already has an observation in kf or its
  /// observation list is full (map.max_observations_per_point). Does not refresh the
  /// descriptor (update_point) nor the covisibility (update_covisibility).
  bool add_observation(PointId p, KeyframeId kf, std::uint32_t kp);
  /// Recomputes the representative descriptor (the observation descriptor with the least
  /// median Hamming distance to all observation descriptors), the normal (mean unit vector
  /// from the observing camera centres) and the distance range (from the reference keyframe).
  void update_point(PointId p);
  /// Moves a point (and between cells when its cell changes). Descriptor, normal and
  /// distances are kept: call update_point after a batch of moves if they matter.
  void set_point_position(PointId p, const Eigen::Vector3d& p_w);
  /// Sets a keyframe pose and its similarity scale (Sim3 corrections; stored, not applied).
  void set_keyframe_pose(KeyframeId kf, const SE3d& T_w_c, double scale = 1.0);
  /// Moves keypoint kp of kf to (x, y), level-0 px (keypoint alignment, the ground-truth
  /// check). Writer-lock holders only; positions are writer-side data (above). Covisibility
  /// and point descriptors are unaffected. False for an unknown keyframe or keypoint, or a
  /// non-finite position.
  bool set_keypoint_position(KeyframeId kf, std::uint32_t kp, float x, float y);
  /// Marks keypoint kp of kf as measuring its point's anchor (Keypoint::anchored), or not.
  /// Writer-lock holders only, like positions. A point freed by set_point_bad clears the mark
  /// of every keypoint that observed it (a later association starts as a detection). False
  /// for an unknown keyframe or keypoint.
  bool set_keypoint_anchored(KeyframeId kf, std::uint32_t kp, bool anchored);
  /// Records a world-frame correction of one segment (a loop closure moved that segment's
  /// map by S_new_old around its newest keyframes): the segment's cumulative correction
  /// becomes S_new_old * previous. Readers that keep poses of their own in that segment (the
  /// tracker's last pose) move them by the part they missed. Ignored for a segment id of
  /// kMaxSegments or more.
  void publish_correction(std::uint16_t segment, const geometry::Sim3d& S_new_old) noexcept;
  /// Joins segment `from` to segment `into`: every keyframe of `from` is moved into the
  /// world frame of `into` by S_into_from (keyframe depths and map units scale by its s),
  /// every point of `from` moves with it (its cell re-keyed, its distance range refreshed)
  /// and both are relabelled `into`. The merge is recorded (segment_merge) and published as a
  /// correction of `from` (publish_correction), so a reader holding a pose of `from` moves it
  /// into the frame of `into` and then follows `into`. Returns the keyframes moved; 0 and
  /// nothing done for a segment id of kMaxSegments or more, from == into, a segment already
  /// merged, a discarded one (discard_segment), or a non-finite similarity.
  std::uint32_t merge_segment(std::uint16_t from, std::uint16_t into,
                              const geometry::Sim3d& S_into_from);
  /// Marks `segment` discarded (a failed start: tracking.init.discard_failed_starts), from any
  /// thread, without the writer lock. A discarded segment's keyframes are never relocalized or
  /// closed a loop against, map culling removes them, and it never merges. False (nothing
  /// done) for an id of kMaxSegments or more, or a segment that is merging or merged: the
  /// discard and merge_segment claim the segment atomically, the first one wins.
  bool discard_segment(std::uint16_t segment) noexcept;
  /// Whether `segment` was discarded (acquire; any thread); false for an id out of range.
  bool segment_discarded(std::uint16_t segment) const noexcept;
  /// Segments discarded so far (acquire; any thread).
  std::uint32_t discarded_segments() const noexcept {
    return discarded_count_.load(std::memory_order_acquire);
  }
  /// Records that `segment`'s start is in the map (first and last keyframe; kInserted) or
  /// could not be inserted (kRefused, ids kNoId), once per segment, after its keyframes and
  /// points are written: a reader that sees the record (segment_start) sees them too.
  /// Ignored for a segment id of kMaxSegments or more.
  void publish_segment_start(std::uint16_t segment, SegmentStartState state, KeyframeId first,
                             KeyframeId last) noexcept;
  /// Sets the depth / confidence of one keypoint (depth refinement after publication).
  void set_keyframe_depth(KeyframeId kf, std::uint32_t kp, float depth, float confidence);
  /// Frees a point: not live (generation incremented), removed from its cell, its keypoint
  /// associations and observations cleared, its slot queued for reuse. Covisibility weights
  /// change at the next update_covisibility.
  void set_point_bad(PointId p);
  /// Merges two points that are one (duplicates): drop's observations move to keep (those
  /// of a keyframe that already observes keep, or beyond keep's observation capacity, are
  /// dropped), drop is freed (set_point_bad) and keep's descriptor / normal are refreshed.
  /// keep's position is kept. Returns the observations moved, or -1 when either id is not a
  /// live point or they are the same. Covisibility weights change at the next
  /// update_covisibility.
  int merge_points(PointId keep, PointId drop);
  /// Removes keyframe kf: every covisibility edge to it, its observations from its points
  /// (a point whose reference it was takes its first remaining observation as reference),
  /// and frees the points left with fewer than max(1, min_point_observations) observations
  /// (counted in *bad_points). The slot is queued for reuse. False (nothing done) for an id
  /// that is not live or for the newest keyframe (newest_keyframe() always names a live one).
  bool remove_keyframe(KeyframeId kf, std::uint32_t min_point_observations,
                       std::uint32_t* bad_points = nullptr);
  /// Recomputes kf's KF-KF edges (weight = shared non-bad points; the strongest
  /// map.max_covisible_per_keyframe kept, sorted by weight desc then id asc) and the reverse
  /// edges in every keyframe sharing points with kf (each keeps its strongest edges too);
  /// reverse edges of former neighbours that share nothing any more are removed.
  void update_covisibility(KeyframeId kf);
  /// Observations (keyframe, keypoint) of p, up to out.size(); the count written.
  std::size_t point_observations(PointId p,
                                 std::span<std::pair<KeyframeId, std::uint32_t>> out) const;
  /// Number of observations of p (0 for a bad or unknown point).
  std::size_t point_num_observations(PointId p) const;
  /// Observations, visible / found counters and creation serial of p (zeros if not live).
  PointStats point_stats(PointId p) const;
  /// Keyframes added so far; the newest keyframe's serial is keyframes_added() - 1.
  std::uint64_t keyframes_added() const noexcept { return kf_serial_next_; }
  /// Serial (insertion order, 0 for the first keyframe ever added) of a live keyframe;
  /// kNoSerial for an id that is not live.
  std::uint64_t keyframe_serial(KeyframeId kf) const noexcept;
  /// T_a_b = T_w_a^-1 * T_w_b from the current poses (identity for an unknown id).
  SE3d relative_pose(KeyframeId a, KeyframeId b) const;
  /// Live / used / freed / reused slot counts.
  MapCounters counters() const noexcept;
  /// Registers a reader thread for slot reclamation (setup call: before the reader and the
  /// writer run concurrently). The handle is passed to reader_quiescent(). Error when
  /// kMaxMapReaders readers are registered.
  Result<int> register_reader();
  /// Unregisters a reader: from its own thread once it reads the map no more (its release
  /// store orders its reads before any reuse), or as a setup call.
  void release_reader(int reader) noexcept;

  // ------------------------------------------------------- any thread, lock-free --------
  /// Quiescent point of a registered reader: it holds no map reference except ids it will
  /// validate by generation. Call at the start of each unit of work.
  void reader_quiescent(int reader) noexcept;
  /// Keyframe slots ever used (acquire); ids below it may be live.
  std::uint32_t num_keyframes() const noexcept;
  /// Point slots ever used (acquire); ids below it may be live.
  std::uint32_t num_points() const noexcept;
  /// The keyframe added last (kNoId before the first one).
  KeyframeId newest_keyframe() const noexcept;
  /// Live keyframes / points (relaxed snapshots).
  std::uint32_t live_keyframes() const noexcept;
  std::uint32_t live_points() const noexcept;
  /// Every live keyframe's capture time and pose, sorted by time; only those of `segment`
  /// unless it is kNoSegment. Allocates: not for the real-time threads (outputs and offline
  /// tools read it once the stages have stopped).
  std::vector<StampedPose> live_keyframe_poses(std::uint16_t segment = kNoSegment) const;
  /// True for a live keyframe.
  bool keyframe_is_live(KeyframeId kf) const noexcept;
  /// Generation of a live keyframe, kNoGeneration otherwise.
  Generation keyframe_generation(KeyframeId kf) const noexcept;
  /// Generation of a live point, kNoGeneration otherwise.
  Generation point_generation(PointId p) const noexcept;
  /// Corrections published so far, of all segments (acquire; any thread).
  std::uint32_t correction_count() const noexcept;
  /// The cumulative correction of one segment and the number of that segment's corrections it
  /// includes (identity and 0 for a segment never corrected or out of range); false after
  /// failed retries.
  bool read_correction(std::uint16_t segment, geometry::Sim3d& S,
                       std::uint32_t& count) const noexcept;
  /// Consistent pose (and scale); false for an unknown id or after failed retries.
  bool keyframe_pose(KeyframeId kf, SE3d& T_w_c, double* scale = nullptr) const noexcept;
  /// Keypoints of kf (valid until the caller's next quiescent point; empty for an unknown
  /// id). Their positions are writer-side data: lock-free readers may use the size only.
  std::span<const features::Keypoint> keyframe_keypoints(KeyframeId kf) const noexcept;
  /// Descriptors of kf (as keyframe_keypoints).
  std::span<const features::Descriptor> keyframe_descriptors(KeyframeId kf) const noexcept;
  /// Number of keypoints of kf (0 for an unknown id).
  std::uint32_t keyframe_num_keypoints(KeyframeId kf) const noexcept;
  /// Capture time of kf, ns (0 for an unknown id).
  std::int64_t keyframe_t_ns(KeyframeId kf) const noexcept;
  /// Frame sequence number of kf (0 for an unknown id).
  std::uint64_t keyframe_seq(KeyframeId kf) const noexcept;
  /// Map segment of kf (KeyframeInput::segment; kNoSegment for an unknown id). A segment's
  /// keyframes and points share one world frame, unrelated to another segment's until the two
  /// are merged; its points are those whose reference keyframe is in it.
  std::uint16_t keyframe_segment(KeyframeId kf) const noexcept;
  /// The merge of `segment` into another (acquire; any thread); false when it never merged
  /// (or the id is out of range). Follow `into` for later merges.
  bool segment_merge(std::uint16_t segment, SegmentMerge& out) const noexcept;
  /// How the start of `segment` stands (acquire; any thread): kPending until keyframe creation
  /// has inserted or refused it (publish_segment_start), and for an id out of range.
  SegmentStartRecord segment_start(std::uint16_t segment) const noexcept;
  /// The segment `segment` ended up in after every merge (itself when it never merged) and
  /// the similarity from its world frame to that one's (composed along the merges).
  std::uint16_t merged_segment(std::uint16_t segment,
                               geometry::Sim3d& S_final_segment) const noexcept;
  /// Point associated with keypoint kp of kf, kNoId if none.
  PointId keyframe_point(KeyframeId kf, std::uint32_t kp) const noexcept;
  /// Depth (camera z, map units; 0: unknown) of keypoint kp of kf.
  float keyframe_depth(KeyframeId kf, std::uint32_t kp) const noexcept;
  /// Depth confidence of keypoint kp of kf (0: none).
  float keyframe_depth_confidence(KeyframeId kf, std::uint32_t kp) const noexcept;
  /// Keypoint kp of kf as a 3D point in kf's camera frame: depth * K^-1 [u v 1]. False when
  /// the depth is unknown or an id is invalid.
  bool keyframe_point_3d(KeyframeId kf, std::uint32_t kp, const geometry::Pinhole& K,
                         Eigen::Vector3d& p_c) const noexcept;
  /// Consistent snapshot of p; false if bad, unpublished or inconsistent after retries.
  bool read_point(PointId p, PointView& out) const noexcept;
  /// True for a bad or unpublished point.
  bool point_is_bad(PointId p) const noexcept;
  /// Counts a frame p projected into (tracking statistics; relaxed atomic add).
  void note_visible(PointId p) noexcept;
  /// Counts a frame p was a tracked inlier in (tracking statistics; relaxed atomic add).
  void note_found(PointId p) noexcept;
  /// kf's covisible keyframes sorted by weight desc (up to out.size()); count written (0 for
  /// an unknown id or after failed retries).
  std::size_t covisible_keyframes(KeyframeId kf, std::span<CovisibleKeyframe> out) const noexcept;
  /// Weight of the edge a->b as stored in a's list (0 if none).
  std::uint32_t covisibility_weight(KeyframeId a, KeyframeId b) const noexcept;
  /// Distinct ids of the points of `segment` (their reference keyframe's) in the cells
  /// intersecting the view frustum of a camera at T_w_c (K, width x height px, camera-z range
  /// [near, far] in that segment's map units), nearest cell layers first (unless a concurrent
  /// move forced a de-duplication, which sorts by id). A superset of the segment's points
  /// that project into the image within [near, far]: filter by projection. Up to out.size()
  /// ids; the count written (0 for a degenerate camera).
  std::size_t query_visible(const SE3d& T_w_c, const geometry::Pinhole& K, int width, int height,
                            double near, double far, std::uint16_t segment,
                            std::span<PointId> out) const noexcept;
  /// Distinct ids of the points of `segment` in the cells intersecting the ball (c_w,
  /// radius): a superset of its points within radius, each within radius + one cell diagonal.
  std::size_t query_radius(const Eigen::Vector3d& c_w, double radius, std::uint16_t segment,
                           std::span<PointId> out) const noexcept;

  /// Effective options.
  const MapOptions& options() const noexcept { return opts_; }
  /// Cell inserts that failed (full cell, full table, position out of range), all attempts.
  std::uint64_t cell_insert_failures() const noexcept { return grid_.failures(); }
  /// The cell grid (statistics, direct cell access for tests and tools).
  const CellGrid& cell_grid() const noexcept { return grid_; }
  /// Bytes of preallocated storage.
  std::size_t memory_bytes() const noexcept;

 private:
  // Seqlock payload layouts (64-bit words).
  static constexpr int kPoseRotation = 0;     // 9 words, column-major
  static constexpr int kPoseTranslation = 9;  // 3 words
  static constexpr int kPoseScale = 12;
  static constexpr int kPoseWords = 13;
  static constexpr int kCorrectionWords = 14;  // rotation 9, translation 3, scale, count
  static constexpr int kPointPosition = 0;     // 3 words
  static constexpr int kPointDescriptor = 3;   // 4 words
  static constexpr int kPointNormalXY = 7;     // floats (normal x, normal y)
  static constexpr int kPointNormalZMin = 8;   // floats (normal z, min distance)
  static constexpr int kPointMax = 9;          // floats (max distance, unused)
  static constexpr int kPointRef = 10;         // reference keyframe (low), keypoint (high)
  static constexpr int kPointWords = 11;

  /// State word: generation << 1 | live.
  static constexpr std::uint32_t kLiveBit = 1U;
  static bool is_live(std::uint32_t state) noexcept { return (state & kLiveBit) != 0U; }
  static Generation generation_of(std::uint32_t state) noexcept { return state >> 1U; }
  /// The state of the slot's next occupant while it is free.
  static std::uint32_t freed(std::uint32_t state) noexcept {
    return (generation_of(state) + 1U) << 1U;
  }
  /// Announcement of a reader slot nobody registered.
  static constexpr std::uint64_t kReaderUnused = ~std::uint64_t{0};

  struct KeyframeSlot {
    std::uint64_t seq = 0;  // immutable while live
    std::int64_t t_ns = 0;
    std::uint32_t num_keypoints = 0;
    std::atomic<std::uint16_t> segment{0};  // relabelled by merge_segment (relaxed)
    std::atomic<std::uint32_t> state{0};    // generation << 1 | live
    SeqLock pose_lock;
    std::atomic<std::uint64_t> pose[kPoseWords] = {};
    SeqLock covis_lock;
    std::atomic<std::uint32_t> covis_count{0};
  };
  struct PointSlot {
    SeqLock lock;
    std::atomic<std::uint32_t> state{0};  // generation << 1 | live; stored in write sections
    std::atomic<std::uint64_t> words[kPointWords] = {};
  };
  /// (keyframe, keypoint) in 32 bits: the option ranges keep max_keyframes <= 100000 <
  /// 2^18 and max_keypoints_per_keyframe <= 2^14 (halves the largest writer-side array).
  struct Observation {
    static constexpr unsigned kKeypointBits = 14;
    std::uint32_t bits = 0;
    static Observation make(KeyframeId kf, std::uint32_t kp) noexcept {
      return {(kf << kKeypointBits) | kp};
    }
    KeyframeId kf() const noexcept { return bits >> kKeypointBits; }
    std::uint32_t kp() const noexcept { return bits & ((1U << kKeypointBits) - 1U); }
  };
  /// A freed slot and the epoch it may be reused from.
  struct Retired {
    std::uint64_t epoch = 0;
    std::uint32_t id = 0;
  };
  /// FIFO of freed slots (capacity: every slot once); epochs increase from front to back.
  struct RetireQueue {
    std::unique_ptr<Retired[]> items;
    std::uint32_t capacity = 0;
    std::uint32_t head = 0;
    std::uint32_t size = 0;
    explicit RetireQueue(std::uint32_t cap)
        : items(std::make_unique<Retired[]>(cap)), capacity(cap) {}
    void push(std::uint32_t id, std::uint64_t epoch) noexcept {
      items[(head + size) % capacity] = {epoch, id};
      ++size;
    }
    const Retired& front() const noexcept { return items[head]; }
    void pop() noexcept {
      head = (head + 1U) % capacity;
      --size;
    }
  };
  /// One registered reader's last announced epoch, alone on its cache line.
  struct alignas(platform::kCacheLine) ReaderSlot {
    std::atomic<std::uint64_t> announced{kReaderUnused};
  };

  std::size_t kp_index(KeyframeId kf, std::uint32_t kp) const noexcept {
    return static_cast<std::size_t>(kf) * max_kp_ + kp;
  }
  bool live_keyframe(KeyframeId kf) const noexcept;  // acquire: any thread
  bool valid_keypoint(KeyframeId kf, std::uint32_t kp) const noexcept;
  bool own_keyframe(KeyframeId kf) const noexcept;  // writer: live
  bool own_point(PointId p) const noexcept;         // writer: live
  static SE3d decode_pose(const std::uint64_t (&w)[kPoseWords]) noexcept;
  static void decode_point(const std::uint64_t (&w)[kPointWords], PointView& out) noexcept;
  SE3d own_pose(KeyframeId kf) const noexcept;
  Eigen::Vector3d own_position(PointId p) const noexcept;
  KeyframeId own_ref_keyframe(PointId p) const noexcept;
  std::uint32_t own_ref_keypoint(PointId p) const noexcept;
  void write_pose(KeyframeId kf, const SE3d& T_w_c, double scale) noexcept;
  void write_position(PointId p, const Eigen::Vector3d& p_w) noexcept;
  void write_shape(PointId p, const features::Descriptor& d, const Eigen::Vector3d& normal,
                   float min_d, float max_d) noexcept;
  void write_ref(PointId p, KeyframeId kf, std::uint32_t kp) noexcept;
  void write_point_state(PointId p, std::uint32_t state) noexcept;
  void shape_from_ref(PointId p, const Eigen::Vector3d& p_w, Eigen::Vector3d& normal, float& min_d,
                      float& max_d) const noexcept;
  std::uint32_t own_covis(KeyframeId kf, CovisibleKeyframe* out) const noexcept;
  void write_covis(KeyframeId kf, const CovisibleKeyframe* list, std::uint32_t n) noexcept;
  void upsert_edge(KeyframeId owner, KeyframeId other, std::uint32_t weight) noexcept;
  void remove_edge(KeyframeId owner, KeyframeId other) noexcept;
  std::uint64_t retire_epoch() noexcept;  // advances the epoch
  bool readers_passed(std::uint64_t epoch) const noexcept;
  std::uint32_t take_slot(std::atomic<std::uint32_t>& high_water, std::uint32_t capacity,
                          RetireQueue& retired, std::uint64_t& reused) noexcept;

  MapOptions opts_;
  platform::PiMutex writer_lock_;
  std::uint32_t max_kf_;
  std::uint32_t max_pts_;
  std::uint32_t max_kp_;
  std::uint32_t max_obs_;
  std::uint32_t max_cov_;

  // Reader-visible storage.
  std::unique_ptr<KeyframeSlot[]> kfs_;
  std::unique_ptr<features::Keypoint[]> kf_keypoints_;      // max_kf x max_kp
  std::unique_ptr<features::Descriptor[]> kf_descriptors_;  // max_kf x max_kp
  std::unique_ptr<std::atomic<PointId>[]> kf_points_;       // max_kf x max_kp
  std::unique_ptr<std::atomic<float>[]> kf_depth_;          // max_kf x max_kp
  std::unique_ptr<std::atomic<float>[]> kf_depth_conf_;     // max_kf x max_kp
  std::unique_ptr<std::atomic<std::uint64_t>[]> covis_;     // max_kf x max_cov (id<<32|w)
  std::unique_ptr<PointSlot[]> points_;
  std::unique_ptr<std::atomic<std::uint32_t>[]> pt_visible_;  // max_pts, reader-incremented
  std::unique_ptr<std::atomic<std::uint32_t>[]> pt_found_;    // max_pts, reader-incremented
  CellGrid grid_;

  // Writer-only storage.
  std::unique_ptr<Observation[]> obs_;           // max_pts x max_obs
  std::unique_ptr<std::uint8_t[]> obs_count_;    // max_pts
  std::unique_ptr<CellKey[]> point_cell_;        // cell holding each point, kNoCell if none
  std::unique_ptr<std::uint64_t[]> kf_serial_;   // max_kf: insertion order of the occupant
  std::unique_ptr<std::uint64_t[]> pt_serial_;   // max_pts: keyframes_added() at creation
  std::unique_ptr<std::uint16_t[]> pt_segment_;  // max_pts: segment (of the reference keyframe)
  RetireQueue kf_retired_;
  RetireQueue pt_retired_;
  std::uint64_t kf_serial_next_ = 0;
  SeqLock correction_lock_;
  // kMaxSegments x kCorrectionWords: each segment's cumulative correction and its count.
  std::unique_ptr<std::atomic<std::uint64_t>[]> correction_ =
      std::make_unique<std::atomic<std::uint64_t>[]>(std::size_t{kMaxSegments} * kCorrectionWords);
  std::atomic<std::uint32_t> correction_count_{0};  // all segments
  // kMaxSegments: the segment each one merged into (kNoSegment: none; release-published after
  // its record in merges_, which is never written again).
  std::unique_ptr<std::atomic<std::uint16_t>[]> merged_into_ =
      std::make_unique<std::atomic<std::uint16_t>[]>(kMaxSegments);
  std::unique_ptr<SegmentMerge[]> merges_ = std::make_unique<SegmentMerge[]>(kMaxSegments);
  // kMaxSegments: SegmentFate of each one, claimed by compare-exchange from kLive (a discard
  // by the tracker, a merge by the loop closer: whichever comes first).
  std::unique_ptr<std::atomic<std::uint8_t>[]> fate_ =
      std::make_unique<std::atomic<std::uint8_t>[]>(kMaxSegments);
  std::atomic<std::uint32_t> discarded_count_{0};
  // kMaxSegments: each segment's start (state release-published after its keyframe ids).
  std::unique_ptr<std::atomic<SegmentStartState>[]> start_state_ =
      std::make_unique<std::atomic<SegmentStartState>[]>(kMaxSegments);
  std::unique_ptr<SegmentStartRecord[]> starts_ =
      std::make_unique<SegmentStartRecord[]>(kMaxSegments);
  // Writer side copies of each segment's cumulative correction.
  std::unique_ptr<geometry::Sim3d[]> correction_own_ =
      std::make_unique<geometry::Sim3d[]>(kMaxSegments);
  std::uint64_t epoch_own_ = 0;  // writer's copy of epoch_
  std::uint64_t removed_keyframes_ = 0;
  std::uint64_t bad_points_ = 0;
  std::uint64_t merged_points_ = 0;
  std::uint64_t reused_kf_slots_ = 0;
  std::uint64_t reused_pt_slots_ = 0;

  // Writer scratch (sized at construction).
  std::unique_ptr<std::uint32_t[]> covis_weight_;      // max_kf, all zero between calls
  std::unique_ptr<KeyframeId[]> covis_touched_;        // max_kf
  std::unique_ptr<CovisibleKeyframe[]> covis_sorted_;  // max_kf
  std::unique_ptr<CovisibleKeyframe[]> list_scratch_;  // max_cov + 1
  std::unique_ptr<int[]> medoid_dist_;                 // max_obs x max_obs
  std::unique_ptr<int[]> medoid_row_;                  // max_obs
  std::unique_ptr<Observation[]> merge_scratch_;       // max_obs

  alignas(platform::kCacheLine) std::atomic<std::uint32_t> num_keyframes_{0};
  std::atomic<KeyframeId> newest_kf_{kNoId};
  std::atomic<std::uint32_t> live_kfs_{0};
  alignas(platform::kCacheLine) std::atomic<std::uint32_t> num_points_{0};
  std::atomic<std::uint32_t> live_pts_{0};
  alignas(platform::kCacheLine) std::atomic<std::uint64_t> epoch_{0};
  ReaderSlot readers_[kMaxMapReaders];
};

}  // namespace mer::map
