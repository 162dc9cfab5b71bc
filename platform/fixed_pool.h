#pragma once

#include <atomic>
#include <cassert>
#include <concepts>
#include <cstddef>
#include <cstdint>
#include <memory>
#include <stdexcept>
#include <utility>

#include "platform/cache_line.h"

namespace mer::platform {

/// Index value meaning "no slot" (an empty handle's index(), release_raw() of an empty handle).
inline constexpr std::uint32_t kInvalidPoolIndex = 0xFFFF'FFFFu;

template <typename T>
class FixedPool;

/// Move-only owning handle to one slot of a FixedPool (instead of shared_ptr: no control
/// block, no refcount, no allocation). The slot goes back to the pool when the handle is
/// destroyed, reset(), or assigned over. An empty handle (default-constructed, moved-from,
/// or returned by an exhausted pool) is falsy. The pool must outlive its handles.
template <typename T>
class PoolHandle {
 public:
  /// Empty handle.
  PoolHandle() noexcept = default;
  PoolHandle(const PoolHandle&) = delete;
  PoolHandle& operator=(const PoolHandle&) = delete;

  /// Takes over `other`'s slot; `other` becomes empty.
  PoolHandle(PoolHandle&& other) noexcept
      : pool_(std::exchange(other.pool_, nullptr)),
        ptr_(std::exchange(other.ptr_, nullptr)),
        index_(std::exchange(other.index_, kInvalidPoolIndex)) {}

  /// Releases the current slot (if any) and takes over `other`'s.
  PoolHandle& operator=(PoolHandle&& other) noexcept {
    if (this != &other) {
      reset();
      pool_ = std::exchange(other.pool_, nullptr);
      ptr_ = std::exchange(other.ptr_, nullptr);
      index_ = std::exchange(other.index_, kInvalidPoolIndex);
    }
    return *this;
  }

  /// Returns the slot to the pool.
  ~PoolHandle() { reset(); }

  /// Returns the slot to the pool now; the handle becomes empty. No-op when empty.
  void reset() noexcept {
    if (pool_ != nullptr) {
      pool_->release(index_);
      pool_ = nullptr;
      ptr_ = nullptr;
      index_ = kInvalidPoolIndex;
    }
  }

  /// Gives up ownership without returning the slot and returns its index (for passing the
  /// slot through an OverwriteRing<std::uint32_t>); FixedPool::adopt() turns it back into a
  /// handle. Returns kInvalidPoolIndex for an empty handle.
  [[nodiscard]] std::uint32_t release_raw() noexcept {
    if (pool_ == nullptr) {
      return kInvalidPoolIndex;
    }
    pool_->mark_raw(index_);
    pool_ = nullptr;
    ptr_ = nullptr;
    return std::exchange(index_, kInvalidPoolIndex);
  }

  /// The slot's object, or nullptr when empty.
  T* get() const noexcept { return ptr_; }
  /// The slot's object. Precondition: not empty.
  T& operator*() const noexcept {
    assert(ptr_ != nullptr && "PoolHandle: dereferencing an empty handle");
    return *ptr_;
  }
  /// Member access on the slot's object. Precondition: not empty.
  T* operator->() const noexcept {
    assert(ptr_ != nullptr && "PoolHandle: dereferencing an empty handle");
    return ptr_;
  }
  /// True when the handle owns a slot.
  explicit operator bool() const noexcept { return ptr_ != nullptr; }
  /// Slot index in [0, pool capacity), or kInvalidPoolIndex when empty.
  std::uint32_t index() const noexcept { return index_; }

 private:
  friend class FixedPool<T>;
  PoolHandle(FixedPool<T>* pool, T* ptr, std::uint32_t index) noexcept
      : pool_(pool), ptr_(ptr), index_(index) {}

  FixedPool<T>* pool_ = nullptr;
  T* ptr_ = nullptr;
  std::uint32_t index_ = kInvalidPoolIndex;
};

/// Fixed-capacity pool of preallocated T slots handed out as PoolHandle<T>.
///
/// - All memory is allocated in the constructor; acquire/release never allocate.
/// - Lock-free and thread-safe: any number of threads may acquire, and handles may be
///   released on any thread. The free list is a Treiber stack of slot indices whose 64-bit
///   head packs {32-bit ABA tag, 32-bit index}; every head change bumps the tag, so a stale
///   head can't be CASed back in. LIFO reuse keeps recently used buffers cache-warm.
/// - Exhaustion is not an error: acquire() returns an empty handle and counts it.
/// - Each slot has a small ownership state (free / owned by a handle / released raw) that
///   catches double release and adopting a slot that isn't released raw: debug builds
///   assert, release builds refuse the operation and count it in misuse_count() instead of
///   corrupting the free list.
/// - A released slot keeps its object as is (no destruction / reconstruction): e.g. a frame
///   slot keeps its image buffer for the next frame.
template <typename T>
class FixedPool {
 public:
  /// Creates `capacity` default-constructed slots. Throws std::length_error when capacity
  /// does not fit the 32-bit index (init-time misconfiguration).
  explicit FixedPool(std::size_t capacity) : FixedPool(capacity, [](T&, std::size_t) {}) {}

  /// Creates `capacity` default-constructed slots and calls `init_slot(slot, index)` on each
  /// (e.g. to allocate a frame's image buffer once, here rather than on the hot path).
  template <class F>
  requires std::invocable<F&, T&, std::size_t> FixedPool(std::size_t capacity, F&& init_slot)
      : capacity_(checked_capacity(capacity)),
        slots_(std::make_unique<T[]>(capacity)),
        meta_(std::make_unique<Meta[]>(capacity)) {
    for (std::size_t i = 0; i < capacity_; ++i) {
      init_slot(slots_[i], i);
      meta_[i].next.store(i + 1 < capacity_ ? static_cast<std::uint32_t>(i + 1) : kNil,
                          std::memory_order_relaxed);
    }
    head_.store(pack(0, capacity_ > 0 ? 0u : kNil), std::memory_order_release);
    available_.store(static_cast<std::int64_t>(capacity_), std::memory_order_relaxed);
  }

  FixedPool(const FixedPool&) = delete;
  FixedPool& operator=(const FixedPool&) = delete;
  FixedPool(FixedPool&&) = delete;
  FixedPool& operator=(FixedPool&&) = delete;

  /// Takes a free slot. Returns an empty handle (and counts it in exhausted_count()) when
  /// none is free. Lock-free, no allocation.
  [[nodiscard]] PoolHandle<T> acquire() noexcept {
    std::uint64_t head = head_.load(std::memory_order_acquire);
    for (;;) {
      const std::uint32_t idx = index_of(head);
      if (idx == kNil) {
        exhausted_.fetch_add(1, std::memory_order_relaxed);
        return {};
      }
      // May read a stale `next` if idx was taken meanwhile; the tag makes that CAS fail.
      const std::uint32_t next = meta_[idx].next.load(std::memory_order_relaxed);
      if (head_.compare_exchange_weak(head, pack(tag_of(head) + 1, next), std::memory_order_acquire,
                                      std::memory_order_acquire)) {
        break;
      }
    }
    const std::uint32_t idx = index_of(head);
    available_.fetch_sub(1, std::memory_order_relaxed);
    [[maybe_unused]] const std::uint8_t prev =
        meta_[idx].state.exchange(kOwned, std::memory_order_relaxed);
    assert(prev == kFree && "FixedPool: free list handed out a slot that is not free");
    return PoolHandle<T>(this, &slots_[idx], idx);
  }

  /// Re-wraps an index obtained from PoolHandle::release_raw() into an owning handle.
  /// Returns an empty handle (debug: asserts; counted in misuse_count()) when the index is
  /// out of range or the slot is not currently released raw (e.g. adopted twice).
  [[nodiscard]] PoolHandle<T> adopt(std::uint32_t index) noexcept {
    std::uint8_t expected = kRaw;
    if (index >= capacity_ ||
        !meta_[index].state.compare_exchange_strong(expected, kOwned, std::memory_order_acq_rel)) {
      misuse_.fetch_add(1, std::memory_order_relaxed);
      assert(false && "FixedPool::adopt: index out of range or slot not released raw");
      return {};
    }
    return PoolHandle<T>(this, &slots_[index], index);
  }

  /// Direct access to slot `index` (e.g. a consumer peeking at a raw index). No ownership
  /// check. Precondition: index < capacity().
  T& slot(std::uint32_t index) noexcept {
    assert(index < capacity_ && "FixedPool::slot: index out of range");
    return slots_[index];
  }
  /// Const access to slot `index`. Precondition: index < capacity().
  const T& slot(std::uint32_t index) const noexcept {
    assert(index < capacity_ && "FixedPool::slot: index out of range");
    return slots_[index];
  }

  /// Number of slots.
  std::size_t capacity() const noexcept { return capacity_; }

  /// Snapshot of the number of free slots (exact when no acquire/release is in flight).
  std::size_t available_approx() const noexcept {
    const std::int64_t n = available_.load(std::memory_order_relaxed);
    return n < 0 ? 0 : static_cast<std::size_t>(n);
  }

  /// Number of acquire() calls that found the pool empty.
  std::uint64_t exhausted_count() const noexcept {
    return exhausted_.load(std::memory_order_relaxed);
  }

  /// Number of refused double releases / invalid adopts (always 0 in a correct program).
  std::uint64_t misuse_count() const noexcept { return misuse_.load(std::memory_order_relaxed); }

 private:
  friend class PoolHandle<T>;

  static constexpr std::uint32_t kNil = 0xFFFF'FFFFu;
  static constexpr std::uint8_t kFree = 0;
  static constexpr std::uint8_t kOwned = 1;
  static constexpr std::uint8_t kRaw = 2;

  /// Per-slot free-list link and ownership state.
  struct Meta {
    std::atomic<std::uint32_t> next{kNil};
    std::atomic<std::uint8_t> state{kFree};
  };

  static std::size_t checked_capacity(std::size_t capacity) {
    if (capacity >= kNil) {
      throw std::length_error("FixedPool: capacity must be < 2^32 - 1");
    }
    return capacity;
  }
  static constexpr std::uint64_t pack(std::uint32_t tag, std::uint32_t index) noexcept {
    return (static_cast<std::uint64_t>(tag) << 32) | index;
  }
  static constexpr std::uint32_t index_of(std::uint64_t head) noexcept {
    return static_cast<std::uint32_t>(head);
  }
  static constexpr std::uint32_t tag_of(std::uint64_t head) noexcept {
    return static_cast<std::uint32_t>(head >> 32);
  }

  // Called by PoolHandle::reset(): owned -> free, then push on the free list.
  void release(std::uint32_t index) noexcept {
    std::uint8_t expected = kOwned;
    if (!meta_[index].state.compare_exchange_strong(expected, kFree, std::memory_order_relaxed)) {
      misuse_.fetch_add(1, std::memory_order_relaxed);
      assert(false && "FixedPool: double release of a slot");
      return;
    }
    std::uint64_t head = head_.load(std::memory_order_relaxed);
    for (;;) {
      meta_[index].next.store(index_of(head), std::memory_order_relaxed);
      // Release: the slot's contents and `next` are visible to the next acquirer.
      if (head_.compare_exchange_weak(head, pack(tag_of(head) + 1, index),
                                      std::memory_order_release, std::memory_order_relaxed)) {
        break;
      }
    }
    available_.fetch_add(1, std::memory_order_relaxed);
  }

  // Called by PoolHandle::release_raw(): owned -> raw (still not on the free list).
  void mark_raw(std::uint32_t index) noexcept {
    std::uint8_t expected = kOwned;
    [[maybe_unused]] const bool ok =
        meta_[index].state.compare_exchange_strong(expected, kRaw, std::memory_order_acq_rel);
    assert(ok && "FixedPool: release_raw of a slot that is not owned");
  }

  std::size_t capacity_;
  std::unique_ptr<T[]> slots_;
  std::unique_ptr<Meta[]> meta_;
  alignas(kCacheLine) std::atomic<std::uint64_t> head_{0};
  std::atomic<std::int64_t> available_{0};
  alignas(kCacheLine) std::atomic<std::uint64_t> exhausted_{0};
  std::atomic<std::uint64_t> misuse_{0};
};

}  // namespace mer::platform
