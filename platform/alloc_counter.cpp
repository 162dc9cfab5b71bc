// Counting replacement of the global operator new / delete (all C++17 variants).
//
// Built as an OBJECT library so its objects are linked unconditionally: from a static
// archive the linker would drop them (nothing references operator new *here*), silently
// leaving the default allocator in place. Allocation goes to malloc / posix_memalign and
// free, so ASan/TSan still see (and check) every heap block through their malloc hooks.
#include "platform/alloc_counter.h"

#include <atomic>
#include <cstddef>
#include <cstdint>
#include <cstdlib>
#include <new>

namespace {

// Constant-initialized POD thread_locals: no TLS init guard, safe to touch from inside
// operator new at any point of a thread's life.
thread_local std::uint64_t t_allocs = 0;
thread_local std::uint64_t t_deallocs = 0;

constexpr std::uint64_t kPublishBatch = 64;
std::atomic<std::uint64_t> g_published_allocs{0};

inline void count_alloc() noexcept {
  const std::uint64_t n = ++t_allocs;
  if ((n & (kPublishBatch - 1)) == 0) {
    g_published_allocs.fetch_add(kPublishBatch, std::memory_order_relaxed);
  }
}

inline void count_dealloc(void* p) noexcept {
  if (p != nullptr) {
    ++t_deallocs;
  }
}

void* alloc_or_null(std::size_t size) noexcept {
  return std::malloc(size != 0 ? size : 1);
}

void* aligned_alloc_or_null(std::size_t size, std::align_val_t al) noexcept {
  std::size_t align = static_cast<std::size_t>(al);
  if (align < sizeof(void*)) {
    align = sizeof(void*);  // posix_memalign's minimum
  }
  void* p = nullptr;
  if (::posix_memalign(&p, align, size != 0 ? size : 1) != 0) {
    return nullptr;
  }
  return p;
}

// Throwing new: standard loop over the new-handler.
void* alloc_throwing(std::size_t size) {
  count_alloc();
  for (;;) {
    if (void* p = alloc_or_null(size)) {
      return p;
    }
    std::new_handler handler = std::get_new_handler();
    if (handler == nullptr) {
      throw std::bad_alloc();
    }
    handler();
  }
}

void* aligned_alloc_throwing(std::size_t size, std::align_val_t al) {
  count_alloc();
  for (;;) {
    if (void* p = aligned_alloc_or_null(size, al)) {
      return p;
    }
    std::new_handler handler = std::get_new_handler();
    if (handler == nullptr) {
      throw std::bad_alloc();
    }
    handler();
  }
}

void* alloc_nothrow(std::size_t size) noexcept {
  try {
    return alloc_throwing(size);
  } catch (...) {
    return nullptr;
  }
}

void* aligned_alloc_nothrow(std::size_t size, std::align_val_t al) noexcept {
  try {
    return aligned_alloc_throwing(size, al);
  } catch (...) {
    return nullptr;
  }
}

inline void release(void* p) noexcept {
  count_dealloc(p);
  std::free(p);
}

}  // namespace

namespace mer::platform::alloc {

std::uint64_t thread_allocations() noexcept {
  return t_allocs;
}
std::uint64_t thread_deallocations() noexcept {
  return t_deallocs;
}
std::uint64_t total_allocations() noexcept {
  return g_published_allocs.load(std::memory_order_relaxed) + (t_allocs & (kPublishBatch - 1));
}
bool counter_linked() noexcept {
  return true;
}

}  // namespace mer::platform::alloc

// ---- Replaceable global allocation functions -------------------------------------------

void* operator new(std::size_t size) {
  return alloc_throwing(size);
}
void* operator new[](std::size_t size) {
  return alloc_throwing(size);
}
void* operator new(std::size_t size, const std::nothrow_t&) noexcept {
  return alloc_nothrow(size);
}
void* operator new[](std::size_t size, const std::nothrow_t&) noexcept {
  return alloc_nothrow(size);
}
void* operator new(std::size_t size, std::align_val_t al) {
  return aligned_alloc_throwing(size, al);
}
void* operator new[](std::size_t size, std::align_val_t al) {
  return aligned_alloc_throwing(size, al);
}
void* operator new(std::size_t size, std::align_val_t al, const std::nothrow_t&) noexcept {
  return aligned_alloc_nothrow(size, al);
}
void* operator new[](std::size_t size, std::align_val_t al, const std::nothrow_t&) noexcept {
  return aligned_alloc_nothrow(size, al);
}

void operator delete(void* p) noexcept {
  release(p);
}
void operator delete[](void* p) noexcept {
  release(p);
}
void operator delete(void* p, const std::nothrow_t&) noexcept {
  release(p);
}
void operator delete[](void* p, const std::nothrow_t&) noexcept {
  release(p);
}
void operator delete(void* p, std::size_t) noexcept {
  release(p);
}
void operator delete[](void* p, std::size_t) noexcept {
  release(p);
}
void operator delete(void* p, std::align_val_t) noexcept {
  release(p);
}
void operator delete[](void* p, std::align_val_t) noexcept {
  release(p);
}
void operator delete(void* p, std::size_t, std::align_val_t) noexcept {
  release(p);
}
void operator delete[](void* p, std::size_t, std::align_val_t) noexcept {
  release(p);
}
void operator delete(void* p, std::align_val_t, const std::nothrow_t&) noexcept {
  release(p);
}
void operator delete[](void* p, std::align_val_t, const std::nothrow_t&) noexcept {
  release(p);
}
