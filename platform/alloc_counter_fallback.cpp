// Weak defaults for programs that link mer_platform without the mer_alloc_counter OBJECT
// library: nothing is counted and counter_linked() says so. alloc_counter.cpp's strong
// definitions take precedence when it is linked.
#include "platform/alloc_counter.h"

namespace mer::platform::alloc {

__attribute__((weak)) std::uint64_t thread_allocations() noexcept {
  return 0;
}
__attribute__((weak)) std::uint64_t thread_deallocations() noexcept {
  return 0;
}
__attribute__((weak)) std::uint64_t total_allocations() noexcept {
  return 0;
}
__attribute__((weak)) bool counter_linked() noexcept {
  return false;
}

}  // namespace mer::platform::alloc
