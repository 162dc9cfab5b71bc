#include "map/cell_grid.h"

#include <algorithm>
#include <cmath>
#include <limits>

namespace mer::map {
namespace {

constexpr int kCoordBits = 21;  // bits per axis field in a key
constexpr std::int64_t kCoordOffset = std::int64_t{1} << (kCoordBits - 1);
constexpr std::uint64_t kCoordMask = (std::uint64_t{1} << kCoordBits) - 1;
// A coordinate takes the low kRangeBits of its field (its offset-binary value's top
// kCoordBits - kRangeBits bits are then 011 or 100); the segment's bits, 3 per axis, are
// XOR-ed into those top bits.
constexpr int kRangeBits = 18;
constexpr int kSegmentBitsPerAxis = kCoordBits - kRangeBits;
constexpr std::uint64_t kSegmentAxisMask = (std::uint64_t{1} << kSegmentBitsPerAxis) - 1;
constexpr std::uint64_t kRangeMask = (std::uint64_t{1} << kRangeBits) - 1;
constexpr std::int64_t kCoordMin = -(std::int64_t{1} << (kRangeBits - 1));  // smallest coordinate
constexpr std::int64_t kCoordMax = (std::int64_t{1} << (kRangeBits - 1)) - 1;  // largest
static_assert(3 * kSegmentBitsPerAxis >= 8 && kMaxSegments <= 256, "segment bits in a key");

/// Longest linear-probe run a lookup or an insert follows.
constexpr std::uint32_t kMaxProbes = 64;
/// A frustum spanning more cell layers than this is answered by a table scan.
constexpr double kMaxMarchLayers = 4096.0;
/// Cost of one marched candidate cell (plane test + hash lookup, usually a cache miss)
/// relative to one entry of a table scan (sequential key read); picks the cheaper strategy.
constexpr double kScanCostRatio = 6.0;
/// Depth bands of the nearest-first second pass of a truncated frustum table scan.
constexpr int kScanBands = 8;
/// Cell boxes are inflated by this fraction of the cell size in the intersection tests so
/// that rounding in floor(p / cell_size) never drops a point on a cell face.
constexpr double kBoxMargin = 1e-6;

/// The 12 edges of a frustum (corner indices, see Frustum::corner).
constexpr int kFrustumEdges[12][2] = {{0, 1}, {1, 2}, {2, 3}, {3, 0}, {4, 5}, {5, 6},
                                      {6, 7}, {7, 4}, {0, 4}, {1, 5}, {2, 6}, {3, 7}};

/// splitmix64 finalizer: spreads neighbouring cells over the table.
std::uint64_t mix(std::uint64_t k) noexcept {
  k ^= k >> 30U;
  k *= 0xBF58476D1CE4E5B9ULL;
  k ^= k >> 27U;
  k *= 0x94D049BB133111EBULL;
  k ^= k >> 31U;
  return k;
}

/// floor(v), clamped one past the coordinate range (so the caller can detect it), as int.
std::int64_t cell_floor(double v) noexcept {
  const double f = std::floor(v);
  if (!(f >= static_cast<double>(kCoordMin))) return kCoordMin - 1;  // also NaN
  if (f > static_cast<double>(kCoordMax)) return kCoordMax + 1;
  return static_cast<std::int64_t>(f);
}

/// [lo, hi] clamped to the coordinate range; false when empty.
bool clamp_range(std::int64_t& lo, std::int64_t& hi) noexcept {
  lo = std::max(lo, kCoordMin);
  hi = std::min(hi, kCoordMax);
  return lo <= hi;
}

/// Conservative box-vs-frustum test: false only when the box is fully outside a plane.
bool box_in_frustum(const Frustum& f, const double (&l1)[6], const Eigen::Vector3d& center,
                    double half) noexcept {
  for (int i = 0; i < 6; ++i) {
    if (f.normal[i].dot(center) + f.offset[i] + half * l1[i] < 0.0) return false;
  }
  return true;
}

/// Depth band (0..kScanBands-1) of a cell centre in a frustum, by camera depth.
int band_of(const Frustum& f, const Eigen::Vector3d& center) noexcept {
  const double depth = f.view_dir.dot(center - f.center);
  const double t = (depth - f.near_z) / (f.far_z - f.near_z);
  const int b = static_cast<int>(std::floor(std::clamp(t, 0.0, 1.0) * kScanBands));
  return std::clamp(b, 0, kScanBands - 1);
}

/// Squared distance from `c` to the axis-aligned box [lo, lo + size]^3.
double box_distance_sq(const Eigen::Vector3d& c, const Eigen::Vector3d& lo, double size) noexcept {
  double d2 = 0.0;
  for (int k = 0; k < 3; ++k) {
    const double below = lo[k] - c[k];
    const double above = c[k] - (lo[k] + size);
    const double d = std::max({below, above, 0.0});
    d2 += d * d;
  }
  return d2;
}

/// Bounds, along axes b and c, of the section of the frustum between planes x_a = lo and
/// x_a = hi (hull of the corners inside the slab and the edge crossings of its planes).
bool slab_bounds(const Frustum& f, int a, int b, int c, double lo, double hi, double (&bmin)[2],
                 double (&bmax)[2]) noexcept {
  bool any = false;
  auto add = [&](const Eigen::Vector3d& p) {
    const double v[2] = {p[b], p[c]};
    for (int k = 0; k < 2; ++k) {
      bmin[k] = any ? std::min(bmin[k], v[k]) : v[k];
      bmax[k] = any ? std::max(bmax[k], v[k]) : v[k];
    }
    any = true;
  };
  for (const Eigen::Vector3d& p : f.corner) {
    if (p[a] >= lo && p[a] <= hi) add(p);
  }
  for (const auto& e : kFrustumEdges) {
    const Eigen::Vector3d& p = f.corner[e[0]];
    const Eigen::Vector3d& q = f.corner[e[1]];
    const double dp = q[a] - p[a];
    if (dp == 0.0) continue;
    for (const double s : {lo, hi}) {
      const double t = (s - p[a]) / dp;
      if (t > 0.0 && t < 1.0) add(p + t * (q - p));
    }
  }
  return any;
}

}  // namespace

// ---- Frustum -------------------------------------------------------------------------

bool Frustum::make(const SE3d& T_w_c, const geometry::Pinhole& K, int width, int height,
                   double near, double far, Frustum& out) {
  if (width <= 0 || height <= 0 || !(near > 0.0) || !(far > near) || !std::isfinite(far) ||
      !(K.fx > 0.0) || !(K.fy > 0.0) || !std::isfinite(K.cx) || !std::isfinite(K.cy) ||
      !T_w_c.matrix().allFinite()) {
    return false;
  }
  const Eigen::Matrix3d R = T_w_c.linear();
  const Eigen::Vector3d C = T_w_c.translation();
  const double w = width;
  const double h = height;
  const double us[4] = {0.0, w, w, 0.0};
  const double vs[4] = {0.0, 0.0, h, h};
  Eigen::Vector3d ray[4];
  for (int i = 0; i < 4; ++i) ray[i] = K.unproject({us[i], vs[i]});
  const Eigen::Vector3d inside = K.unproject({0.5 * w, 0.5 * h});

  Eigen::Vector3d n_c[6];
  double d_c[6];
  n_c[0] = Eigen::Vector3d::UnitZ();  // z >= near
  d_c[0] = -near;
  n_c[1] = -Eigen::Vector3d::UnitZ();  // z <= far
  d_c[1] = far;
  for (int i = 0; i < 4; ++i) {
    Eigen::Vector3d n = ray[i].cross(ray[(i + 1) % 4]).normalized();
    if (n.dot(inside) < 0.0) n = -n;
    n_c[2 + i] = n;
    d_c[2 + i] = 0.0;
  }
  for (int i = 0; i < 6; ++i) {
    out.normal[i] = R * n_c[i];
    out.offset[i] = d_c[i] - out.normal[i].dot(C);
  }
  for (int i = 0; i < 4; ++i) {
    out.corner[i] = C + R * (near * ray[i]);
    out.corner[4 + i] = C + R * (far * ray[i]);
  }
  out.view_dir = R.col(2);
  out.center = C;
  out.near_z = near;
  out.far_z = far;
  return true;
}

// ---- CellGrid ------------------------------------------------------------------------

struct CellGrid::Query {
  std::span<PointId> out;
  std::size_t n = 0;
  std::uint32_t move_seq0 = 0;
  bool full() const noexcept { return n >= out.size(); }
};

CellGrid::CellGrid(double cell_size, std::uint32_t table_size, std::uint32_t points_per_cell)
    : cell_size_(cell_size),
      inv_cell_size_(1.0 / cell_size),
      table_size_(table_size),
      mask_(table_size - 1U),
      points_per_cell_(points_per_cell),
      keys_(std::make_unique<std::atomic<CellKey>[]>(table_size)),
      headers_(std::make_unique<Header[]>(table_size)),
      ids_(std::make_unique<std::atomic<PointId>[]>(static_cast<std::size_t>(table_size) *
                                                    points_per_cell)),
      home_count_(std::make_unique<std::atomic<std::uint8_t>[]>(table_size)) {
  for (std::uint32_t e = 0; e < table_size_; ++e) {
    keys_[e].store(kNoCell, std::memory_order_relaxed);
  }
  const std::size_t n_ids = static_cast<std::size_t>(table_size) * points_per_cell;
  for (std::size_t i = 0; i < n_ids; ++i) ids_[i].store(kNoId, std::memory_order_relaxed);
}

CellKey CellGrid::key_of(std::int64_t x, std::int64_t y, std::int64_t z,
                         std::uint16_t segment) noexcept {
  if (x < kCoordMin || x > kCoordMax || y < kCoordMin || y > kCoordMax || z < kCoordMin ||
      z > kCoordMax || segment >= kMaxSegments) {
    return kNoCell;
  }
  const std::int64_t c[3] = {x, y, z};
  CellKey key = 0;
  for (int k = 0; k < 3; ++k) {
    const std::uint64_t seg_bits =
        (std::uint64_t{segment} >> (k * kSegmentBitsPerAxis)) & kSegmentAxisMask;
    const auto field = static_cast<std::uint64_t>(c[k] + kCoordOffset) ^ (seg_bits << kRangeBits);
    key |= field << (k * kCoordBits);
  }
  return key;
}

CellKey CellGrid::key_of(const Eigen::Vector3d& p_w, std::uint16_t segment) const noexcept {
  return key_of(cell_floor(p_w.x() * inv_cell_size_), cell_floor(p_w.y() * inv_cell_size_),
                cell_floor(p_w.z() * inv_cell_size_), segment);
}

CellCoord CellGrid::coord_of(CellKey key) noexcept {
  CellCoord out;
  std::int32_t c[3];
  unsigned segment = 0;
  for (int k = 0; k < 3; ++k) {
    const std::uint64_t field = (key >> (k * kCoordBits)) & kCoordMask;
    // The low kRangeBits are the coordinate modulo 2^kRangeBits (the offset is a multiple of
    // it): sign-extend them; the top bits then give the segment's bits back.
    auto v = static_cast<std::int64_t>(field & kRangeMask);
    if (v > kCoordMax) v -= std::int64_t{1} << kRangeBits;
    c[k] = static_cast<std::int32_t>(v);
    const std::uint64_t plain = static_cast<std::uint64_t>(v + kCoordOffset);
    segment |= static_cast<unsigned>(((field ^ plain) >> kRangeBits) & kSegmentAxisMask)
               << (k * kSegmentBitsPerAxis);
  }
  out.x = c[0];
  out.y = c[1];
  out.z = c[2];
  out.segment = static_cast<std::uint16_t>(segment);
  return out;
}

std::uint32_t CellGrid::home_of(CellKey key) const noexcept {
  return static_cast<std::uint32_t>(mix(key)) & mask_;
}

std::int64_t CellGrid::find(CellKey key) const noexcept {
  std::uint32_t e = home_of(key);
  if (home_count_[e].load(std::memory_order_acquire) == 0U) return -1;
  const std::uint32_t limit = std::min(kMaxProbes, table_size_);
  for (std::uint32_t probe = 0; probe < limit; ++probe) {
    const CellKey k = keys_[e].load(std::memory_order_acquire);
    if (k == key) return e;
    if (k == kNoCell) return -1;
    e = (e + 1U) & mask_;
  }
  return -1;
}

std::int64_t CellGrid::find_or_claim(CellKey key) noexcept {
  std::uint32_t e = home_of(key);
  const std::uint32_t limit = std::min(kMaxProbes, table_size_);
  std::int64_t reuse = -1;
  std::int64_t empty = -1;
  for (std::uint32_t probe = 0; probe < limit; ++probe) {
    const CellKey k = load_own(keys_[e]);
    if (k == key) return e;
    if (k == kNoCell) {
      empty = e;
      break;
    }
    if (reuse < 0 && load_own(headers_[e].count) == 0U) reuse = e;
    e = (e + 1U) & mask_;
  }
  const std::int64_t target = reuse >= 0 ? reuse : empty;
  if (target < 0) return -1;
  const auto t = static_cast<std::uint32_t>(target);
  auto bump = [this](std::uint32_t home, int delta) {
    std::atomic<std::uint8_t>& c = home_count_[home];
    c.store(static_cast<std::uint8_t>(c.load(std::memory_order_relaxed) + delta),
            std::memory_order_release);
  };
  const CellKey old = load_own(keys_[t]);
  if (old != kNoCell) bump(home_of(old), -1);
  bump(home_of(key), +1);  // before the key is visible, so lookups never skip it
  Header& h = headers_[t];
  h.seq.write_begin();
  store_payload(h.count, 0U);
  store_payload(keys_[t], key);
  h.seq.write_end();
  if (target == empty) {
    used_entries_.store(used_entries_.load(std::memory_order_relaxed) + 1U,
                        std::memory_order_relaxed);
  }
  return target;
}

void CellGrid::count_failure(std::atomic<std::uint64_t>& counter) noexcept {
  counter.store(counter.load(std::memory_order_relaxed) + 1U, std::memory_order_relaxed);
}

bool CellGrid::insert(PointId id, CellKey key) noexcept {
  if (key == kNoCell) {
    count_failure(out_of_range_);
    return false;
  }
  const std::int64_t found = find_or_claim(key);
  if (found < 0) {
    count_failure(table_full_);
    return false;
  }
  const auto e = static_cast<std::uint32_t>(found);
  Header& h = headers_[e];
  const std::uint32_t c = load_own(h.count);
  if (c >= points_per_cell_) {
    count_failure(cell_full_);
    return false;
  }
  std::atomic<PointId>* ids = &ids_[static_cast<std::size_t>(e) * points_per_cell_];
  h.seq.write_begin();
  store_payload(ids[c], id);
  store_payload(h.count, c + 1U);
  h.seq.write_end();
  return true;
}

bool CellGrid::remove(PointId id, CellKey key) noexcept {
  if (key == kNoCell) return false;
  const std::int64_t found = find(key);
  if (found < 0) return false;
  const auto e = static_cast<std::uint32_t>(found);
  Header& h = headers_[e];
  const std::uint32_t c = load_own(h.count);
  std::atomic<PointId>* ids = &ids_[static_cast<std::size_t>(e) * points_per_cell_];
  for (std::uint32_t i = 0; i < c; ++i) {
    if (load_own(ids[i]) != id) continue;
    h.seq.write_begin();
    store_payload(ids[i], load_own(ids[c - 1U]));
    store_payload(ids[c - 1U], kNoId);
    store_payload(h.count, c - 1U);
    h.seq.write_end();
    return true;
  }
  return false;
}

bool CellGrid::move(PointId id, CellKey from, CellKey to) noexcept {
  if (from == kNoCell) return insert(id, to);
  if (from == to) return true;
  const std::uint32_t m = move_seq_.load(std::memory_order_relaxed);
  move_seq_.store(m + 1U, std::memory_order_relaxed);  // ordered by the cells' release stores
  remove(id, from);
  const bool ok = insert(id, to);
  move_seq_.store(m + 2U, std::memory_order_release);
  return ok;
}

bool CellGrid::read_cell(std::uint32_t entry, CellKey key, Query& q) const noexcept {
  const std::atomic<PointId>* ids = &ids_[static_cast<std::size_t>(entry) * points_per_cell_];
  const Header& h = headers_[entry];
  std::size_t got = 0;
  const bool ok = h.seq.read([&] {
    got = 0;
    if (load_payload(keys_[entry]) != key) return;  // re-keyed: that cell was empty
    const std::size_t c = load_payload(h.count);
    const std::size_t take = std::min(c, q.out.size() - q.n);
    for (std::size_t i = 0; i < take; ++i) q.out[q.n + i] = load_payload(ids[i]);
    got = take;
  });
  if (ok) q.n += got;
  return ok;
}

bool CellGrid::lookup_and_read(CellKey key, Query& q) const noexcept {
  const std::int64_t e = find(key);
  if (e < 0) return false;
  return read_cell(static_cast<std::uint32_t>(e), key, q);
}

std::size_t CellGrid::cell_points(CellKey key, std::span<PointId> out) const noexcept {
  Query q{out};
  if (key == kNoCell || out.empty()) return 0;
  lookup_and_read(key, q);
  return q.n;
}

void CellGrid::scan_table(const Frustum* f, const Eigen::Vector3d* c_w, double radius, int band,
                          std::uint16_t segment, Query& q) const noexcept {
  double l1[6] = {};
  if (f != nullptr) {
    for (int i = 0; i < 6; ++i) l1[i] = f->normal[i].lpNorm<1>();
  }
  const double half = 0.5 * cell_size_ + kBoxMargin * cell_size_;
  const double r2 = radius * radius;
  for (std::uint32_t e = 0; e < table_size_ && !q.full(); ++e) {
    const CellKey k = keys_[e].load(std::memory_order_acquire);
    if (k == kNoCell || headers_[e].count.load(std::memory_order_relaxed) == 0U) continue;
    const CellCoord cc = coord_of(k);
    if (cc.segment != segment) continue;
    const Eigen::Vector3d lo(cc.x * cell_size_, cc.y * cell_size_, cc.z * cell_size_);
    if (f != nullptr) {
      const Eigen::Vector3d center = lo + Eigen::Vector3d::Constant(0.5 * cell_size_);
      if (!box_in_frustum(*f, l1, center, half)) continue;
      if (band >= 0 && band_of(*f, center) != band) continue;
    } else {
      const double m = kBoxMargin * cell_size_;
      if (box_distance_sq(*c_w, lo - Eigen::Vector3d::Constant(m), cell_size_ + 2.0 * m) > r2) {
        continue;
      }
    }
    read_cell(e, k, q);
  }
}

std::size_t CellGrid::finish(Query& q) const noexcept {
  const std::uint32_t m1 = move_seq_.load(std::memory_order_acquire);
  if (m1 != q.move_seq0 || (q.move_seq0 & 1U) != 0U) {
    // A move overlapped the query: the moved id may have been read in both cells.
    const auto first = q.out.begin();
    const auto last = first + static_cast<std::ptrdiff_t>(q.n);
    std::sort(first, last);
    q.n = static_cast<std::size_t>(std::unique(first, last) - first);
  }
  return q.n;
}

std::size_t CellGrid::query_frustum(const Frustum& f, std::uint16_t segment,
                                    std::span<PointId> out) const noexcept {
  Query q{out};
  q.move_seq0 = move_seq_.load(std::memory_order_acquire);
  if (out.empty()) return 0;

  // March cell layers along the world axis closest to the viewing direction, nearest layer
  // first; in each layer visit the cells of the bounding rectangle of the frustum section.
  int a = 0;
  f.view_dir.cwiseAbs().maxCoeff(&a);
  const int b = (a + 1) % 3;
  const int c = (a + 2) % 3;
  double amin = f.corner[0][a];
  double amax = amin;
  for (const Eigen::Vector3d& p : f.corner) {
    amin = std::min(amin, p[a]);
    amax = std::max(amax, p[a]);
  }
  std::int64_t la0 = cell_floor(amin * inv_cell_size_);
  std::int64_t la1 = cell_floor(amax * inv_cell_size_);
  bool scan = static_cast<double>(la1 - la0) + 1.0 > kMaxMarchLayers;
  if (!scan && !clamp_range(la0, la1)) return finish(q);

  auto layer_rect = [&](std::int64_t layer, std::int64_t(&r)[4]) {
    double bmin[2];
    double bmax[2];
    const double lo = static_cast<double>(layer) * cell_size_;
    if (!slab_bounds(f, a, b, c, lo, lo + cell_size_, bmin, bmax)) return false;
    r[0] = cell_floor(bmin[0] * inv_cell_size_);
    r[1] = cell_floor(bmax[0] * inv_cell_size_);
    r[2] = cell_floor(bmin[1] * inv_cell_size_);
    r[3] = cell_floor(bmax[1] * inv_cell_size_);
    return clamp_range(r[0], r[1]) && clamp_range(r[2], r[3]);
  };
  if (!scan) {
    double estimate = 0.0;
    std::int64_t r[4];
    for (std::int64_t layer = la0; layer <= la1; ++layer) {
      if (layer_rect(layer, r)) {
        estimate += static_cast<double>(r[1] - r[0] + 1) * static_cast<double>(r[3] - r[2] + 1);
      }
    }
    scan = estimate * kScanCostRatio > static_cast<double>(table_size_);
  }
  if (scan) {
    // One pass returns everything when it fits. When the output fills up, the pass kept an
    // arbitrary subset: redo it band by band, nearest depth band first.
    scan_table(&f, nullptr, 0.0, -1, segment, q);
    if (q.full()) {
      q.n = 0;
      for (int band = 0; band < kScanBands && !q.full(); ++band) {
        scan_table(&f, nullptr, 0.0, band, segment, q);
      }
    }
    return finish(q);
  }

  double l1[6];
  for (int i = 0; i < 6; ++i) l1[i] = f.normal[i].lpNorm<1>();
  const double half = 0.5 * cell_size_ + kBoxMargin * cell_size_;
  const bool ascending = f.view_dir[a] >= 0.0;
  const std::int64_t n_layers = la1 - la0 + 1;
  std::int64_t coord[3];
  for (std::int64_t i = 0; i < n_layers && !q.full(); ++i) {
    const std::int64_t layer = ascending ? la0 + i : la1 - i;
    std::int64_t r[4];
    if (!layer_rect(layer, r)) continue;
    coord[a] = layer;
    for (std::int64_t ib = r[0]; ib <= r[1] && !q.full(); ++ib) {
      coord[b] = ib;
      for (std::int64_t ic = r[2]; ic <= r[3] && !q.full(); ++ic) {
        coord[c] = ic;
        const Eigen::Vector3d center((static_cast<double>(coord[0]) + 0.5) * cell_size_,
                                     (static_cast<double>(coord[1]) + 0.5) * cell_size_,
                                     (static_cast<double>(coord[2]) + 0.5) * cell_size_);
        if (!box_in_frustum(f, l1, center, half)) continue;
        lookup_and_read(key_of(coord[0], coord[1], coord[2], segment), q);
      }
    }
  }
  return finish(q);
}

std::size_t CellGrid::query_radius(const Eigen::Vector3d& c_w, double radius, std::uint16_t segment,
                                   std::span<PointId> out) const noexcept {
  Query q{out};
  q.move_seq0 = move_seq_.load(std::memory_order_acquire);
  if (out.empty() || !(radius >= 0.0) || !std::isfinite(radius) || !c_w.allFinite()) return 0;
  std::int64_t lo[3];
  std::int64_t hi[3];
  double cells = 1.0;
  for (int k = 0; k < 3; ++k) {
    lo[k] = cell_floor((c_w[k] - radius) * inv_cell_size_);
    hi[k] = cell_floor((c_w[k] + radius) * inv_cell_size_);
    cells *= static_cast<double>(hi[k] - lo[k] + 1);
    if (!clamp_range(lo[k], hi[k])) return 0;
  }
  if (cells * kScanCostRatio > static_cast<double>(table_size_)) {
    scan_table(nullptr, &c_w, radius, -1, segment, q);
    return finish(q);
  }
  const double r2 = radius * radius;
  const double m = kBoxMargin * cell_size_;
  for (std::int64_t x = lo[0]; x <= hi[0] && !q.full(); ++x) {
    for (std::int64_t y = lo[1]; y <= hi[1] && !q.full(); ++y) {
      for (std::int64_t z = lo[2]; z <= hi[2] && !q.full(); ++z) {
        const Eigen::Vector3d corner(static_cast<double>(x) * cell_size_ - m,
                                     static_cast<double>(y) * cell_size_ - m,
                                     static_cast<double>(z) * cell_size_ - m);
        if (box_distance_sq(c_w, corner, cell_size_ + 2.0 * m) > r2) continue;
        lookup_and_read(key_of(x, y, z, segment), q);
      }
    }
  }
  return finish(q);
}

CellGridStats CellGrid::stats() const noexcept {
  CellGridStats s;
  s.used_entries = used_entries_.load(std::memory_order_relaxed);
  s.cell_full = cell_full_.load(std::memory_order_relaxed);
  s.table_full = table_full_.load(std::memory_order_relaxed);
  s.out_of_range = out_of_range_.load(std::memory_order_relaxed);
  return s;
}

std::uint64_t CellGrid::failures() const noexcept {
  const CellGridStats s = stats();
  return s.cell_full + s.table_full + s.out_of_range;
}

std::size_t CellGrid::memory_bytes() const noexcept {
  return static_cast<std::size_t>(table_size_) *
         (sizeof(std::atomic<CellKey>) + sizeof(Header) + sizeof(std::atomic<std::uint8_t>) +
          static_cast<std::size_t>(points_per_cell_) * sizeof(std::atomic<PointId>));
}

}  // namespace mer::map
