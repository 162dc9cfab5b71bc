#pragma once
/// @file keyframe_database.h
/// Image retrieval over the map's keyframes: which keyframes look like this image?
///
/// Every descriptor gives kKeyTables keys of kKeyBits bits (fixed bit subsets, as in
/// locality-sensitive hashing). A keyframe is keyed by the distinct keys of its descriptors,
/// per table. The score of keyframe k for a query image q is
///
///     score(q, k) = sum over tables t, over keys x in keys_t(q) ∩ keys_t(k) of
///                   log(N / max(1, f_t(x)))
///
/// with N the keyed keyframes and f_t(x) the keyed keyframes with key x in table t (inverse
/// keyframe frequency: a key every keyframe has counts for nothing). Scores are accumulated
/// through an inverted index (table, key) -> keyframes, so a query costs the length of the
/// posting lists of its own keys, not a pass over every keyframe's keys.
///
/// Slots: the database mirrors the map's keyframe slots (ids are slot indices) and records
/// the generation of the occupant it keyed. refresh(kf) re-keys a slot whose occupant changed;
/// a query only returns keyframes whose keyed generation is the map's live one (a culled or
/// reused slot is never returned as the keyframe it was). A freed slot keeps its keys, and its
/// share of the key frequencies, until it is refreshed with its next occupant or remove()d
/// (that is how loop closure has always weighted keys; keep it so its results do not change).
///
/// Memory and real time: the constructor preallocates everything from the map's capacities
/// (map.max_keyframes x map.max_keypoints_per_keyframe x kKeyTables keys, 2 B each, posting
/// blocks of 13 slots in 32 B for them and for every (table, key) once, plus 1 MiB of key
/// frequencies and 1 MiB of list heads: 20.2 MiB at the default 400 x 1500, memory_bytes());
/// no method allocates afterwards. Descriptors beyond map.max_keypoints_per_keyframe in a
/// query are ignored.
///
/// Threading: one instance serves the loop closer (back-end thread) and the relocalizer
/// (depth thread, threaded mode): each holds mutex() across a refresh, a query or a score_*
/// call and its use of the span that returns (refreshing is idempotent, so either may key a
/// new keyframe first). refresh() reads keyframe descriptors through the map's lock-free
/// reader group (immutable while the slot is live), so it runs on a registered reader thread
/// or under the map's writer lock.

#include <array>
#include <cstddef>
#include <cstdint>
#include <span>
#include <vector>

#include "features/keypoint.h"
#include "map/map.h"
#include "platform/pi_mutex.h"

namespace mer::loop {

/// Retrieval keys: kKeyTables fixed subsets of kKeyBits descriptor bits each. Two views of
/// one point usually differ in 10-20 % of their bits, so a 16-bit subset is often the same,
/// while unrelated descriptors share one by chance 1 in 65536 times.
inline constexpr int kKeyTables = 4;
inline constexpr int kKeyBits = 16;

/// The keys of a descriptor, one per table.
std::array<std::uint16_t, kKeyTables> descriptor_keys(const features::Descriptor& d);

/// One retrieved keyframe.
struct RetrievalHit {
  map::KeyframeId id = map::kNoId;                  ///< keyframe slot
  map::Generation generation = map::kNoGeneration;  ///< its occupant when it was scored
  double score = 0.0;                               ///< weighted shared keys (file comment)
};

/// Keyframe database: inverted index of retrieval keys (file comment for the contract).
class KeyframeDatabase {
 public:
  /// Preallocates for map.options().max_keyframes keyframes of up to
  /// map.options().max_keypoints_per_keyframe descriptors. The map must outlive it.
  explicit KeyframeDatabase(const map::Map& map);
  KeyframeDatabase(const KeyframeDatabase&) = delete;
  KeyframeDatabase& operator=(const KeyframeDatabase&) = delete;

  /// Keys the live keyframe kf unless its current occupant is keyed already (a reused slot's
  /// former occupant is removed first). Returns true when kf is keyed (now or before), false
  /// for an id that is not live or beyond capacity (nothing changes then).
  bool refresh(map::KeyframeId kf);
  /// Same as refresh(): the name for a new keyframe.
  bool add(map::KeyframeId kf) { return refresh(kf); }
  /// refresh() of every live keyframe below map.num_keyframes(), in id order.
  void refresh_live();
  /// Drops slot kf's keys (whichever occupant they belong to) and its share of the key
  /// frequencies. No-op for a slot that is not keyed.
  void remove(map::KeyframeId kf);

  /// True when slot kf is keyed with the map's live occupant of that slot.
  bool contains(map::KeyframeId kf) const;
  /// Keyed slots (including freed slots still keyed: see the file comment).
  std::uint32_t size() const { return keyed_; }
  /// Keyframe slots it can hold (map.max_keyframes).
  std::size_t capacity() const { return slots_.size(); }
  /// Bytes of preallocated storage.
  std::size_t memory_bytes() const;
  /// The lock its users on different threads hold across each use (file comment).
  platform::PiMutex& mutex() const { return mutex_; }
  /// Distinct keys of table t of slot kf, sorted (empty when not keyed).
  std::span<const std::uint16_t> keys(map::KeyframeId kf, int t) const;
  /// Keyed keyframes with key `key` in table t.
  std::uint32_t key_frequency(int t, std::uint16_t key) const { return frequency_[index(t, key)]; }

  /// Scores of every slot against keyed slot kf's keys (kf itself included), indexed by slot,
  /// over [0, map.num_keyframes() when scored); 0 for a slot that shares nothing. Valid until
  /// the next score_* / query call. Empty when kf is not keyed.
  std::span<const double> score_keyframe(map::KeyframeId kf);
  /// Scores of every slot against an image's descriptors (as score_keyframe).
  std::span<const double> score_descriptors(std::span<const features::Descriptor> descriptors);
  /// The best-scoring live keyframes for an image, best first (ties: lower id first), score
  /// > 0 only; up to out.size() written, the count returned.
  std::size_t query(std::span<const features::Descriptor> descriptors, std::span<RetrievalHit> out);

 private:
  static constexpr std::uint32_t kNone = ~std::uint32_t{0};
  static std::size_t index(int t, std::uint16_t key) {
    return (static_cast<std::size_t>(t) << static_cast<unsigned>(kKeyBits)) | key;
  }
  struct Slot {
    map::Generation generation = map::kNoGeneration;  ///< keyed occupant (kNoGeneration: none)
    std::array<std::uint32_t, kKeyTables> count{};    ///< distinct keys per table
  };
  /// First posting entry of slot s, table t: entries are slot-major, then table-major.
  std::size_t entry(std::size_t s, int t) const {
    return (s * kKeyTables + static_cast<std::size_t>(t)) * per_table_;
  }
  /// Accumulates scores_ from the sorted distinct keys in `keys` per table.
  std::span<const double> accumulate(
      const std::array<std::span<const std::uint16_t>, kKeyTables>& keys);

  /// A run of a posting list: the keyframe slots with one (table, key). Every block of a list
  /// but its head (the newest) is full, so a list of n slots spans ceil(n / kBlockIds)
  /// contiguous runs: a query reads a few cache lines per key instead of chasing one link
  /// per slot.
  static constexpr int kBlockIds = 13;
  struct Block {
    std::uint32_t next = kNone;  ///< next block of the list (or of the free list)
    std::uint16_t count = 0;
    std::array<std::uint16_t, kBlockIds> id{};
  };
  void post(std::size_t h, std::uint16_t slot);
  void unpost(std::size_t h, std::uint16_t slot);

  const map::Map& map_;
  mutable platform::PiMutex mutex_;
  std::size_t per_table_ = 0;  ///< keys per table and slot, at most
  std::vector<Slot> slots_;
  std::vector<std::uint16_t> key_;        ///< per slot, table and position: its key
  std::vector<Block> blocks_;             ///< posting blocks (pool)
  std::uint32_t free_block_ = kNone;      ///< free list of blocks_
  std::vector<std::uint32_t> head_;       ///< per (table, key): head block, kNone if none
  std::vector<std::uint32_t> frequency_;  ///< per (table, key): keyed slots with it
  std::uint32_t keyed_ = 0;
  std::uint32_t high_water_ = 0;  ///< slots below it may be keyed
  // Query scratch.
  std::vector<std::uint16_t> query_keys_;  ///< kKeyTables x per_table_
  std::vector<double> scores_;             ///< per slot
};

}  // namespace mer::loop
