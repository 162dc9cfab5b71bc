#pragma once
/// @file descriptor_match.h
/// Nearest-neighbour descriptor search shared by loop closure and relocalization.

#include <cstddef>
#include <limits>

#include "features/keypoint.h"

namespace mer::loop {

/// The nearest and second-nearest of n descriptors to d (Hamming), for a ratio test.
struct NearestTwo {
  int best = std::numeric_limits<int>::max();    ///< distance of the nearest
  int second = std::numeric_limits<int>::max();  ///< distance of the second nearest
  std::size_t index = 0;                         ///< index of the nearest (0 when n == 0)

  /// True when the nearest is within max_distance and at most ratio x the second.
  bool passes(int max_distance, double ratio) const {
    return best <= max_distance && static_cast<double>(best) <= ratio * static_cast<double>(second);
  }
};

/// Brute-force search of d among desc_at(0) .. desc_at(n - 1) (first of equal distances wins).
template <class DescAt>
NearestTwo nearest_two(const features::Descriptor& d, std::size_t n, DescAt&& desc_at) {
  NearestTwo r;
  for (std::size_t k = 0; k < n; ++k) {
    const int dist = features::hamming(d, desc_at(k));
    if (dist < r.best) {
      r.second = r.best;
      r.best = dist;
      r.index = k;
    } else if (dist < r.second) {
      r.second = dist;
    }
  }
  return r;
}

}  // namespace mer::loop
