#pragma once
/// @file plane_sweep_internal.h
/// Internal to the plane-sweep stereo (plane_sweep.cpp, plane_sweep_cost.cpp): the cost units
/// both share. Not part of the depth module's interface.

namespace mer::depth::plane_sweep_detail {

// Integer cost units per unit of the [0, 1] photometric cost (int16 volumes: with 8 SGM
// paths the sum stays below 8 x (kCostUnits + P2) = 16000 < 32767).
inline constexpr float kCostUnits = 1000.0F;
// A source cost meaning "this source does not see the window centre" (above any real cost).
inline constexpr float kNoCost = 2.0F;

}  // namespace mer::depth::plane_sweep_detail
