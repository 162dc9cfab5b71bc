#pragma once
/// @file v4l2_util.h
/// Small helpers shared by the V4L2 backend's files (no V4L2 header needed here).

#include <cstddef>
#include <cstdint>
#include <string>

namespace mer::hal {

/// ioctl() retried on EINTR; returns ioctl's result (errno set on failure).
int xioctl(int fd, unsigned long request, void* arg) noexcept;

/// "No such device (ENODEV)": strerror plus the errno name.
std::string errno_text(int err);

/// A FourCC code as its four characters ("YUYV"); non-printable bytes as '?'.
std::string fourcc_text(std::uint32_t fourcc);

/// A fixed-size, possibly unterminated C char array (QUERYCAP strings) as a string.
std::string c_string(const std::uint8_t* chars, std::size_t size);
/// Same for char arrays (QUERY_EXT_CTRL names).
std::string c_string(const char* chars, std::size_t size);

}  // namespace mer::hal
