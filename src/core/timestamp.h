#pragma once
/// @file timestamp.h
/// Timestamps written as decimal seconds, the one parser of the project (dataset readers,
/// the evaluator, the run's own output files).

#include <cstdint>
#include <string_view>

namespace mer {

/// Seconds written in decimal ("1305031102.175304", "1.000000e-01", "-3", "+2.5") to
/// integer nanoseconds. Plain decimal notation is converted exactly (digits past the 9th
/// decimal are truncated); exponent notation goes through a double (rounded to the
/// nearest ns). Returns false for anything else, non-finite values and |t| >= 9.2e9 s.
bool parse_seconds_ns(std::string_view token, std::int64_t& t_ns);

}  // namespace mer
