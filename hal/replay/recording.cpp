#include "hal/replay/recording.h"

#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <bit>
#include <cerrno>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <limits>
#include <utility>

#include "hal/replay/recording_internal.h"
#include "platform/clock.h"

namespace mer::hal {
namespace {

// ---- CRC32 (IEEE 802.3, reflected) ---------------------------------------------------------

constexpr std::uint32_t kCrcPolynomial = 0xEDB88320U;  // 0x04C11DB7 bit-reversed
constexpr std::uint32_t kCrcInit = 0xFFFFFFFFU;
constexpr std::size_t kCrcTableSize = 256;
constexpr double kMaxQuaternionNormError = 1e-2;  // stored quaternions are unit length
constexpr unsigned kBitsPerByte = 8;
constexpr std::uint32_t kByteMask = 0xFFU;

constexpr std::array<std::uint32_t, kCrcTableSize> make_crc_table() {
  std::array<std::uint32_t, kCrcTableSize> table{};
  for (std::uint32_t i = 0; i < kCrcTableSize; ++i) {
    std::uint32_t c = i;
    for (unsigned k = 0; k < kBitsPerByte; ++k)
      c = (c & 1U) != 0U ? kCrcPolynomial ^ (c >> 1U) : c >> 1U;
    table[i] = c;
  }
  return table;
}
constexpr std::array<std::uint32_t, kCrcTableSize> kCrcTable = make_crc_table();

// ---- Header and chunk field offsets (see the tables in recording.h) --------------------------

constexpr std::size_t kOffVersion = 8;
constexpr std::size_t kOffHeaderLength = 12;
constexpr std::size_t kOffFlags = 16;
constexpr std::size_t kOffPixelFormat = 20;
constexpr std::size_t kOffWidth = 24;
constexpr std::size_t kOffHeight = 28;
constexpr std::size_t kOffFps = 32;
constexpr std::size_t kOffCalibration = 40;
constexpr std::size_t kCalibrationDoubles = 8;  // fx fy cx cy k1 k2 p1 p2
constexpr std::size_t kOffDescriptionLength = 104;
static_assert(kOffCalibration + kCalibrationDoubles * sizeof(double) == kOffDescriptionLength);
static_assert(kOffDescriptionLength + sizeof(std::uint32_t) == kHeaderFixedSize);

constexpr std::size_t kOffChunkLength = 4;
constexpr std::size_t kOffChunkSeq = 8;
constexpr std::size_t kOffChunkTime = 16;
constexpr std::size_t kOffChunkFlags = 24;
constexpr std::size_t kOffChunkPayloadLength = 28;
static_assert(kOffChunkPayloadLength + sizeof(std::uint32_t) == kChunkPrefixSize);
constexpr std::size_t kMagicBytes = sizeof(std::uint32_t);

constexpr double kMaxNominalFps = 1e6;
constexpr std::size_t kDepthBytesPerPixel = sizeof(float);

// ---- Little-endian encoding ----------------------------------------------------------------

void put_u32(std::uint8_t* p, std::uint32_t v) {
  for (unsigned i = 0; i < sizeof(v); ++i)
    p[i] = static_cast<std::uint8_t>((v >> (kBitsPerByte * i)) & kByteMask);
}
void put_u64(std::uint8_t* p, std::uint64_t v) {
  for (unsigned i = 0; i < sizeof(v); ++i)
    p[i] = static_cast<std::uint8_t>((v >> (kBitsPerByte * i)) & kByteMask);
}
void put_f64(std::uint8_t* p, double v) {
  put_u64(p, std::bit_cast<std::uint64_t>(v));
}

std::uint32_t get_u32(const std::uint8_t* p) {
  std::uint32_t v = 0;
  for (unsigned i = 0; i < sizeof(v); ++i)
    v |= static_cast<std::uint32_t>(p[i]) << (kBitsPerByte * i);
  return v;
}
std::uint64_t get_u64(const std::uint8_t* p) {
  std::uint64_t v = 0;
  for (unsigned i = 0; i < sizeof(v); ++i)
    v |= static_cast<std::uint64_t>(p[i]) << (kBitsPerByte * i);
  return v;
}
double get_f64(const std::uint8_t* p) {
  return std::bit_cast<double>(get_u64(p));
}

std::string hex32(std::uint32_t v) {
  char buf[16];
  std::snprintf(buf, sizeof(buf), "0x%08X", v);
  return buf;
}

std::string hex_bytes(std::span<const std::uint8_t> bytes) {
  std::string s;
  for (std::size_t i = 0; i < bytes.size(); ++i) {
    char buf[4];
    std::snprintf(buf, sizeof(buf), "%s%02X", i == 0 ? "" : " ", bytes[i]);
    s += buf;
  }
  return s;
}

std::string_view pixel_format_name(std::uint32_t code) {
  switch (static_cast<RecPixelFormat>(code)) {
    case RecPixelFormat::kGrey8:
      return "GREY8";
    case RecPixelFormat::kYuyv:
      return "YUYV";
    case RecPixelFormat::kNv12:
      return "NV12";
  }
  return "unknown";
}

// ---- Header decoding -----------------------------------------------------------------------

Status header_error(std::string_view name, std::uint64_t offset, const std::string& what) {
  return input_error(std::string(name) + ": invalid recording header at byte offset " +
                     std::to_string(offset) + ": " + what);
}

Status truncated_header(std::string_view name, std::uint64_t size, std::uint64_t needed) {
  return header_error(name, size,
                      "file ends after " + std::to_string(size) + " bytes, inside the header (" +
                          std::to_string(needed) + " bytes needed)");
}

}  // namespace

namespace recording_detail {

// Decodes and validates the header at the start of `bytes` (`bytes` holds the first
// min(file size, kMaxHeaderSize) bytes; `file_size` is the whole size).
Result<RecordingHeader> decode_header(std::span<const std::uint8_t> bytes, std::uint64_t file_size,
                                      std::string_view name, std::size_t& header_size) {
  if (file_size == 0) {
    return header_error(name, 0,
                        "empty file (0 bytes), expected a recording starting with \"MERREC\"");
  }
  const std::size_t magic_n = std::min(bytes.size(), kRecordingMagic.size());
  if (!std::equal(bytes.begin(), bytes.begin() + static_cast<std::ptrdiff_t>(magic_n),
                  kRecordingMagic.begin())) {
    return header_error(name, 0,
                        "not a mer recording: bad magic (found " + hex_bytes(bytes.first(magic_n)) +
                            ", expected " + hex_bytes(kRecordingMagic) + " = \"MERREC\\0\\0\")");
  }
  if (bytes.size() < kOffVersion + sizeof(std::uint32_t)) {
    return truncated_header(name, bytes.size(), kHeaderOverhead);
  }
  const std::uint32_t version = get_u32(bytes.data() + kOffVersion);
  if (version > kRecordingVersion) {
    return header_error(name, kOffVersion,
                        "format version " + std::to_string(version) +
                            " is newer than this reader supports (version " +
                            std::to_string(kRecordingVersion) + "); use a newer mer-slam");
  }
  if (version != kRecordingVersion) {
    return header_error(name, kOffVersion,
                        "unsupported format version " + std::to_string(version) + " (expected " +
                            std::to_string(kRecordingVersion) + ")");
  }
  if (bytes.size() < kHeaderFixedSize) return truncated_header(name, bytes.size(), kHeaderOverhead);
  const std::uint32_t header_length = get_u32(bytes.data() + kOffHeaderLength);
  const std::uint32_t description_length = get_u32(bytes.data() + kOffDescriptionLength);
  if (description_length > kMaxDescriptionLength) {
    return header_error(name, kOffDescriptionLength,
                        "description length " + std::to_string(description_length) +
                            " exceeds the maximum " + std::to_string(kMaxDescriptionLength));
  }
  const std::size_t expected_length = kHeaderOverhead + description_length;
  if (header_length != expected_length) {
    return header_error(name, kOffHeaderLength,
                        "header length " + std::to_string(header_length) +
                            " does not match the description length (" +
                            std::to_string(description_length) + " -> expected " +
                            std::to_string(expected_length) + ")");
  }
  if (bytes.size() < expected_length) return truncated_header(name, bytes.size(), expected_length);
  const std::size_t crc_offset = expected_length - kChunkCrcSize;
  const std::uint32_t stored_crc = get_u32(bytes.data() + crc_offset);
  const std::uint32_t crc = crc32(bytes.first(crc_offset));
  if (stored_crc != crc) {
    return header_error(
        name, crc_offset,
        "header CRC mismatch (stored " + hex32(stored_crc) + ", computed " + hex32(crc) + ")");
  }

  // The CRC matches: the fields are as written; check they are ones this reader supports.
  const std::uint32_t flags = get_u32(bytes.data() + kOffFlags);
  if ((flags & ~kHeaderFlagsKnown) != 0U) {
    return header_error(name, kOffFlags, "unknown header flags " + hex32(flags));
  }
  const std::uint32_t format = get_u32(bytes.data() + kOffPixelFormat);
  if (format != static_cast<std::uint32_t>(RecPixelFormat::kGrey8)) {
    return header_error(name, kOffPixelFormat,
                        "pixel format " + std::to_string(format) + " (" +
                            std::string(pixel_format_name(format)) +
                            ") is not supported by this reader (supported: 1 = GREY8)");
  }
  const std::uint32_t width = get_u32(bytes.data() + kOffWidth);
  const std::uint32_t height = get_u32(bytes.data() + kOffHeight);
  if (width == 0 || height == 0 || width > kMaxImageDimension || height > kMaxImageDimension) {
    return header_error(name, kOffWidth,
                        "image size " + std::to_string(width) + "x" + std::to_string(height) +
                            " out of range [1, " + std::to_string(kMaxImageDimension) + "]");
  }
  RecordingHeader h;
  h.version = version;
  h.pixel_format = RecPixelFormat::kGrey8;
  h.has_depth = (flags & kHeaderFlagHasDepth) != 0U;
  h.has_ground_truth = (flags & kHeaderFlagHasGroundTruth) != 0U;
  h.nominal_fps = get_f64(bytes.data() + kOffFps);
  if (!std::isfinite(h.nominal_fps) || h.nominal_fps < 0.0 || h.nominal_fps > kMaxNominalFps) {
    return header_error(
        name, kOffFps,
        "nominal fps " + std::to_string(h.nominal_fps) + " is not a number in [0, 1e6]");
  }
  std::array<double, kCalibrationDoubles> calib{};
  for (std::size_t i = 0; i < kCalibrationDoubles; ++i) {
    calib[i] = get_f64(bytes.data() + kOffCalibration + i * sizeof(double));
    if (!std::isfinite(calib[i])) {
      return header_error(name, kOffCalibration + i * sizeof(double),
                          "calibration value " + std::to_string(i) + " is not finite");
    }
  }
  CameraIntrinsics& k = h.intrinsics;
  k.width = static_cast<int>(width);
  k.height = static_cast<int>(height);
  k.fx = calib[0];
  k.fy = calib[1];
  k.cx = calib[2];
  k.cy = calib[3];
  k.dist = {calib[4], calib[5], calib[6], calib[7]};
  k.focal_known = (flags & kHeaderFlagFocalKnown) != 0U;
  h.description.assign(reinterpret_cast<const char*>(bytes.data() + kHeaderFixedSize),
                       description_length);
  header_size = expected_length;
  return h;
}

// ---- Chunk checks (shared by the file reader and the in-memory parser) -----------------------

RecordingDamage make_damage(DamageKind kind, std::string_view name, std::uint64_t offset,
                            std::uint64_t index, const std::string& detail) {
  RecordingDamage d;
  d.kind = kind;
  d.offset = offset;
  d.frame_index = index;
  d.message = std::string(name) + ": recording damaged at frame " + std::to_string(index) +
              " (byte offset " + std::to_string(offset) +
              "): " + std::string(damage_kind_name(kind)) + ": " + detail + "; the " +
              std::to_string(index) + " frame(s) before it are intact";
  return d;
}

// Checks the structure of the chunk at `offset`: `probe` holds its first
// min(avail, kChunkProbeSize) bytes, `avail` is the number of bytes from `offset` to the end
// of the data. Fills `info` (pose included) when the structure is intact.
std::optional<RecordingDamage> check_chunk_structure(const RecordingHeader& h,
                                                     std::span<const std::uint8_t> probe,
                                                     std::uint64_t offset, std::uint64_t avail,
                                                     std::uint64_t index, std::string_view name,
                                                     RecordedFrameInfo& info) {
  std::array<std::uint8_t, kMagicBytes> magic{};
  put_u32(magic.data(), kChunkMagic);
  const std::size_t magic_n = std::min(probe.size(), kMagicBytes);
  if (!std::equal(probe.begin(), probe.begin() + static_cast<std::ptrdiff_t>(magic_n),
                  magic.begin())) {
    return make_damage(DamageKind::kBadChunkMagic, name, offset, index,
                       "found " + hex_bytes(probe.first(magic_n)) + ", expected " +
                           hex_bytes(magic) + " (\"MERF\")");
  }
  if (avail < kChunkPrefixSize) {
    return make_damage(DamageKind::kTruncatedChunk, name, offset, index,
                       "the file ends " + std::to_string(avail) + " bytes into the chunk header (" +
                           std::to_string(kChunkPrefixSize) + " bytes)");
  }
  const std::uint32_t length = get_u32(probe.data() + kOffChunkLength);
  const std::uint32_t flags = get_u32(probe.data() + kOffChunkFlags);
  const std::uint32_t payload = get_u32(probe.data() + kOffChunkPayloadLength);
  if ((flags & ~kChunkFlagsKnown) != 0U) {
    return make_damage(DamageKind::kBadFlags, name, offset, index,
                       "unknown chunk flags " + hex32(flags));
  }
  const bool has_pose = (flags & kChunkFlagHasPose) != 0U;
  if (has_pose && !h.has_ground_truth) {
    return make_damage(DamageKind::kBadFlags, name, offset, index,
                       "chunk has a pose but the header says the recording has no ground truth");
  }
  const std::uint64_t expected_payload = frame_payload_size(h);
  if (payload != expected_payload) {
    return make_damage(
        DamageKind::kBadLength, name, offset, index,
        "payload length " + std::to_string(payload) + ", expected " +
            std::to_string(expected_payload) + " for " + std::to_string(h.intrinsics.width) + "x" +
            std::to_string(h.intrinsics.height) + " GREY8" + (h.has_depth ? " + f32 depth" : ""));
  }
  const std::uint64_t expected_length =
      kChunkPrefixSize + (has_pose ? kChunkPoseSize : 0) + expected_payload + kChunkCrcSize;
  if (length != expected_length) {
    return make_damage(
        DamageKind::kBadLength, name, offset, index,
        "chunk length " + std::to_string(length) + ", expected " + std::to_string(expected_length));
  }
  if (length > avail) {
    return make_damage(DamageKind::kTruncatedChunk, name, offset, index,
                       "the chunk needs " + std::to_string(length) + " bytes, the file has " +
                           std::to_string(avail) + " left");
  }
  // length <= avail and length >= kChunkProbeSize when there is a pose: the probe has it.
  info = RecordedFrameInfo{};
  info.offset = offset;
  info.length = length;
  info.seq = get_u64(probe.data() + kOffChunkSeq);
  info.t_ns = static_cast<std::int64_t>(get_u64(probe.data() + kOffChunkTime));
  info.has_pose = has_pose;
  if (has_pose) {
    for (std::size_t i = 0; i < kPoseDoubles; ++i) {
      info.pose[i] = get_f64(probe.data() + kChunkPrefixSize + i * sizeof(double));
      if (!std::isfinite(info.pose[i])) {
        return make_damage(DamageKind::kBadPose, name, offset, index,
                           "pose value " + std::to_string(i) + " is not finite");
      }
    }
    const double qn = std::sqrt(info.pose[3] * info.pose[3] + info.pose[4] * info.pose[4] +
                                info.pose[5] * info.pose[5] + info.pose[6] * info.pose[6]);
    if (std::abs(qn - 1.0) > kMaxQuaternionNormError) {
      return make_damage(DamageKind::kBadPose, name, offset, index,
                         "pose quaternion norm " + std::to_string(qn) + " is not 1");
    }
  }
  info.payload_offset = offset + kChunkPrefixSize + (has_pose ? kChunkPoseSize : 0);
  return std::nullopt;
}

// Checks the CRC of a whole chunk (`chunk` holds exactly its `length` bytes).
std::optional<RecordingDamage> check_chunk_crc(std::span<const std::uint8_t> chunk,
                                               std::uint64_t offset, std::uint64_t index,
                                               std::string_view name) {
  const std::size_t body = chunk.size() - kChunkCrcSize;
  const std::uint32_t stored = get_u32(chunk.data() + body);
  const std::uint32_t crc = crc32(chunk.first(body));
  if (stored != crc) {
    return make_damage(DamageKind::kCrcMismatch, name, offset, index,
                       "stored " + hex32(stored) + ", computed " + hex32(crc));
  }
  return std::nullopt;
}

}  // namespace recording_detail

using recording_detail::check_chunk_crc;
using recording_detail::check_chunk_structure;
using recording_detail::decode_header;
using recording_detail::kChunkProbeSize;

// ---- Public helpers ----------------------------------------------------------------------------

std::uint32_t crc32(std::span<const std::uint8_t> bytes, std::uint32_t crc) noexcept {
  std::uint32_t c = crc ^ kCrcInit;
  for (const std::uint8_t b : bytes) c = kCrcTable[(c ^ b) & kByteMask] ^ (c >> kBitsPerByte);
  return c ^ kCrcInit;
}

std::uint64_t frame_payload_size(const RecordingHeader& header) noexcept {
  const int w = header.intrinsics.width;
  const int h = header.intrinsics.height;
  if (w <= 0 || h <= 0 || static_cast<std::uint32_t>(w) > kMaxImageDimension ||
      static_cast<std::uint32_t>(h) > kMaxImageDimension ||
      header.pixel_format != RecPixelFormat::kGrey8) {
    return 0;
  }
  const std::uint64_t pixels = static_cast<std::uint64_t>(w) * static_cast<std::uint64_t>(h);
  return pixels + (header.has_depth ? pixels * kDepthBytesPerPixel : 0);
}

SE3d pose_from_stored(const std::array<double, kPoseDoubles>& pose) {
  const Eigen::Quaterniond q(pose[6], pose[3], pose[4], pose[5]);  // w, x, y, z
  return make_se3(q, Eigen::Vector3d(pose[0], pose[1], pose[2]));
}

std::array<double, kPoseDoubles> stored_from_pose(const SE3d& T_w_c) {
  const Eigen::Quaterniond q(T_w_c.linear());
  const Eigen::Vector3d t = T_w_c.translation();
  return {t.x(), t.y(), t.z(), q.x(), q.y(), q.z(), q.w()};
}

std::string_view damage_kind_name(DamageKind kind) noexcept {
  switch (kind) {
    case DamageKind::kTruncatedChunk:
      return "truncated chunk";
    case DamageKind::kBadChunkMagic:
      return "bad chunk magic";
    case DamageKind::kBadLength:
      return "bad length";
    case DamageKind::kBadFlags:
      return "bad chunk flags";
    case DamageKind::kCrcMismatch:
      return "CRC mismatch";
    case DamageKind::kBadPose:
      return "bad pose";
    case DamageKind::kIoError:
      return "I/O error";
  }
  return "unknown";
}

std::vector<std::uint8_t> encode_header(const RecordingHeader& header) {
  const std::size_t d = std::min(header.description.size(), kMaxDescriptionLength);
  std::vector<std::uint8_t> out(kHeaderOverhead + d, 0);
  std::uint8_t* p = out.data();
  std::copy(kRecordingMagic.begin(), kRecordingMagic.end(), p);
  put_u32(p + kOffVersion, kRecordingVersion);
  put_u32(p + kOffHeaderLength, static_cast<std::uint32_t>(out.size()));
  const CameraIntrinsics& k = header.intrinsics;
  std::uint32_t flags = 0;
  if (header.has_depth) flags |= kHeaderFlagHasDepth;
  if (header.has_ground_truth) flags |= kHeaderFlagHasGroundTruth;
  if (k.focal_known) flags |= kHeaderFlagFocalKnown;
  put_u32(p + kOffFlags, flags);
  put_u32(p + kOffPixelFormat, static_cast<std::uint32_t>(header.pixel_format));
  put_u32(p + kOffWidth, static_cast<std::uint32_t>(k.width));
  put_u32(p + kOffHeight, static_cast<std::uint32_t>(k.height));
  put_f64(p + kOffFps, header.nominal_fps);
  const std::array<double, kCalibrationDoubles> calib{k.fx,      k.fy,      k.cx,      k.cy,
                                                      k.dist[0], k.dist[1], k.dist[2], k.dist[3]};
  for (std::size_t i = 0; i < kCalibrationDoubles; ++i) {
    put_f64(p + kOffCalibration + i * sizeof(double), calib[i]);
  }
  put_u32(p + kOffDescriptionLength, static_cast<std::uint32_t>(d));
  std::copy_n(header.description.data(), d, p + kHeaderFixedSize);
  const std::size_t crc_offset = out.size() - kChunkCrcSize;
  put_u32(p + crc_offset, crc32(std::span<const std::uint8_t>(out).first(crc_offset)));
  return out;
}

Status encode_chunk(const RecordingHeader& header, const Frame& frame,
                    std::vector<std::uint8_t>& out) {
  const std::uint64_t payload = frame_payload_size(header);
  if (payload == 0) {
    return invalid_argument("recording: unsupported header (image " +
                            std::to_string(header.intrinsics.width) + "x" +
                            std::to_string(header.intrinsics.height) + ", pixel format " +
                            std::to_string(static_cast<std::uint32_t>(header.pixel_format)) + ")");
  }
  const int w = header.intrinsics.width;
  const int h = header.intrinsics.height;
  if (frame.gray.type() != CV_8UC1 || frame.gray.cols != w || frame.gray.rows != h) {
    return invalid_argument("recording: frame seq " + std::to_string(frame.seq) + ": image " +
                            std::to_string(frame.gray.cols) + "x" +
                            std::to_string(frame.gray.rows) + " (type " +
                            std::to_string(frame.gray.type()) + ") does not match the recording (" +
                            std::to_string(w) + "x" + std::to_string(h) + " 8-bit grey)");
  }
  if (header.has_depth &&
      (frame.depth.type() != CV_32FC1 || frame.depth.cols != w || frame.depth.rows != h)) {
    return invalid_argument("recording: frame seq " + std::to_string(frame.seq) + ": depth " +
                            std::to_string(frame.depth.cols) + "x" +
                            std::to_string(frame.depth.rows) + " does not match the recording (" +
                            std::to_string(w) + "x" + std::to_string(h) + " f32)");
  }
  const bool has_pose = header.has_ground_truth && frame.has_ground_truth;
  const std::uint64_t length =
      kChunkPrefixSize + (has_pose ? kChunkPoseSize : 0) + payload + kChunkCrcSize;
  if (length > std::numeric_limits<std::uint32_t>::max()) {
    return invalid_argument("recording: frame chunk of " + std::to_string(length) +
                            " bytes exceeds the format's 4 GiB limit");
  }
  const std::size_t start = out.size();
  out.resize(start + length);
  std::uint8_t* p = out.data() + start;
  put_u32(p, kChunkMagic);
  put_u32(p + kOffChunkLength, static_cast<std::uint32_t>(length));
  put_u64(p + kOffChunkSeq, frame.seq);
  put_u64(p + kOffChunkTime, static_cast<std::uint64_t>(frame.t_ns));
  put_u32(p + kOffChunkFlags, has_pose ? kChunkFlagHasPose : 0U);
  put_u32(p + kOffChunkPayloadLength, static_cast<std::uint32_t>(payload));
  std::uint8_t* q = p + kChunkPrefixSize;
  if (has_pose) {
    const auto pose = stored_from_pose(frame.T_w_c_gt);
    for (std::size_t i = 0; i < kPoseDoubles; ++i) put_f64(q + i * sizeof(double), pose[i]);
    q += kChunkPoseSize;
  }
  const auto row_bytes = static_cast<std::size_t>(w);
  for (int r = 0; r < h; ++r, q += row_bytes)
    std::memcpy(q, frame.gray.ptr<std::uint8_t>(r), row_bytes);
  if (header.has_depth) {
    for (int r = 0; r < h; ++r) {
      const float* src = frame.depth.ptr<float>(r);
      if constexpr (std::endian::native == std::endian::little) {
        std::memcpy(q, src, row_bytes * kDepthBytesPerPixel);
        q += row_bytes * kDepthBytesPerPixel;
      } else {
        for (int c = 0; c < w; ++c, q += kDepthBytesPerPixel) {
          put_u32(q, std::bit_cast<std::uint32_t>(src[c]));
        }
      }
    }
  }
  const std::size_t body = length - kChunkCrcSize;
  put_u32(p + body, crc32(std::span<const std::uint8_t>(p, body)));
  return Status::ok();
}

Status decode_payload(const RecordingHeader& header, std::span<const std::uint8_t> payload,
                      Frame& out) {
  const std::uint64_t expected = frame_payload_size(header);
  if (expected == 0 || payload.size() != expected) {
    return input_error("recording: payload of " + std::to_string(payload.size()) +
                       " bytes, expected " + std::to_string(expected));
  }
  const int w = header.intrinsics.width;
  const int h = header.intrinsics.height;
  if (out.gray.rows != h || out.gray.cols != w || out.gray.type() != CV_8UC1) {
    out.gray.create(h, w, CV_8UC1);
  }
  const std::uint8_t* q = payload.data();
  const auto row_bytes = static_cast<std::size_t>(w);
  for (int r = 0; r < h; ++r, q += row_bytes)
    std::memcpy(out.gray.ptr<std::uint8_t>(r), q, row_bytes);
  if (header.has_depth) {
    if (out.depth.rows != h || out.depth.cols != w || out.depth.type() != CV_32FC1) {
      out.depth.create(h, w, CV_32FC1);
    }
    for (int r = 0; r < h; ++r) {
      float* dst = out.depth.ptr<float>(r);
      if constexpr (std::endian::native == std::endian::little) {
        std::memcpy(dst, q, row_bytes * kDepthBytesPerPixel);
        q += row_bytes * kDepthBytesPerPixel;
      } else {
        for (int c = 0; c < w; ++c, q += kDepthBytesPerPixel)
          dst[c] = std::bit_cast<float>(get_u32(q));
      }
    }
  }
  return Status::ok();
}

Result<ParsedRecording> parse_recording(std::span<const std::uint8_t> bytes,
                                        std::string_view name) {
  std::size_t header_size = 0;
  auto header = decode_header(bytes.first(std::min(bytes.size(), kMaxHeaderSize)), bytes.size(),
                              name, header_size);
  if (!header.is_ok()) return header.status();
  ParsedRecording out;
  out.header = std::move(header).value();
  std::uint64_t offset = header_size;
  for (std::uint64_t index = 0; offset < bytes.size(); ++index) {
    const std::uint64_t avail = bytes.size() - offset;
    const auto probe = bytes.subspan(offset, std::min<std::uint64_t>(avail, kChunkProbeSize));
    RecordedFrameInfo info;
    out.damage = check_chunk_structure(out.header, probe, offset, avail, index, name, info);
    if (!out.damage)
      out.damage = check_chunk_crc(bytes.subspan(offset, info.length), offset, index, name);
    if (out.damage) break;
    out.frames.push_back(info);
    offset += info.length;
  }
  return out;
}

// ---- RecordingWriter -------------------------------------------------------------------------

}  // namespace mer::hal
