#pragma once
/// @file random.h
/// Tiny deterministic random number generator for RANSAC sampling: xoshiro256** (Blackman &
/// Vigna, 2018) seeded through splitmix64. Same seed -> same sequence on every platform; no
/// std::random_device, no allocation, 32 bytes of state.

#include <cstdint>

namespace mer::geometry {

/// xoshiro256** generator. Not cryptographic; statistically sound for sampling.
class Rng {
 public:
  /// Seeds the four state words from `seed` with splitmix64 (any seed, including 0, is fine).
  explicit Rng(std::uint64_t seed = 1) { reseed(seed); }

  /// Restarts the sequence from `seed`.
  void reseed(std::uint64_t seed) {
    std::uint64_t x = seed;
    for (auto& s : s_) s = splitmix64(x);
  }

  /// Next 64 random bits.
  std::uint64_t next() {
    const std::uint64_t result = rotl(s_[1] * kMul5, kRotResult) * kMul9;
    const std::uint64_t t = s_[1] << kShiftT;
    s_[2] ^= s_[0];
    s_[3] ^= s_[1];
    s_[1] ^= s_[2];
    s_[0] ^= s_[3];
    s_[2] ^= t;
    s_[3] = rotl(s_[3], kRotState);
    return result;
  }

  /// Uniform integer in [0, n) for 0 < n <= 2^32 (Lemire's multiply-shift on the high 32
  /// bits; bias < n / 2^32, negligible for RANSAC). Returns 0 for n == 0.
  std::uint32_t uniform_index(std::uint32_t n) {
    const std::uint64_t r = next() >> kHighHalf;
    return static_cast<std::uint32_t>((r * n) >> kHighHalf);
  }

  /// Uniform double in [0, 1) (53 random bits).
  double uniform01() { return static_cast<double>(next() >> kDoubleShift) * kDoubleUnit; }

 private:
  // splitmix64 constants (Steele, Lea & Flood 2014).
  static constexpr std::uint64_t kGolden = 0x9e3779b97f4a7c15ULL;  ///< increment
  static constexpr std::uint64_t kMixA = 0xbf58476d1ce4e5b9ULL;    ///< first mix multiplier
  static constexpr std::uint64_t kMixB = 0x94d049bb133111ebULL;    ///< second mix multiplier
  static constexpr int kMixShiftA = 30;                            ///< splitmix shifts
  static constexpr int kMixShiftB = 27;
  static constexpr int kMixShiftC = 31;
  // xoshiro256** constants.
  static constexpr std::uint64_t kMul5 = 5;  ///< scrambler multipliers
  static constexpr std::uint64_t kMul9 = 9;
  static constexpr int kRotResult = 7;              ///< scrambler rotation
  static constexpr int kShiftT = 17;                ///< state shift
  static constexpr int kRotState = 45;              ///< state rotation
  static constexpr int kHighHalf = 32;              ///< bits in half a word
  static constexpr int kDoubleShift = 11;           ///< 64 - 53 mantissa bits
  static constexpr double kDoubleUnit = 0x1.0p-53;  ///< 2^-53

  static std::uint64_t rotl(std::uint64_t x, int k) { return (x << k) | (x >> (64 - k)); }
  static std::uint64_t splitmix64(std::uint64_t& x) {
    std::uint64_t z = (x += kGolden);
    z = (z ^ (z >> kMixShiftA)) * kMixA;
    z = (z ^ (z >> kMixShiftB)) * kMixB;
    return z ^ (z >> kMixShiftC);
  }

  std::uint64_t s_[4] = {};
};

}  // namespace mer::geometry
