#pragma once
/// @file assert.h
/// MER_ASSERT(cond, msg): a broken invariant (a bug, not bad input). Always on: prints the
/// condition, message and location to stderr and aborts. Bad input is reported with
/// Status, never with an assert.

#include <cstdio>
#include <cstdlib>

#define MER_ASSERT(cond, msg)                                                             \
  do {                                                                                    \
    if (!(cond)) [[unlikely]] {                                                           \
      std::fprintf(stderr, "MER_ASSERT failed: %s (%s) at %s:%d\n", #cond, msg, __FILE__, \
                   __LINE__);                                                             \
      std::abort();                                                                       \
    }                                                                                     \
  } while (false)
