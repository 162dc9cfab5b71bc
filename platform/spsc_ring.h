#pragma once

#include <array>
#include <atomic>
#include <cstddef>
#include <memory>
#include <new>
#include <type_traits>
#include <utility>

#include "platform/cache_line.h"

namespace mer::platform {

/// Lock-free bounded single-producer single-consumer FIFO ring (after rigtorp SPSCQueue).
///
/// - Exactly one thread may call the producer side (try_push), exactly one thread the
///   consumer side (try_pop). size_approx()/empty_approx() may be called from anywhere.
/// - Storage is inline (no heap at all); elements are constructed in place on push and
///   destroyed on pop, so move-only and non-default-constructible T are supported.
/// - All N slots are usable: indices run freely (64-bit, never wrap in practice) and are
///   masked with N-1, full means write - read == N.
/// - The write index and the read index live on separate cache lines; each side keeps a
///   cached copy of the other side's index and only re-reads the shared one when the cache
///   says full (producer) or empty (consumer), so steady-state traffic is one line per op.
/// - Memory order: the producer publishes an element with a release store of the write
///   index, the consumer hands the slot back with a release store of the read index.
template <typename T, std::size_t N>
class SpscRing {
  static_assert(N >= 2, "SpscRing: capacity must be at least 2");
  static_assert((N & (N - 1)) == 0, "SpscRing: capacity N must be a power of two");
  static_assert(std::is_nothrow_destructible_v<T>, "SpscRing: T must be nothrow destructible");

 public:
  /// Creates an empty ring. No allocation.
  SpscRing() = default;
  SpscRing(const SpscRing&) = delete;
  SpscRing& operator=(const SpscRing&) = delete;
  SpscRing(SpscRing&&) = delete;
  SpscRing& operator=(SpscRing&&) = delete;

  /// Destroys the elements still in the ring. Must not race with push or pop.
  ~SpscRing() {
    if constexpr (!std::is_trivially_destructible_v<T>) {
      std::size_t r = read_idx_.load(std::memory_order_relaxed);
      const std::size_t w = write_idx_.load(std::memory_order_relaxed);
      for (; r != w; ++r) {
        std::destroy_at(slot(r));
      }
    }
  }

  /// Producer: moves `v` into the ring. Returns false (and leaves `v` untouched) when full.
  [[nodiscard]] bool try_push(T&& v) noexcept(std::is_nothrow_move_constructible_v<T>) {
    return emplace_impl(std::move(v));
  }

  /// Producer: copies `v` into the ring. Returns false when full.
  [[nodiscard]] bool try_push(const T& v) noexcept(std::is_nothrow_copy_constructible_v<T>) {
    return emplace_impl(v);
  }

  /// Consumer: moves the oldest element into `out` and removes it. Returns false when empty
  /// (`out` untouched).
  [[nodiscard]] bool try_pop(T& out) noexcept(std::is_nothrow_move_assignable_v<T>) {
    const std::size_t r = read_idx_.load(std::memory_order_relaxed);
    if (r == write_idx_cache_) {
      write_idx_cache_ = write_idx_.load(std::memory_order_acquire);
      if (r == write_idx_cache_) {
        return false;
      }
    }
    T* p = slot(r);
    out = std::move(*p);
    std::destroy_at(p);
    read_idx_.store(r + 1, std::memory_order_release);
    return true;
  }

  /// Number of elements, exact when called by the producer or consumer with the other side
  /// idle, otherwise a snapshot that may be stale by the time it is used. In [0, N].
  [[nodiscard]] std::size_t size_approx() const noexcept {
    // Read index first: it never overtakes the write index, so w - r cannot underflow.
    const std::size_t r = read_idx_.load(std::memory_order_acquire);
    const std::size_t w = write_idx_.load(std::memory_order_acquire);
    const std::size_t n = w - r;
    return n > N ? N : n;
  }

  /// True when size_approx() == 0.
  bool empty_approx() const noexcept { return size_approx() == 0; }

  /// Maximum number of elements (= N; every slot is usable).
  static constexpr std::size_t capacity() noexcept { return N; }

 private:
  static constexpr std::size_t kMask = N - 1;
  static constexpr std::size_t kSlotAlign = alignof(T) > kCacheLine ? alignof(T) : kCacheLine;

  template <typename U>
  bool emplace_impl(U&& v) {
    const std::size_t w = write_idx_.load(std::memory_order_relaxed);
    if (w - read_idx_cache_ == N) {
      read_idx_cache_ = read_idx_.load(std::memory_order_acquire);
      if (w - read_idx_cache_ == N) {
        return false;
      }
    }
    ::new (static_cast<void*>(storage_.data() + (w & kMask) * sizeof(T))) T(std::forward<U>(v));
    write_idx_.store(w + 1, std::memory_order_release);
    return true;
  }

  T* slot(std::size_t i) noexcept {
    return std::launder(reinterpret_cast<T*>(storage_.data() + (i & kMask) * sizeof(T)));
  }

  // Producer-owned line: the shared write index, then the producer's private cache of the
  // read index on its own line (the consumer reads write_idx_ often; keep producer-private
  // writes off that line).
  alignas(kCacheLine) std::atomic<std::size_t> write_idx_{0};
  alignas(kCacheLine) std::size_t read_idx_cache_{0};
  // Consumer-owned lines.
  alignas(kCacheLine) std::atomic<std::size_t> read_idx_{0};
  alignas(kCacheLine) std::size_t write_idx_cache_{0};
  // Element storage, starting on its own line so it never shares one with an index.
  alignas(kSlotAlign) std::array<std::byte, N * sizeof(T)> storage_;
};

}  // namespace mer::platform
