#pragma once
// Reporting shared by the in-VM hardware test programs: one `MER_HW_CHECK PASS|FAIL name:
// detail` line per check (parsed by tools/hw/vm_common.sh), and a failure count for the
// exit code.

#include <cstdio>
#include <string>

#include "platform/log_ring.h"

namespace mer::hw {

/// Checks that failed so far.
inline int& failures() {
  static int n = 0;
  return n;
}

/// Prints one check result (and any pending log lines) and counts failures.
inline void report(bool ok, const std::string& name, const std::string& detail) {
  std::printf("MER_HW_CHECK %s %s: %s\n", ok ? "PASS" : "FAIL", name.c_str(), detail.c_str());
  std::fflush(stdout);
  platform::flush_default_log_to_stderr(platform::LogLevel::kInfo);
  if (!ok) ++failures();
}

/// True when `s` contains `part`.
inline bool contains(const std::string& s, const std::string& part) {
  return s.find(part) != std::string::npos;
}

/// printf-formats one number.
inline std::string fmt(const char* f, double v) {
  char buf[64];
  std::snprintf(buf, sizeof buf, f, v);
  return buf;
}

}  // namespace mer::hw
