#pragma once
/// @file cell_grid.h
/// Spatial hash of map points: fixed-size open-addressing table of 3D cells keyed by integer
/// cell coordinates and map segment (each segment's world frame is its own: its cells never
/// hold another segment's points), each cell a fixed array of point ids. One writer at a time (the
/// map's writer lock) inserts, removes and moves ids; any number of readers look cells up and run
/// frustum / radius queries without locks. Nothing grows after construction: a full cell or a full
/// table is counted (failures()), never silent.
///
/// Concurrency design:
///  - Table keys are std::atomic words, stored once with release when an entry is claimed;
///    an entry is never emptied again (linear-probe chains stay intact for readers). An entry
///    whose cell became empty may be re-keyed by the writer for another cell in the same
///    probe chain, so a long exploration does not exhaust the table.
///  - Each entry has a seqlock (seqlock.h) over (key, count, ids): removal swaps the id with
///    the last one, so cells stay dense and a scan never meets holes. Readers copy a cell
///    straight into the output span and re-copy on a torn read (bounded retries; a cell that
///    stays torn is skipped).
///  - Frustum queries march cell layers along the world axis closest to the view direction,
///    nearest layer first, testing each cell of the layer's section bounds against the six
///    frustum planes before a hash lookup (a per-home-slot byte count answers most lookups of
///    empty space without touching the key array). When the frustum covers more candidate
///    cells than a table scan costs, the table is scanned once instead (work bounded by the
///    table size whatever near / far are); if that fills the output, the scan is redone by
///    depth bands, nearest first, so a truncated answer still holds the nearest cells.
///  - Moving a point (remove from one cell + insert into another) is bracketed by a grid-wide
///    move sequence. A query that overlapped a move may have seen the id in both cells; it
///    detects that from the sequence and de-duplicates its output (sort + unique, in place),
///    so results are always distinct ids.

#include <atomic>
#include <cstddef>
#include <cstdint>
#include <memory>
#include <span>

#include <Eigen/Core>

#include "core/pose.h"
#include "geometry/camera_model.h"
#include "map/map_types.h"
#include "map/seqlock.h"

namespace mer::map {

/// Integer cell coordinates and a map segment packed into 63 bits: one 21-bit field per axis
/// holding the coordinate (in [-2^17, 2^17)) in offset binary with 3 bits of the segment
/// XOR-ed into its top 3 bits (segment 0: plain offset binary).
using CellKey = std::uint64_t;
/// No cell (position out of range or not finite); also the empty table-entry marker.
inline constexpr CellKey kNoCell = ~CellKey{0};

/// Integer coordinates of a cell.
struct CellCoord {
  std::int32_t x = 0;
  std::int32_t y = 0;
  std::int32_t z = 0;
  std::uint16_t segment = 0;  ///< map segment (below kMaxSegments)
};

/// A view frustum in world coordinates: 6 inward planes n.p + d >= 0 and its 8 corners.
struct Frustum {
  Eigen::Vector3d normal[6];  ///< inward unit normals: near, far, then the 4 image sides
  double offset[6] = {};      ///< plane offsets d
  Eigen::Vector3d corner[8];  ///< near corners 0..3, far corners 4..7 (same image order)
  Eigen::Vector3d view_dir;   ///< camera z axis in the world
  Eigen::Vector3d center;     ///< camera centre in the world
  double near_z = 0.0;        ///< depth range along view_dir
  double far_z = 0.0;

  /// Frustum of a pinhole camera at T_w_c with an image of width x height px, camera-z range
  /// [near, far]. False for a degenerate input (non-positive size, focal or depth range,
  /// non-finite values).
  static bool make(const SE3d& T_w_c, const geometry::Pinhole& K, int width, int height,
                   double near, double far, Frustum& out);
};

/// Counters of the grid (failures are the inserts that could not be stored).
struct CellGridStats {
  std::uint32_t used_entries = 0;  ///< table entries that hold a key
  std::uint64_t cell_full = 0;     ///< inserts into a full cell
  std::uint64_t table_full = 0;    ///< inserts that found no table entry
  std::uint64_t out_of_range = 0;  ///< inserts of a non-finite or out-of-range position
};

/// The spatial hash (see the file comment for the threading contract).
class CellGrid {
 public:
  /// Preallocates `table_size` entries (a power of two) of `points_per_cell` ids each.
  CellGrid(double cell_size, std::uint32_t table_size, std::uint32_t points_per_cell);
  CellGrid(const CellGrid&) = delete;
  CellGrid& operator=(const CellGrid&) = delete;

  /// Cell of a world position of `segment`; kNoCell when not finite, beyond the coordinate
  /// range (+-2^17 cells per axis) or for a segment of kMaxSegments or more.
  CellKey key_of(const Eigen::Vector3d& p_w, std::uint16_t segment) const noexcept;
  /// Key of integer coordinates of `segment`; kNoCell when out of range.
  static CellKey key_of(std::int64_t x, std::int64_t y, std::int64_t z,
                        std::uint16_t segment) noexcept;
  /// Coordinates and segment of a key (key != kNoCell).
  static CellCoord coord_of(CellKey key) noexcept;

  // ---- writer (one at a time: the map's writer lock) ----
  /// Adds `id` to cell `key`. False (and counted) when key is kNoCell, the cell is full or no
  /// table entry is free within the probe limit.
  bool insert(PointId id, CellKey key) noexcept;
  /// Removes `id` from cell `key`; false when it is not there (not a failure).
  bool remove(PointId id, CellKey key) noexcept;
  /// Moves `id` from cell `from` (kNoCell: nowhere) to `to`; the insert result.
  bool move(PointId id, CellKey from, CellKey to) noexcept;

  // ---- any thread, lock-free ----
  /// Ids in cell `key` (up to out.size()); 0 when absent or not read consistently.
  std::size_t cell_points(CellKey key, std::span<PointId> out) const noexcept;
  /// Distinct ids of the points of `segment` in the cells intersecting `f` (up to out.size(),
  /// nearest cells first when truncated); the count written.
  std::size_t query_frustum(const Frustum& f, std::uint16_t segment,
                            std::span<PointId> out) const noexcept;
  /// Distinct ids of the points of `segment` in the cells intersecting the ball (c_w,
  /// radius); count written.
  std::size_t query_radius(const Eigen::Vector3d& c_w, double radius, std::uint16_t segment,
                           std::span<PointId> out) const noexcept;

  /// Counters (relaxed snapshot).
  CellGridStats stats() const noexcept;
  /// Inserts that failed, all causes.
  std::uint64_t failures() const noexcept;
  /// Edge length of a cell, map units.
  double cell_size() const noexcept { return cell_size_; }
  /// Bytes of preallocated storage.
  std::size_t memory_bytes() const noexcept;

 private:
  struct Query;  // per-call output state (cell_grid.cpp)

  std::uint32_t home_of(CellKey key) const noexcept;
  std::int64_t find(CellKey key) const noexcept;  // entry index or -1
  std::int64_t find_or_claim(CellKey key) noexcept;
  bool read_cell(std::uint32_t entry, CellKey key, Query& q) const noexcept;
  bool lookup_and_read(CellKey key, Query& q) const noexcept;
  void scan_table(const Frustum* f, const Eigen::Vector3d* c_w, double radius, int band,
                  std::uint16_t segment, Query& q) const noexcept;
  std::size_t finish(Query& q) const noexcept;
  void count_failure(std::atomic<std::uint64_t>& counter) noexcept;

  double cell_size_;
  double inv_cell_size_;
  std::uint32_t table_size_;
  std::uint32_t mask_;
  std::uint32_t points_per_cell_;

  /// Per-entry seqlock and id count, side by side (one cache line access per cell read).
  struct Header {
    SeqLock seq;
    std::atomic<std::uint32_t> count{0};
  };

  std::unique_ptr<std::atomic<CellKey>[]> keys_;  ///< table keys (kNoCell: never used)
  std::unique_ptr<Header[]> headers_;             ///< per-entry seqlock and count
  std::unique_ptr<std::atomic<PointId>[]> ids_;   ///< table_size x points_per_cell ids
  /// Number of keyed entries whose home slot is this one. A lookup of a cell whose home
  /// count is 0 stops after one byte read (most cells a frustum query visits are empty
  /// space), instead of a probe into the 8x larger key array. At most kMaxProbes keys
  /// share a home, so a byte is enough.
  std::unique_ptr<std::atomic<std::uint8_t>[]> home_count_;

  std::atomic<std::uint32_t> move_seq_{0};  ///< odd while a move is in progress
  std::atomic<std::uint32_t> used_entries_{0};
  std::atomic<std::uint64_t> cell_full_{0};
  std::atomic<std::uint64_t> table_full_{0};
  std::atomic<std::uint64_t> out_of_range_{0};
};

}  // namespace mer::map
