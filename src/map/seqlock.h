#pragma once
/// @file seqlock.h
/// Single-writer sequence lock whose payload lives in std::atomic words, so that readers
/// never take a lock, never see a torn value and ThreadSanitizer sees no data race.
///
/// Protocol (fence-free on purpose: GCC's -fsanitize=thread does not model
/// std::atomic_thread_fence and warns about it with -Wtsan):
///  - writer: write_begin() (sequence becomes odd, relaxed); every payload word stored with
///    memory_order_release (store_payload); write_end() (sequence even again, release);
///  - reader: s0 = sequence (acquire), must be even; every payload word loaded with
///    memory_order_acquire (load_payload); then the sequence again must still equal s0.
/// If a reader's acquire load sees a word stored in a write section, that release store
/// synchronizes with it, so the odd sequence value written before it is visible to the final
/// sequence load and the read is rejected. On x86 release/acquire accesses are plain moves;
/// on AArch64 they are stlr/ldar (ldapr), which costs far less than a lock.
///
/// Readers retry at most kSeqlockReadAttempts times and then report failure (the caller skips
/// the item), so a writer preempted inside a write section cannot stall a real-time reader.

#include <atomic>
#include <bit>
#include <cstdint>

namespace mer::map {

/// Attempts a reader makes before giving up on a consistent read.
inline constexpr int kSeqlockReadAttempts = 64;

/// Spin-wait hint between read attempts.
inline void cpu_relax() noexcept {
#if defined(__x86_64__) || defined(__i386__)
  __builtin_ia32_pause();
#elif defined(__aarch64__)
  asm volatile("yield" ::: "memory");
#endif
}

/// Stores a payload word inside a write section.
template <typename T>
inline void store_payload(std::atomic<T>& a, T v) noexcept {
  a.store(v, std::memory_order_release);
}

/// Loads a payload word inside a read section.
template <typename T>
inline T load_payload(const std::atomic<T>& a) noexcept {
  return a.load(std::memory_order_acquire);
}

/// Loads a payload word on the writer side (one writer at a time, ordered by the map's writer
/// lock, so relaxed loads see the last write: always consistent).
template <typename T>
inline T load_own(const std::atomic<T>& a) noexcept {
  return a.load(std::memory_order_relaxed);
}

/// The sequence counter. One writer at a time (writers are serialized by a lock outside this
/// class: Map::writer_lock()); any number of reader threads.
class SeqLock {
 public:
  /// Opens a write section (the current writer only).
  void write_begin() noexcept {
    seq_.store(seq_.load(std::memory_order_relaxed) + 1U, std::memory_order_relaxed);
  }
  /// Closes a write section and publishes it.
  void write_end() noexcept {
    seq_.store(seq_.load(std::memory_order_relaxed) + 1U, std::memory_order_release);
  }

  /// Runs `body` (which loads the payload with load_payload) until it ran on a consistent
  /// snapshot; false after kSeqlockReadAttempts failed attempts.
  template <typename F>
  bool read(F&& body) const noexcept {
    for (int attempt = 0; attempt < kSeqlockReadAttempts; ++attempt) {
      const std::uint32_t s0 = seq_.load(std::memory_order_acquire);
      if ((s0 & 1U) == 0U) {
        body();
        if (seq_.load(std::memory_order_relaxed) == s0) {
          return true;
        }
      }
      cpu_relax();
    }
    return false;
  }

 private:
  std::atomic<std::uint32_t> seq_{0};
};

/// Two floats in one payload word.
inline std::uint64_t pack_floats(float lo, float hi) noexcept {
  return static_cast<std::uint64_t>(std::bit_cast<std::uint32_t>(lo)) |
         (static_cast<std::uint64_t>(std::bit_cast<std::uint32_t>(hi)) << 32U);
}
/// Low float of a payload word.
inline float low_float(std::uint64_t w) noexcept {
  return std::bit_cast<float>(static_cast<std::uint32_t>(w & 0xFFFFFFFFULL));
}
/// High float of a payload word.
inline float high_float(std::uint64_t w) noexcept {
  return std::bit_cast<float>(static_cast<std::uint32_t>(w >> 32U));
}
/// A double as a payload word.
inline std::uint64_t pack_double(double d) noexcept {
  return std::bit_cast<std::uint64_t>(d);
}
/// The double of a payload word.
inline double unpack_double(std::uint64_t w) noexcept {
  return std::bit_cast<double>(w);
}

}  // namespace mer::map
