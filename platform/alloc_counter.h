#pragma once

#include <cstdint>

/// Heap-allocation counters, for tests and the steady-state "0 allocations per frame" check.
///
/// The counting replacement of the global operator new/delete lives in the OBJECT library
/// `mer_alloc_counter` (alloc_counter.cpp), linked into every test and into mer_slam. Code
/// that links only mer_platform still links: mer_platform carries weak fallbacks returning
/// 0 / false (alloc_counter_fallback.cpp), which the replacement overrides when linked.
///
/// Counted: every call of a global operator new / new[] (all variants: sized, aligned,
/// nothrow) and delete / delete[] on a non-null pointer. Not counted: direct malloc calls
/// (C libraries, vsnprintf internals) - those are the sanitizers' and heaptrack's job.
namespace mer::platform::alloc {

/// operator new calls made by the calling thread since it started (a plain thread_local
/// counter: reading it costs nothing, and the other threads don't disturb it).
std::uint64_t thread_allocations() noexcept;

/// operator delete calls (non-null) made by the calling thread since it started.
std::uint64_t thread_deallocations() noexcept;

/// operator new calls by all threads, approximate: each thread publishes its count in
/// batches of 64 to keep atomics off the fast path, so the value may lag by up to 63 per
/// other live thread (the calling thread's own count is exact).
std::uint64_t total_allocations() noexcept;

/// True only when the counting operator new replacement is linked into this program.
bool counter_linked() noexcept;

/// Counts the calling thread's heap allocations across one unit of work (from construction).
class Scope {
 public:
  Scope() : start_(thread_allocations()) {}
  std::uint64_t delta() const { return thread_allocations() - start_; }

 private:
  std::uint64_t start_;
};

}  // namespace mer::platform::alloc
