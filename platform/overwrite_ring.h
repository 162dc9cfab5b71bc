#pragma once

#include <array>
#include <atomic>
#include <bit>
#include <cstddef>
#include <cstdint>
#include <cstring>
#include <optional>
#include <type_traits>

#include "platform/cache_line.h"

namespace mer::platform {

/// Lock-free drop-oldest single-producer single-consumer ring (after iceoryx spsc_sofi).
///
/// push() never fails: when the ring already holds N elements the producer evicts the
/// oldest one and hands it back to the caller (e.g. a frame-buffer slot index that must go
/// back to its pool), and dropped() counts it. Every pushed element is therefore either
/// popped exactly once or returned exactly once from push() as evicted.
///
/// How: there are N + 1 internal cells and free-running 64-bit read/write positions.
///  - push writes the cell at `w`, publishes `w + 1` (release), and if the ring now holds
///    N + 1 elements tries to CAS the read position from `r` to `r + 1`; the winner of that
///    CAS owns element `r`. If the CAS fails, the consumer popped `r` concurrently and
///    nothing is evicted.
///  - try_pop copies the cell at `r` *speculatively* and then CASes the read position from
///    `r` to `r + 1`; only on success is the copy the consumer's. If the producer evicted
///    `r` in between (and may even be overwriting that cell), the CAS fails and the copy is
///    discarded.
/// The cell written by a push is never the one a successful pop or eviction reads: with
/// N + 1 cells, the cell at `w` last held element `w - N - 1`, which was popped or evicted
/// (read position > w - N - 1) before the producer reaches `w`.
///
/// The read position is only ever modified by read-modify-write operations, so the
/// consumer's successful CAS (acq_rel) synchronizes with the producer's next acquire load of
/// it: a cell the consumer copied can't have been overwritten by a write the producer made
/// after it learned the element was consumed. Cells are stored as relaxed atomic 64-bit
/// words so the speculative copy is not a data race (TSan-clean); for a 4- or 8-byte T
/// that is a single plain load/store on x86-64 and AArch64.
template <typename T, std::size_t N>
class OverwriteRing {
  static_assert(std::is_trivially_copyable_v<T>,
                "OverwriteRing<T>: T must be trivially copyable. Eviction by the producer races "
                "with pop by the consumer, so the ring copies an element speculatively and only "
                "the winner of the CAS on the read position owns it; a losing copy is discarded "
                "without running any destructor. Pass pool slot indices (e.g. "
                "PoolHandle::release_raw()) through it, not owning handles.");
  static_assert(N >= 1, "OverwriteRing: capacity must be at least 1");

 public:
  /// Creates an empty ring. No allocation.
  OverwriteRing() = default;
  OverwriteRing(const OverwriteRing&) = delete;
  OverwriteRing& operator=(const OverwriteRing&) = delete;
  OverwriteRing(OverwriteRing&&) = delete;
  OverwriteRing& operator=(OverwriteRing&&) = delete;

  /// Producer: appends `v`. Always succeeds. Returns the evicted oldest element when the ring
  /// was full (the caller now owns it, e.g. returns its buffer to a pool), else nullopt.
  [[nodiscard]] std::optional<T> push(const T& v) noexcept {
    const std::uint64_t w = write_pos_.load(std::memory_order_relaxed);
    std::uint64_t r = read_pos_.load(std::memory_order_acquire);
    store_cell(w % kCells, v);
    write_pos_.store(w + 1, std::memory_order_release);
    if (w + 1 - r <= N) {
      return std::nullopt;  // r may be stale (smaller): then there is even more room
    }
    // Now N + 1 elements: evict element r unless the consumer takes it first.
    if (read_pos_.compare_exchange_strong(r, r + 1, std::memory_order_acq_rel,
                                          std::memory_order_acquire)) {
      dropped_.store(dropped_.load(std::memory_order_relaxed) + 1, std::memory_order_relaxed);
      return load_cell(r % kCells);
    }
    return std::nullopt;
  }

  /// Consumer: moves the oldest element into `out`. Returns false when empty.
  [[nodiscard]] bool try_pop(T& out) noexcept {
    std::uint64_t r = read_pos_.load(std::memory_order_acquire);
    for (;;) {
      if (r == write_pos_.load(std::memory_order_acquire)) {
        return false;
      }
      T copy = load_cell(r % kCells);  // speculative: ours only if the CAS below succeeds
      if (read_pos_.compare_exchange_weak(r, r + 1, std::memory_order_acq_rel,
                                          std::memory_order_acquire)) {
        out = copy;
        return true;
      }
      // r was reloaded by the failed CAS (producer evicted, or spurious failure); retry.
    }
  }

  /// Number of evictions so far (producer-written, safe to read from any thread).
  std::uint64_t dropped() const noexcept { return dropped_.load(std::memory_order_relaxed); }

  /// Snapshot of the number of elements, in [0, N].
  std::size_t size_approx() const noexcept {
    const std::uint64_t r = read_pos_.load(std::memory_order_acquire);
    const std::uint64_t w = write_pos_.load(std::memory_order_acquire);
    const std::uint64_t n = w > r ? w - r : 0;
    return n > N ? N : static_cast<std::size_t>(n);
  }

  /// Maximum number of elements held (= N; all N are usable).
  static constexpr std::size_t capacity() noexcept { return N; }

 private:
  static constexpr std::size_t kCells = N + 1;
  static constexpr std::size_t kWords =
      (sizeof(T) + sizeof(std::uint64_t) - 1) / sizeof(std::uint64_t);

  void store_cell(std::size_t i, const T& v) noexcept {
    std::array<std::uint64_t, kWords> buf{};
    std::memcpy(buf.data(), &v, sizeof(T));
    std::atomic<std::uint64_t>* cell = words_.data() + i * kWords;
    for (std::size_t k = 0; k < kWords; ++k) {
      cell[k].store(buf[k], std::memory_order_relaxed);
    }
  }

  T load_cell(std::size_t i) const noexcept {
    std::array<std::uint64_t, kWords> buf;
    const std::atomic<std::uint64_t>* cell = words_.data() + i * kWords;
    for (std::size_t k = 0; k < kWords; ++k) {
      buf[k] = cell[k].load(std::memory_order_relaxed);
    }
    std::array<std::byte, sizeof(T)> bytes;
    std::memcpy(bytes.data(), buf.data(), sizeof(T));
    return std::bit_cast<T>(bytes);  // no default constructor needed
  }

  alignas(kCacheLine) std::atomic<std::uint64_t> write_pos_{0};
  std::atomic<std::uint64_t> dropped_{0};  // producer-written, same line as write_pos_
  alignas(kCacheLine) std::atomic<std::uint64_t> read_pos_{0};
  // kCells cells of kWords words each.
  alignas(kCacheLine) std::array<std::atomic<std::uint64_t>, kCells * kWords> words_{};
};

}  // namespace mer::platform
