#include "core/timestamp.h"

#include <system_error>

#include <algorithm>
#include <charconv>
#include <cmath>

namespace mer {
namespace {

constexpr std::int64_t kNsPerS = 1'000'000'000;
constexpr double kMaxAbsSeconds = 9.2e9;  // |t| * 1e9 must fit an int64
constexpr std::int64_t kMaxWholeSeconds = 9'200'000'000;
constexpr int kFracDigits = 9;  // ns resolution

/// Exponent notation: through a double, rounded to the nearest ns.
bool parse_seconds_double(std::string_view token, std::int64_t& t_ns) {
  if (!token.empty() && token.front() == '+') token.remove_prefix(1);
  if (token.empty()) return false;
  double v = 0.0;
  const auto [ptr, ec] = std::from_chars(token.data(), token.data() + token.size(), v);
  if (ec != std::errc() || ptr != token.data() + token.size() || !std::isfinite(v) ||
      std::abs(v) >= kMaxAbsSeconds) {
    return false;
  }
  t_ns = std::llround(v * static_cast<double>(kNsPerS));
  return true;
}

}  // namespace

bool parse_seconds_ns(std::string_view token, std::int64_t& t_ns) {
  if (token.find_first_of("eE") != std::string_view::npos) {
    return parse_seconds_double(token, t_ns);
  }
  bool negative = false;
  if (!token.empty() && (token.front() == '+' || token.front() == '-')) {
    negative = token.front() == '-';
    token.remove_prefix(1);
  }
  const std::size_t dot = token.find('.');
  const std::string_view whole = token.substr(0, dot);
  const std::string_view frac =
      dot == std::string_view::npos ? std::string_view{} : token.substr(dot + 1);
  if (whole.empty() && frac.empty()) return false;
  const auto all_digits = [](std::string_view s) {
    return std::all_of(s.begin(), s.end(), [](char c) { return c >= '0' && c <= '9'; });
  };
  if (!all_digits(whole) || !all_digits(frac)) return false;
  std::int64_t secs = 0;
  for (char c : whole) {
    secs = secs * 10 + (c - '0');
    if (secs >= kMaxWholeSeconds) return false;
  }
  std::int64_t ns = 0;
  for (int i = 0; i < kFracDigits; ++i) {
    ns = ns * 10 +
         (static_cast<std::size_t>(i) < frac.size() ? frac[static_cast<std::size_t>(i)] - '0' : 0);
  }
  const std::int64_t total = secs * kNsPerS + ns;
  t_ns = negative ? -total : total;
  return true;
}

}  // namespace mer
