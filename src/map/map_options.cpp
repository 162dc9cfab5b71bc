#include "map/map_options.h"

#include <bit>
#include <cstdint>
#include <string>
#include <type_traits>

namespace mer::map {
namespace {

/// Visitor that moves every ranged field into its range (NaN becomes the lower bound) and an
/// enum field without a name to the first one.
struct Clamper {
  template <typename T, typename C = options::Any>
  void field(std::string_view /*key*/, T& value, std::string_view /*doc*/, const C& c = {}) {
    if constexpr (std::is_same_v<C, options::Range<T>>) {
      if (!(value >= c.lo)) value = c.lo;
      if (value > c.hi) value = c.hi;
    } else if constexpr (std::is_same_v<C, options::Names<T>>) {
      if (!options::satisfies(value, c)) value = static_cast<T>(0);
    }
  }
};

}  // namespace

Status validate(const MapOptions& opts) {
  MapOptions copy = opts;
  options::Validator v("map.");
  copy.visit(v);
  if (!v.status().is_ok()) return v.status();
  const auto table = static_cast<std::uint32_t>(opts.cell_table_size);
  if (!std::has_single_bit(table)) {
    return invalid_argument("key 'map.cell_table_size': expected a power of two, found " +
                            std::to_string(opts.cell_table_size));
  }
  return Status::ok();
}

MapOptions effective_options(const MapOptions& opts) {
  MapOptions out = opts;
  Clamper c;
  out.visit(c);
  out.cell_table_size =
      static_cast<int>(std::bit_ceil(static_cast<std::uint32_t>(out.cell_table_size)));
  return out;
}

}  // namespace mer::map
