#pragma once
/// @file tracking_options.h
/// Options of the localization front end (config section `tracking`).

#include <array>
#include <cstdint>
#include <string_view>

#include "core/options.h"
#include "features/extractor.h"
#include "frontend/keyframe_policy.h"
#include "geometry/pnp.h"
#include "geometry/two_view.h"
#include "map/map_types.h"

namespace mer::frontend {

/// Projection-guided matching of map-points against the frame's keypoints.
struct MatchOptions {
  int max_hamming = 80;
  double ratio = 0.85;
  double radius_px = 10.0;
  double wide_radius_px = 40.0;
  double refine_radius_px = 4.0;
  int min_matches = 40;
  int grid_cell_px = 16;
  double min_view_cos = 0.4;
  int level_window = 1;

  template <class V>
  void visit(V& v) {
    v.field("max_hamming", max_hamming, "largest descriptor distance of a match",
            options::Range<int>{0, 256});
    v.field("ratio", ratio, "best / second-best descriptor distance ratio",
            options::Range<double>{0.0, 1.0});
    v.field("radius_px", radius_px, "search radius around the predicted projection, px",
            options::Range<double>{0.5, 1000.0});
    v.field("wide_radius_px", wide_radius_px, "search radius when the prediction is poor, px",
            options::Range<double>{0.5, 2000.0});
    v.field("refine_radius_px", refine_radius_px,
            "search radius of the second pass with the estimated pose, px",
            options::Range<double>{0.5, 1000.0});
    v.field("min_matches", min_matches, "fewer matches retries with the wide radius",
            options::Range<int>{3, 100000});
    v.field("grid_cell_px", grid_cell_px, "keypoint grid cell size, px",
            options::Range<int>{2, 512});
    v.field("min_view_cos", min_view_cos,
            "cosine of the largest angle between the view ray and a point's mean view direction",
            options::Range<double>{-1.0, 1.0});
    v.field("level_window", level_window, "pyramid levels around the predicted level searched",
            options::Range<int>{0, 16});
  }
};

/// Photometric refinement of the initializer's matches (`tracking.init.align`).
struct InitAlignOptions {
  bool enabled = false;
  bool drop_refused = true;
  double max_rms = 255.0;
  double max_shift_px = 1.5;

  template <class V>
  void visit(V& v) {
    v.field("enabled", enabled,
            "move each match to where the reference keypoint's patch (its pixels in the "
            "reference frame, at the keypoint's pyramid level) aligns best in the frame, so "
            "that every frame measures the same surface point the reference saw, not an "
            "independent detection near it");
    v.field("drop_refused", drop_refused,
            "a match whose alignment is refused (residual, shift, no texture) is dropped; off: "
            "its detection is kept");
    v.field("max_rms", max_rms,
            "an alignment whose RMS intensity residual (grey levels, brightness offset removed) "
            "stays above this is refused (255: no residual gate; image noise, blur and the "
            "change of viewpoint set the residual of a right match too)",
            options::Range<double>{0.0, 255.0});
    v.field("max_shift_px", max_shift_px,
            "an alignment that moves the match farther than this from its detection (px of the "
            "keypoint's pyramid level) is refused",
            options::Range<double>{0.1, 10.0});
  }
};

/// Monocular start over a window of frames (frontend/initializer.h): when the two-view
/// reconstruction of the reference and the current frame refuses an essential model's motion
/// as uncertain, the frames tracked in between decide it (a bundle adjustment of the window,
/// geometry/window_ba.h).
struct InitWindowOptions {
  bool enabled = true;
  bool decide_ties = false;
  int max_views = 8;
  int min_views = 2;
  int max_points = 300;
  int iterations = 20;
  double min_evidence_sigmas = 4.0;
  double max_moved_rotation_deg = 0.5;
  double max_moved_direction_deg = 5.0;

  template <class V>
  void visit(V& v) {
    v.field("enabled", enabled,
            "decide with the frames tracked in between the pairs the two-view reconstruction "
            "refuses as an uncertain essential-model motion (low parallax)");
    v.field("decide_ties", decide_ties,
            "also decide the pairs refused as ambiguous (two motion candidates, a wall's "
            "homography and its twin) on the window (off: a tie waits for parallax; when the "
            "camera moves along a line the twin explains the frames in between as well as the "
            "truth, and a few wrong tracks then decide it)");
    v.field("max_views", max_views,
            "frames kept between the reference and the current frame (spread evenly: when "
            "full, every other one is dropped)",
            options::Range<int>{1, 64});
    v.field("min_views", min_views, "frames in between needed to decide",
            options::Range<int>{1, 64});
    v.field("max_points", max_points,
            "points (spread over the matches) in each candidate's bundle adjustment",
            options::Range<int>{8, 100000});
    v.field("iterations", iterations, "Levenberg-Marquardt iterations per solve",
            options::Range<int>{1, 1000});
    v.field(
        "min_evidence_sigmas", min_evidence_sigmas,
        "with decide_ties: the winning motion candidate's points must cost less than every other "
        "candidate's by this many standard errors of the mean per-point difference (a "
        "paired test over the window's points), or the window is ambiguous",
        options::Range<double>{0.0, 1e6});
    v.field("max_moved_rotation_deg", max_moved_rotation_deg,
            "released from the candidate's motion, a solution of the whole window may turn "
            "the current frame this far, or the motion is uncertain, deg",
            options::Range<double>{0.0, 180.0});
    v.field("max_moved_direction_deg", max_moved_direction_deg,
            "and move its translation direction this far, deg", options::Range<double>{0.0, 180.0});
  }
};

/// Monocular / RGB-D initialization.
struct InitOptions {
  geometry::TwoViewOptions two_view;
  InitWindowOptions window;
  InitAlignOptions align;
  double search_radius_px = 100.0;
  int max_hamming = 60;
  double ratio = 0.9;
  int min_features = 150;
  double max_reference_age_s = 1.4;
  double rotation_renew_fraction = 0.5;
  double failed_start_window_s = 1.0;
  int failed_start_max_keyframes = 5;
  bool discard_failed_starts = true;
  bool plane_hints = false;
  double max_plane_hint_reference_age_s = 3.0;
  int rgbd_min_points = 100;

  template <class V>
  void visit(V& v) {
    v.section("two_view", two_view, "two-view reconstruction (monocular)");
    v.section("window", window, "monocular start over a window of frames");
    v.section("align", align, "photometric refinement of the matches to the reference (monocular)");
    v.field("search_radius_px", search_radius_px,
            "window of the frame-to-frame search of the reference keypoints, px",
            options::Range<double>{1.0, 4000.0});
    v.field("max_hamming", max_hamming, "descriptor distance of an initialization match",
            options::Range<int>{0, 256});
    v.field("ratio", ratio, "best / second-best ratio of an initialization match",
            options::Range<double>{0.0, 1.0});
    v.field("min_features", min_features, "keypoints a reference frame needs",
            options::Range<int>{8, 100000});
    v.field("max_reference_age_s", max_reference_age_s,
            "time a reference frame is kept while initialization is refused, s",
            options::Range<double>{0.01, 1e6});
    v.field("rotation_renew_fraction", rotation_renew_fraction,
            "a frame refused as a pure rotation of the reference that matches fewer than this "
            "fraction of the matches of the reference's first frame becomes the next reference "
            "and keeps its orientation, so that a sweep out of the reference's view stays in one "
            "chain of known orientation (0: only when matches run out or the reference is too "
            "old)",
            options::Range<double>{0.0, 1.0});
    v.field("failed_start_window_s", failed_start_window_s,
            "a segment lost within this time of its start, with at most "
            "failed_start_max_keyframes keyframes, counts as a failed start (summary.json "
            "tracking.failed_starts), s",
            options::Range<double>{0.0, 1e6});
    v.field("failed_start_max_keyframes", failed_start_max_keyframes,
            "most keyframes a segment lost within failed_start_window_s of its start may have "
            "to count as a failed start",
            options::Range<int>{0, 1000000});
    v.field("discard_failed_starts", discard_failed_starts,
            "discard the segment of a failed start: its frames count as lost and leave the "
            "trajectory files, its keyframes are removed from the map and are never "
            "relocalized or closed a loop against, and the next start begins at once (the "
            "first map: state initializing again). Off: the segment is kept and the tracker "
            "relocalizes in it as after any loss");
    v.field("plane_hints", plane_hints,
            "break the two-fold tie of a planar scene with the plane normals an earlier frame "
            "of the same reference reported (off by default: on room_orbit it initializes "
            "1.8-2.5 s into the stream from a thin planar map, and 5 of 8 seeds then diverge)");
    v.field("max_plane_hint_reference_age_s", max_plane_hint_reference_age_s,
            "time a reference frame is kept once an ambiguous planar pair gave it plane hints "
            "(the twin's plane normal turns with the translation until a later frame breaks "
            "the tie), s",
            options::Range<double>{0.01, 1e6});
    v.field("rgbd_min_points", rgbd_min_points, "RGB-D: keypoints with valid depth needed to start",
            options::Range<int>{3, 100000});
  }
};

/// Focal-length estimation (`pipeline.focal: auto`).
struct FocalOptions {
  int min_init_estimates = 5;
  double min_disparity_px = 20.0;
  int stable_frames = 15;
  double stable_tolerance = 0.01;
  int max_frames = 150;
  bool refine_after_init = false;

  template <class V>
  void visit(V& v) {
    v.field("min_init_estimates", min_init_estimates,
            "two-view focal estimates needed before initializing", options::Range<int>{1, 1000});
    v.field("min_disparity_px", min_disparity_px,
            "median disparity a frame pair needs to estimate the focal length, px",
            options::Range<double>{0.0, 1000.0});
    v.field("stable_frames", stable_frames,
            "consecutive estimates within tolerance of the running median that fix the focal",
            options::Range<int>{1, 10000});
    v.field("stable_tolerance", stable_tolerance, "relative tolerance of a stable estimate",
            options::Range<double>{0.0, 1.0});
    v.field("max_frames", max_frames, "tracked frames after which the focal is fixed anyway",
            options::Range<int>{1, 1000000});
    v.field("refine_after_init", refine_after_init,
            "after initialization, keep estimating the focal jointly with each PnP pose until "
            "stable (off: fixed to the two-view median at initialization; PnP against a map "
            "built with that focal mostly confirms it)");
  }
};

/// When a relocalizer's pose is trusted (`tracking.relocalization_check`). After a short loss
/// the camera cannot be far from where its last tracked motion was taking it: a pose within
/// the motion bound is trusted at once. The bound is centred on the last tracked pose carried
/// on at the last tracked velocity (rotation and translation, from the last two tracked
/// frames; at rest when they were not consecutive) and grows with the largest acceleration
/// assumed, as a t^2 / 2 over the time lost t, plus a margin; translation is in median scene
/// depths of the last tracked frame, so that it holds in map units.
/// A pose outside the bound after a short loss is refused: the camera cannot be there, and
/// the tracker keeps searching from its own last pose. A pose of another segment, or any pose
/// after a longer loss, is a candidate: the following frames are tracked from it against the
/// local map, and it is trusted only when `confirm_frames` of them in a row are tracked, each
/// finding (as PnP inliers) a share of the map-points it projects into view of at least
/// `min_found_fraction` of that share's median over the last tracked frames. A look-alike
/// place (a repeated poster, tile or panel) explains the matched pattern but not the rest of
/// the view.
/// The evidence for a place is the lost spell's, not one offer's: the relocalizer offers a
/// look-alike again and again while the camera looks at the copy, and a check that each
/// offer fails most of the time is passed by one of them sooner or later. So every offer
/// refused during a spell counts against its place (the keyframe it was found against and
/// the keyframes that share map-points with it), and a candidate at a place refused n times
/// must be confirmed on `confirm_frames + n` frames in a row (at most
/// `max_confirm_frames`): the frames for the place outnumber the offers against it. The
/// count is forgotten when a frame is tracked. Frames of a candidate are reported lost and
/// write nothing to the map; a refused offer or candidate is counted by reason.
/// What may bring a camera back to a mapped place after a long loss (beyond short_loss_s).
enum class LongLossReturn : std::uint8_t { kConfirm, kMerge };
/// Names of LongLossReturn in config, by value.
inline constexpr std::array<std::string_view, 2> kLongLossReturnNames{"confirm", "merge"};

struct RelocalizationCheckOptions {
  bool enabled = true;
  double short_loss_s = 0.5;
  double max_accel_depths_per_s2 = 4.0;
  double max_angular_accel_deg_per_s2 = 360.0;
  double margin_depths = 0.1;
  double margin_deg = 10.0;
  int confirm_frames = 3;
  double min_found_fraction = 0.4;
  int max_confirm_frames = 30;
  LongLossReturn after_long_loss = LongLossReturn::kConfirm;

  template <class V>
  void visit(V& v) {
    v.field("enabled", enabled,
            "check a relocalizer's pose before it is trusted: within the motion bound after a "
            "short loss it is trusted at once, otherwise the following frames must confirm it "
            "(off: every pose found is trusted at once)");
    v.field("short_loss_s", short_loss_s,
            "a loss up to this long bounds where the camera can be (from the last tracked pose); "
            "after a longer one every relocalization is confirmed on the following frames, s",
            options::Range<double>{0.0, 1e6});
    v.field("max_accel_depths_per_s2", max_accel_depths_per_s2,
            "largest change of the camera's velocity the bound assumes, in median scene depths "
            "(of the last tracked frame) per second squared: after t seconds lost the camera "
            "is within a t^2 / 2 of where its last velocity was taking it",
            options::Range<double>{0.0, 1e6});
    v.field("max_angular_accel_deg_per_s2", max_angular_accel_deg_per_s2,
            "largest change of the camera's turn rate the bound assumes, degrees per second "
            "squared (as max_accel_depths_per_s2, for the orientation)",
            options::Range<double>{0.0, 1e6});
    v.field("margin_depths", margin_depths,
            "added to the translation bound, in median scene depths",
            options::Range<double>{0.0, 1e6});
    v.field("margin_deg", margin_deg, "added to the rotation bound, degrees",
            options::Range<double>{0.0, 360.0});
    v.field("confirm_frames", confirm_frames,
            "frames in a row a relocalization outside the bound must be tracked in, against "
            "the local map, before it is trusted (they are reported lost meanwhile)",
            options::Range<int>{1, 1000});
    v.field("min_found_fraction", min_found_fraction,
            "a confirming frame must find (as PnP inliers) a share of the map-points it "
            "projects into view of at least this fraction of that share's median over the "
            "last tracked frames (measured on tracked frames of synthetic rooms, a corridor "
            "and KITTI: the lowest share was 0.41-0.71 of the median)",
            options::Range<double>{0.0, 1.0});
    v.field("max_confirm_frames", max_confirm_frames,
            "a candidate at a place whose offers were refused n times earlier in the same lost "
            "spell must be confirmed on confirm_frames + n frames in a row, at most this many "
            "(and at least confirm_frames)",
            options::Range<int>{1, 100000});
    v.field("after_long_loss", after_long_loss,
            "what brings the camera back to a mapped place after a loss longer than "
            "short_loss_s: confirm (the relocalizer keeps looking, in every segment, and its "
            "pose is confirmed on the following frames) or merge (the relocalizer looks only "
            "while the loss is short; after that a new segment holds the frames and joins the "
            "map only through a loop closure's merge, which checks the new segment's own "
            "structure against the old map both ways: a view of an unmapped copy of a mapped "
            "place cannot pass for a return)",
            options::Names<LongLossReturn>{kLongLossReturnNames});
  }
};

/// Options of the tracking stage.
struct TrackingOptions {
  features::ExtractorOptions extractor;
  MatchOptions match;
  geometry::PnpOptions pnp;
  KeyframePolicyOptions keyframe;
  InitOptions init;
  FocalOptions focal;
  bool scale_features_with_area = true;
  int temporal_frames = 5;
  int max_query_points = 12000;
  double query_far = 4.0;
  double spatial_max_age_s = 0.0;
  int min_inliers = 25;
  int relocalize_after_lost_frames = 2;
  bool new_segments = true;
  double new_segment_after_s = 0.5;
  int max_segments = 64;
  RelocalizationCheckOptions relocalization_check;
  int busy_work_us = 0;
  double rgbd_max_depth_step = 0.03;

  template <class V>
  void visit(V& v) {
    v.section("extractor", extractor, "keypoint extraction (ORB)");
    v.section("match", match, "projection-guided map-point matching");
    v.section("pnp", pnp, "PnP-RANSAC and pose refinement");
    v.section("keyframe", keyframe, "keyframe decision");
    v.section("init", init, "map initialization");
    v.section("focal", focal, "focal-length estimation (pipeline.focal: auto)");
    v.field("scale_features_with_area", scale_features_with_area,
            "extractor.num_features is meant for 640x480: scale it up with the image area "
            "(capped by map.max_keypoints_per_keyframe)");
    v.field("temporal_frames", temporal_frames,
            "B: keyframes tracked in the last B frames give the temporal query Q_T",
            options::Range<int>{1, 1000});
    v.field("max_query_points", max_query_points, "map-points considered per frame",
            options::Range<int>{16, 1000000});
    v.field("query_far", query_far,
            "spatial query depth range, in multiples of the median tracked depth",
            options::Range<double>{1.0, 1000.0});
    v.field("spatial_max_age_s", spatial_max_age_s,
            "Q_S skips points whose reference keyframe is older than this, s (0: no limit); "
            "in mono such points carry the scale drift since, and a limit leaves them to loop "
            "closure",
            options::Range<double>{0.0, 1e9});
    v.field("min_inliers", min_inliers, "fewer PnP inliers marks the frame lost",
            options::Range<int>{3, 100000});
    v.field("relocalize_after_lost_frames", relocalize_after_lost_frames,
            "consecutive lost frames that are only searched again from the last pose (wide "
            "radius) before each next lost frame is also offered to the relocalizer "
            "(relocalization.*; 0: from the first lost frame)",
            options::Range<int>{0, 100000});
    v.field("new_segments", new_segments,
            "when tracking has been lost for new_segment_after_s without relocalizing, "
            "initialize a new map segment (its own world frame) instead of staying lost; the "
            "relocalizer keeps looking for the earlier segments meanwhile");
    v.field("new_segment_after_s", new_segment_after_s,
            "time since the last tracked frame after which a new map segment is started, s",
            options::Range<double>{0.0, 1e6});
    v.section("relocalization_check", relocalization_check,
              "when a relocalizer's pose is trusted (motion bound, confirmation)");
    v.field("max_segments", max_segments,
            "map segments a run may have, the first included; once reached, tracking stays "
            "lost (relocalizing) instead",
            options::Range<int>{1, int{map::kMaxSegments}});
    v.field("busy_work_us", busy_work_us,
            "extra busy-wait per frame, us (simulates a heavier tracker; 0 in normal use)",
            options::Range<int>{0, 10000000});
    v.field("rgbd_max_depth_step", rgbd_max_depth_step,
            "RGB-D: sensor depth is interpolated over the keypoint's 2x2 pixels; a relative "
            "depth step among them above this marks a depth edge and the reading is refused",
            options::Range<double>{0.0, 100.0});
  }
};

}  // namespace mer::frontend
