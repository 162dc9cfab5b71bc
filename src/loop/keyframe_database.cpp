#include "loop/keyframe_database.h"

#include <algorithm>
#include <cmath>

#include "core/assert.h"

namespace mer::loop {

std::array<std::uint16_t, kKeyTables> descriptor_keys(const features::Descriptor& d) {
  // Table t takes bits t, t + 4, t + 8, ... of a 64-bit word, a different word per table
  // group: spread over the descriptor, no bit used twice.
  std::array<std::uint16_t, kKeyTables> out{};
  for (int t = 0; t < kKeyTables; ++t) {
    const std::uint64_t w = d[static_cast<std::size_t>(t) % d.size()];
    std::uint16_t k = 0;
    for (int i = 0; i < kKeyBits; ++i) {
      k = static_cast<std::uint16_t>((k << 1U) | ((w >> static_cast<unsigned>(i * 4 + t)) & 1U));
    }
    out[static_cast<std::size_t>(t)] = k;
  }
  return out;
}

KeyframeDatabase::KeyframeDatabase(const map::Map& map)
    : map_(map),
      per_table_(static_cast<std::size_t>(map.options().max_keypoints_per_keyframe)),
      slots_(static_cast<std::size_t>(map.options().max_keyframes)),
      key_(slots_.size() * kKeyTables * per_table_, 0),
      head_(static_cast<std::size_t>(kKeyTables) << static_cast<unsigned>(kKeyBits), kNone),
      frequency_(head_.size(), 0U),
      query_keys_(kKeyTables * per_table_, 0),
      scores_(slots_.size(), 0.0) {
  MER_ASSERT(slots_.size() <= 0xffffU, "keyframe database: slot ids are 16-bit");
  // Every list has at most one block that is not full: entries / kBlockIds + one per key.
  const std::size_t nblocks = key_.size() / kBlockIds + std::min(key_.size(), head_.size()) + 1;
  MER_ASSERT(nblocks < kNone, "keyframe database: too many posting blocks for 32-bit links");
  blocks_.resize(nblocks);
  for (std::size_t b = 0; b < nblocks; ++b) {
    blocks_[b].next = b + 1 < nblocks ? static_cast<std::uint32_t>(b + 1) : kNone;
  }
  free_block_ = 0;
}

std::size_t KeyframeDatabase::memory_bytes() const {
  return sizeof(*this) + slots_.size() * sizeof(Slot) + key_.size() * sizeof(std::uint16_t) +
         blocks_.size() * sizeof(Block) + head_.size() * sizeof(std::uint32_t) +
         frequency_.size() * sizeof(std::uint32_t) + query_keys_.size() * sizeof(std::uint16_t) +
         scores_.size() * sizeof(double);
}

void KeyframeDatabase::post(std::size_t h, std::uint16_t slot) {
  std::uint32_t b = head_[h];
  if (b == kNone || blocks_[b].count == kBlockIds) {
    MER_ASSERT(free_block_ != kNone, "keyframe database: posting blocks exhausted");
    const std::uint32_t nb = free_block_;
    free_block_ = blocks_[nb].next;
    blocks_[nb].next = b;
    blocks_[nb].count = 0;
    head_[h] = nb;
    b = nb;
  }
  Block& blk = blocks_[b];
  blk.id[blk.count++] = slot;
  ++frequency_[h];
}

void KeyframeDatabase::unpost(std::size_t h, std::uint16_t slot) {
  // Removal is rare (a slot reused or removed): find the slot, fill its place with the head
  // block's last id (only the head block may be partly filled), free an emptied head.
  const std::uint32_t hb = head_[h];
  MER_ASSERT(hb != kNone, "keyframe database: removing from an empty posting list");
  for (std::uint32_t b = hb; b != kNone; b = blocks_[b].next) {
    Block& blk = blocks_[b];
    for (std::uint16_t i = 0; i < blk.count; ++i) {
      if (blk.id[i] != slot) continue;
      Block& head = blocks_[hb];
      blk.id[i] = head.id[--head.count];
      if (head.count == 0) {
        head_[h] = head.next;
        head.next = free_block_;
        free_block_ = hb;
      }
      --frequency_[h];
      return;
    }
  }
  MER_ASSERT(false, "keyframe database: posting entry missing from its list");
}

bool KeyframeDatabase::refresh(map::KeyframeId kf) {
  if (kf >= slots_.size()) return false;
  const map::Generation gen = map_.keyframe_generation(kf);
  if (gen == map::kNoGeneration) return false;
  Slot& s = slots_[kf];
  if (s.generation == gen) return true;
  remove(kf);  // the slot's former occupant, if any
  const auto descs = map_.keyframe_descriptors(kf);
  const std::size_t n = std::min<std::size_t>(
      {descs.size(), static_cast<std::size_t>(map_.keyframe_num_keypoints(kf)), per_table_});
  for (int t = 0; t < kKeyTables; ++t) {
    std::uint16_t* k = key_.data() + entry(kf, t);
    for (std::size_t i = 0; i < n; ++i)
      k[i] = descriptor_keys(descs[i])[static_cast<std::size_t>(t)];
    std::sort(k, k + n);
    const auto count = static_cast<std::uint32_t>(std::unique(k, k + n) - k);
    s.count[static_cast<std::size_t>(t)] = count;
    for (std::uint32_t i = 0; i < count; ++i) post(index(t, k[i]), static_cast<std::uint16_t>(kf));
  }
  s.generation = gen;
  ++keyed_;
  high_water_ = std::max(high_water_, kf + 1);
  return true;
}

void KeyframeDatabase::refresh_live() {
  const std::uint32_t n =
      std::min<std::uint32_t>(map_.num_keyframes(), static_cast<std::uint32_t>(slots_.size()));
  for (map::KeyframeId id = 0; id < n; ++id) {
    if (map_.keyframe_is_live(id)) (void)refresh(id);
  }
}

void KeyframeDatabase::remove(map::KeyframeId kf) {
  if (kf >= slots_.size()) return;
  Slot& s = slots_[kf];
  if (s.generation == map::kNoGeneration) return;
  for (int t = 0; t < kKeyTables; ++t) {
    const std::uint16_t* k = key_.data() + entry(kf, t);
    for (std::uint32_t i = 0; i < s.count[static_cast<std::size_t>(t)]; ++i) {
      unpost(index(t, k[i]), static_cast<std::uint16_t>(kf));
    }
    s.count[static_cast<std::size_t>(t)] = 0;
  }
  s.generation = map::kNoGeneration;
  --keyed_;
}

bool KeyframeDatabase::contains(map::KeyframeId kf) const {
  return kf < slots_.size() && slots_[kf].generation != map::kNoGeneration &&
         slots_[kf].generation == map_.keyframe_generation(kf);
}

std::span<const std::uint16_t> KeyframeDatabase::keys(map::KeyframeId kf, int t) const {
  if (kf >= slots_.size() || t < 0 || t >= kKeyTables) return {};
  return {key_.data() + entry(kf, t), slots_[kf].count[static_cast<std::size_t>(t)]};
}

std::span<const double> KeyframeDatabase::accumulate(
    const std::array<std::span<const std::uint16_t>, kKeyTables>& keys) {
  std::fill(scores_.begin(), scores_.begin() + high_water_, 0.0);
  // Per slot, contributions arrive table by table in ascending key order: the same sums, in
  // the same order, as a merge of the two sorted key lists (what loop closure computed
  // before the index), so the scores are bit-identical to that.
  const double n = std::max(1.0, static_cast<double>(keyed_));
  for (int t = 0; t < kKeyTables; ++t) {
    for (const std::uint16_t key : keys[static_cast<std::size_t>(t)]) {
      const std::size_t h = index(t, key);
      std::uint32_t b = head_[h];
      if (b == kNone) continue;
      const double w = std::log(n / std::max(1.0, static_cast<double>(frequency_[h])));
      for (; b != kNone; b = blocks_[b].next) {
        const Block& blk = blocks_[b];
        for (std::uint16_t i = 0; i < blk.count; ++i) scores_[blk.id[i]] += w;
      }
    }
  }
  return scores_;
}

std::span<const double> KeyframeDatabase::score_keyframe(map::KeyframeId kf) {
  if (kf >= slots_.size() || slots_[kf].generation == map::kNoGeneration) return {};
  std::array<std::span<const std::uint16_t>, kKeyTables> k;
  for (int t = 0; t < kKeyTables; ++t) k[static_cast<std::size_t>(t)] = keys(kf, t);
  return accumulate(k);
}

std::span<const double> KeyframeDatabase::score_descriptors(
    std::span<const features::Descriptor> descriptors) {
  const std::size_t n = std::min(descriptors.size(), per_table_);
  std::array<std::span<const std::uint16_t>, kKeyTables> k;
  for (int t = 0; t < kKeyTables; ++t) {
    std::uint16_t* q = query_keys_.data() + static_cast<std::size_t>(t) * per_table_;
    for (std::size_t i = 0; i < n; ++i) {
      q[i] = descriptor_keys(descriptors[i])[static_cast<std::size_t>(t)];
    }
    std::sort(q, q + n);
    k[static_cast<std::size_t>(t)] = {q, static_cast<std::size_t>(std::unique(q, q + n) - q)};
  }
  return accumulate(k);
}

std::size_t KeyframeDatabase::query(std::span<const features::Descriptor> descriptors,
                                    std::span<RetrievalHit> out) {
  if (out.empty()) return 0;
  const std::span<const double> scores = score_descriptors(descriptors);
  std::size_t m = 0;
  for (map::KeyframeId id = 0; id < high_water_; ++id) {
    const double s = scores[id];
    if (!(s > 0.0)) continue;
    const map::Generation gen = map_.keyframe_generation(id);
    if (gen == map::kNoGeneration || gen != slots_[id].generation) continue;
    // Insertion into the sorted top list (out.size() is small: max_candidates).
    if (m == out.size() && !(s > out[m - 1].score)) continue;
    std::size_t i = m < out.size() ? m++ : m - 1;
    while (i > 0 && s > out[i - 1].score) {
      out[i] = out[i - 1];
      --i;
    }
    out[i] = RetrievalHit{id, gen, s};
  }
  return m;
}

}  // namespace mer::loop
