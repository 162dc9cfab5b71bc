#pragma once
/// @file recording_internal.h
/// Internal to the native recording format (recording.cpp, recording_io.cpp): the header
/// decoder and the chunk checks the in-memory parser and the file reader share. Not part of
/// the HAL's interface.

#include <cstddef>
#include <cstdint>
#include <optional>
#include <span>
#include <string>
#include <string_view>

#include "hal/replay/recording.h"

namespace mer::hal::recording_detail {

/// Bytes the structure check of a chunk looks at: prefix and pose.
inline constexpr std::size_t kChunkProbeSize = kChunkPrefixSize + kChunkPoseSize;

/// Decodes and validates the header at the start of `bytes` (`bytes` holds the first
/// min(file size, kMaxHeaderSize) bytes; `file_size` is the whole size).
Result<RecordingHeader> decode_header(std::span<const std::uint8_t> bytes, std::uint64_t file_size,
                                      std::string_view name, std::size_t& header_size);

/// The damage record of a chunk: its kind, where, and a message naming the file, the frame
/// and the offset, with the intact frames before it.
RecordingDamage make_damage(DamageKind kind, std::string_view name, std::uint64_t offset,
                            std::uint64_t index, const std::string& detail);

/// Checks the structure of the chunk at `offset`: `probe` holds its first
/// min(avail, kChunkProbeSize) bytes, `avail` is the number of bytes from `offset` to the end
/// of the data. Fills `info` (pose included) when the structure is intact.
std::optional<RecordingDamage> check_chunk_structure(const RecordingHeader& h,
                                                     std::span<const std::uint8_t> probe,
                                                     std::uint64_t offset, std::uint64_t avail,
                                                     std::uint64_t index, std::string_view name,
                                                     RecordedFrameInfo& info);

/// Checks the CRC of a whole chunk (`chunk` holds exactly its `length` bytes).
std::optional<RecordingDamage> check_chunk_crc(std::span<const std::uint8_t> chunk,
                                               std::uint64_t offset, std::uint64_t index,
                                               std::string_view name);

}  // namespace mer::hal::recording_detail
