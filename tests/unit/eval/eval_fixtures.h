#pragma once
// Test helpers for mer_eval: the reference trajectories directory.

#include <cstdlib>
#include <filesystem>
#include <string>

namespace mer::eval::test {

/// $MER_SOURCE_DIR/../shared/data/trajectories, or empty when it does not exist.
inline std::string trajectories_dir() {
  const char* s = std::getenv("MER_SOURCE_DIR");
  if (s == nullptr || *s == '\0') return {};
  const std::filesystem::path p =
      std::filesystem::path(s) / ".." / "shared" / "data" / "trajectories";
  std::error_code ec;
  if (!std::filesystem::is_directory(p, ec)) return {};
  return p.lexically_normal().string();
}

}  // namespace mer::eval::test
