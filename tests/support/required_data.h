#pragma once
/// @file required_data.h
/// Tests that need data outside the checkout (../shared/data, the photo textures of a Debian
/// package) skip when it is absent on a developer machine, saying why; under CI (CI=true in
/// the environment) the same absence is a broken set-up and the test fails instead, so that
/// a silent skip never hides it.
#include <cstdlib>
#include <string_view>

#include <gtest/gtest.h>

namespace mer::testing {

/// Whether the environment says this is a CI run (CI=true or CI=1).
inline bool in_ci() {
  const char* ci = std::getenv("CI");
  if (ci == nullptr) return false;
  const std::string_view v(ci);
  return v == "true" || v == "1";
}

/// The outcome of a test whose required data is missing: a failure under CI, else a skip.
inline ::testing::TestPartResult::Type missing_data_outcome() {
  return in_ci() ? ::testing::TestPartResult::kFatalFailure : ::testing::TestPartResult::kSkip;
}

/// Its message's first words.
inline const char* missing_data_prefix() {
  return in_ci() ? "CI=true and required data is missing:" : "skipped, required data is missing:";
}

}  // namespace mer::testing

/// In a test body (or a void helper): when `present` is false, returns with a failure under
/// CI and a skip elsewhere; stream what is missing and how to get it:
///   MER_REQUIRE_DATA(!dir.empty()) << "../shared/data not found (set MER_SOURCE_DIR)";
#define MER_REQUIRE_DATA(present)                                                       \
  if (present) {                                                                        \
  } else                                                                                \
    return GTEST_MESSAGE_AT_(__FILE__, __LINE__, ::mer::testing::missing_data_prefix(), \
                             ::mer::testing::missing_data_outcome())
