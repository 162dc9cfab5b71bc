#include "hal/v4l2/v4l2_util.h"

#include <sys/ioctl.h>

#include <cerrno>
#include <cstring>

namespace mer::hal {
namespace {
constexpr int kFourccBytes = 4;
constexpr int kBitsPerByte = 8;
constexpr std::uint32_t kByteMask = 0xFF;
constexpr char kFirstPrintable = 0x20;
constexpr char kLastPrintable = 0x7E;
}  // namespace

int xioctl(int fd, unsigned long request, void* arg) noexcept {
  int r = 0;
  do {
    r = ::ioctl(fd, request, arg);
  } while (r == -1 && errno == EINTR);
  return r;
}

std::string errno_text(int err) {
  std::string s = std::strerror(err);
  const char* code = ::strerrorname_np(err);
  s += " (";
  s += code != nullptr ? std::string(code) : "errno " + std::to_string(err);
  s += ")";
  return s;
}

std::string fourcc_text(std::uint32_t fourcc) {
  std::string s(kFourccBytes, '?');
  for (int i = 0; i < kFourccBytes; ++i) {
    const auto c = static_cast<char>((fourcc >> (kBitsPerByte * i)) & kByteMask);
    if (c >= kFirstPrintable && c <= kLastPrintable) s[static_cast<std::size_t>(i)] = c;
  }
  return s;
}

std::string c_string(const std::uint8_t* chars, std::size_t size) {
  return c_string(reinterpret_cast<const char*>(chars), size);
}

std::string c_string(const char* chars, std::size_t size) {
  return std::string(chars, ::strnlen(chars, size));
}

}  // namespace mer::hal
