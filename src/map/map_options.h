#pragma once
/// @file map_options.h
/// Capacities and cell-grid geometry of the SLAM map (config section `map`).

#include "core/options.h"
#include "core/status.h"

namespace mer::map {

/// Options of the map (config section `map`). All storage is sized from these at
/// construction; nothing grows afterwards.
struct MapOptions {
  int max_keyframes = 400;
  int max_points = 150000;
  int max_keypoints_per_keyframe = 1500;
  int max_observations_per_point = 24;
  int max_covisible_per_keyframe = 64;
  double cell_size = 0.25;
  int cell_table_size = 65536;
  int points_per_cell = 48;
  double distance_scale_range = 3.5831808;

  template <class V>
  void visit(V& v) {
    v.field("max_keyframes", max_keyframes,
            "keyframe slots (preallocated; slots of culled keyframes are reused): the most "
            "keyframes alive at once",
            options::Range<int>{2, 100000});  // < 2^18: observations pack into 32 bits
    v.field("max_points", max_points,
            "map-point slots (preallocated; slots of culled points are reused): the most "
            "map points alive at once",
            options::Range<int>{1, 1 << 24});
    v.field("max_keypoints_per_keyframe", max_keypoints_per_keyframe,
            "keypoints stored per keyframe", options::Range<int>{1, 16384});  // <= 2^14
    v.field("max_observations_per_point", max_observations_per_point,
            "keyframe observations kept per map point", options::Range<int>{2, 255});
    v.field("max_covisible_per_keyframe", max_covisible_per_keyframe,
            "strongest covisibility edges kept per keyframe", options::Range<int>{1, 4096});
    v.field("cell_size", cell_size,
            "edge of a 3D spatial-hash cell, map units (the monocular map has median depth 1 "
            "at initialization)",
            options::Range<double>{1e-3, 1e3});
    v.field("cell_table_size", cell_table_size,
            "entries of the cell hash table (a power of two; occupied cells stay allocated)",
            options::Range<int>{64, 1 << 24});
    v.field("points_per_cell", points_per_cell,
            "point ids one cell holds (a full cell counts an insert failure)",
            options::Range<int>{1, 4096});
    v.field("distance_scale_range", distance_scale_range,
            "largest / smallest feature pyramid scale (scale_factor^(levels-1)); sets the "
            "scale-invariance distance range of map points",
            options::Range<double>{1.0, 1000.0});
  }
};

/// Checks every field (keys are reported as `map.<key>`) and the cross-field rules that
/// options::Range cannot express (cell_table_size a power of two). The global config
/// validation (options::validate) only checks the ranges: call this too.
Status validate(const MapOptions& opts);

/// The options the map actually uses for `opts`: each field clamped into its range and
/// cell_table_size rounded up to a power of two. Equal to `opts` when validate() passes.
MapOptions effective_options(const MapOptions& opts);

}  // namespace mer::map
