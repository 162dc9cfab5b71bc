#include "platform/memory.h"

#include <string>

#include <gtest/gtest.h>

namespace mer::platform {
namespace {

TEST(Memory, LockMemoryReportsOutcome) {
  std::string error;
  const bool ok = lock_memory(&error);
  if (ok) {
    EXPECT_TRUE(error.empty());
    EXPECT_TRUE(unlock_memory(&error)) << error;
  } else {
    // Not permitted here (no CAP_IPC_LOCK / small RLIMIT_MEMLOCK): the message says why.
    EXPECT_NE(error.find("mlockall"), std::string::npos) << error;
    EXPECT_NE(error.find("errno"), std::string::npos) << error;
  }
}

TEST(Memory, NullErrorPointerIsAccepted) {
  if (lock_memory(nullptr)) {
    EXPECT_TRUE(unlock_memory(nullptr));
  } else {
    SUCCEED() << "mlockall not permitted here; the call returned false without crashing";
  }
}

}  // namespace
}  // namespace mer::platform
