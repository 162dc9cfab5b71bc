#pragma once
/// @file doc_check.h
/// An options visitor for tests: counts an options struct's fields and checks that each has
/// a doc line and, unless it is a bool, a range.
#include <string_view>
#include <type_traits>

#include <gtest/gtest.h>

#include "core/options.h"

namespace mer::testing {

/// Counts fields and checks that each has a doc line (and a range, bools excepted).
struct DocCheck {
  int fields = 0;
  template <typename T, typename C = options::Any>
  void field(std::string_view key, T& /*value*/, std::string_view doc, const C& /*c*/ = {}) {
    ++fields;
    EXPECT_FALSE(doc.empty()) << key;
    if constexpr (!std::is_same_v<T, bool>) {
      EXPECT_TRUE((std::is_same_v<C, options::Range<T>>)) << key << " has no range";
    }
  }
  /// A nested options struct: its fields are counted too.
  template <typename S>
  void section(std::string_view key, S& sub, std::string_view doc) {
    EXPECT_FALSE(doc.empty()) << key;
    sub.visit(*this);
  }
};

}  // namespace mer::testing
