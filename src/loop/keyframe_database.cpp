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
      next_(key_.size(), kNone),
      head_(static_cast<std::size_t>(kKeyTables) << static_cast<unsigned>(kKeyBits), kNone),
      frequency_(head_.size(), 0U),
      query_keys_(kKeyTables * per_table_, 0),
      scores_(slots_.size(), 0.0) {
  MER_ASSERT(key_.size() < kNone, "keyframe database: too many posting entries for 32-bit links");
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
    const std::size_t e0 = entry(kf, t);
    for (std::uint32_t i = 0; i < count; ++i) {
      const std::size_t h = index(t, k[i]);
      const auto e = static_cast<std::uint32_t>(e0 + i);
      next_[e] = head_[h];
      head_[h] = e;
      ++frequency_[h];
    }
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
    const std::size_t e0 = entry(kf, t);
    for (std::uint32_t i = 0; i < s.count[static_cast<std::size_t>(t)]; ++i) {
      const auto e = static_cast<std::uint32_t>(e0 + i);
      const std::size_t h = index(t, key_[e]);
      // Unlink e: posting lists are short (keyframes with that key), and removal is rare
      // (a slot reused), so a singly linked list walked from its head is enough.
      std::uint32_t* link = &head_[h];
      while (*link != e) {
        MER_ASSERT(*link != kNone, "keyframe database: posting entry missing from its list");
        link = &next_[*link];
      }
      *link = next_[e];
      next_[e] = kNone;
      --frequency_[h];
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
  const std::size_t per_slot = kKeyTables * per_table_;
  for (int t = 0; t < kKeyTables; ++t) {
    for (const std::uint16_t key : keys[static_cast<std::size_t>(t)]) {
      const std::size_t h = index(t, key);
      std::uint32_t e = head_[h];
      if (e == kNone) continue;
      const double w = std::log(n / std::max(1.0, static_cast<double>(frequency_[h])));
      for (; e != kNone; e = next_[e]) scores_[e / per_slot] += w;
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
