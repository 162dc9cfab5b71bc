#pragma once
/// @file median.h
/// The one median of the project: the element of rank n/2 (the upper median for an even
/// count), found in place with std::nth_element (the range is reordered). No allocation.

#include <algorithm>
#include <iterator>

namespace mer {

/// The element of rank n/2 of [first, last) as a double, found in place (reorders the range);
/// 0 when the range is empty.
template <class It>
double upper_median(It first, It last) {
  if (first == last) return 0.0;
  const It mid = first + (std::distance(first, last) / 2);
  std::nth_element(first, mid, last);
  return static_cast<double>(*mid);
}

/// upper_median over a whole container (reordered in place).
template <class C>
double upper_median(C& c) {
  return upper_median(std::begin(c), std::end(c));
}

}  // namespace mer
