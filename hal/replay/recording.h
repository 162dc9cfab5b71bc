#pragma once
/// @file recording.h
/// The native recording format (`.merrec`): writer, reader and an in-memory parser.
///
/// A recording is a file header followed by one chunk per frame. Every multi-byte field is
/// little-endian; f64 is IEEE-754 binary64, f32 binary32. CRC32 is the IEEE 802.3 CRC
/// (reflected polynomial 0xEDB88320, initial value 0xFFFFFFFF, final XOR 0xFFFFFFFF; the
/// check value of "123456789" is 0xCBF43926), the one zlib and PNG use.
///
/// ## File header (version 1), H = 112 + D bytes
/// | offset | size | type   | field                                                         |
/// |-------:|-----:|--------|---------------------------------------------------------------|
/// |      0 |    8 | u8[8]  | magic "MERREC\0\0"                                            |
/// |      8 |    4 | u32    | format version (1)                                            |
/// |     12 |    4 | u32    | header length H (offset 0 through the header CRC)             |
/// |     16 |    4 | u32    | flags: bit 0 has_depth, bit 1 has_ground_truth,               |
/// |        |      |        | bit 2 focal_known; other bits 0                               |
/// |     20 |    4 | u32    | pixel format: 1 GREY8 (reserved: 2 YUYV, 3 NV12)              |
/// |     24 |    4 | u32    | width, px (1..16384)                                          |
/// |     28 |    4 | u32    | height, px (1..16384)                                         |
/// |     32 |    8 | f64    | nominal fps (0: unknown)                                      |
/// |     40 |   64 | f64[8] | fx, fy, cx, cy, k1, k2, p1, p2 (pinhole + radtan)             |
/// |    104 |    4 | u32    | D = camera description length, bytes (<= 4096)               |
/// |    108 |    D | u8[D]  | camera description, UTF-8, not NUL-terminated                 |
/// |  108+D |    4 | u32    | CRC32 of bytes [0, 108+D)                                     |
///
/// ## Frame chunk, C = 36 + G + P bytes (G = 56 with a pose, else 0)
/// | offset | size | type   | field                                                         |
/// |-------:|-----:|--------|---------------------------------------------------------------|
/// |      0 |    4 | u32    | chunk magic 0x4652454D (the bytes "MERF")                     |
/// |      4 |    4 | u32    | chunk length C (chunk magic through the chunk CRC)            |
/// |      8 |    8 | u64    | seq (the source's sequence number)                            |
/// |     16 |    8 | i64    | t_ns (capture time, ns)                                       |
/// |     24 |    4 | u32    | chunk flags: bit 0 has_pose (only when the header's           |
/// |        |      |        | has_ground_truth is set); other bits 0                        |
/// |     28 |    4 | u32    | payload length P; must equal the frame size from the header: |
/// |        |      |        | width*height (GREY8) + width*height*4 when has_depth          |
/// |     32 |    G | f64[7] | T_w_c ground truth: tx ty tz qx qy qz qw (TUM order)          |
/// |   32+G |    P | bytes  | image rows top to bottom, tightly packed (no stride), then    |
/// |        |      |        | the depth image as f32 metres, rows tightly packed            |
/// | 32+G+P |    4 | u32    | CRC32 of chunk bytes [0, C-4)                                 |
///
/// The file ends after the last chunk; there is no trailer, so a recording cut anywhere
/// (kill -9, power loss, full disk) is still a valid prefix up to its last complete chunk.
///
/// Reading: the header must be intact (bad magic, unknown version, bad lengths or CRC are
/// errors naming the file and byte offset). Chunks are then read in order; the first chunk
/// that is truncated, has a bad magic, inconsistent lengths or flags, or a CRC mismatch ends
/// the stream: every frame before it replays, and the damage (byte offset, frame index,
/// what was wrong) is reported. Lengths are checked against the header and the file size
/// before anything is allocated, so no field can make the reader allocate more than the
/// file holds.

#include <array>
#include <cstddef>
#include <cstdint>
#include <optional>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "core/pose.h"
#include "core/status.h"
#include "hal/camera.h"

namespace mer::hal {

/// The 8 bytes every recording starts with.
inline constexpr std::array<std::uint8_t, 8> kRecordingMagic{'M', 'E', 'R', 'R', 'E', 'C', 0, 0};
/// Format version written by this code, and the only one it reads.
inline constexpr std::uint32_t kRecordingVersion = 1;
/// First 4 bytes of every frame chunk ("MERF" read as a little-endian u32).
inline constexpr std::uint32_t kChunkMagic = 0x4652454D;
/// Header bytes before the description (magic through the description length).
inline constexpr std::size_t kHeaderFixedSize = 108;
/// Header bytes besides the description (fixed part + CRC).
inline constexpr std::size_t kHeaderOverhead = kHeaderFixedSize + 4;
/// Longest camera description accepted, bytes (the writer truncates longer ones).
inline constexpr std::size_t kMaxDescriptionLength = 4096;
/// Longest header, bytes.
inline constexpr std::size_t kMaxHeaderSize = kHeaderOverhead + kMaxDescriptionLength;
/// Largest accepted width or height, px.
inline constexpr std::uint32_t kMaxImageDimension = 16384;
/// Chunk bytes before the optional pose (magic through payload length).
inline constexpr std::size_t kChunkPrefixSize = 32;
/// Number of f64 in a chunk's pose (tx ty tz qx qy qz qw).
inline constexpr std::size_t kPoseDoubles = 7;
/// Bytes of a chunk's pose.
inline constexpr std::size_t kChunkPoseSize = kPoseDoubles * sizeof(double);
/// Bytes of the chunk CRC.
inline constexpr std::size_t kChunkCrcSize = 4;

/// Header flag: every chunk carries a depth image.
inline constexpr std::uint32_t kHeaderFlagHasDepth = 1U << 0U;
/// Header flag: chunks may carry a ground-truth pose.
inline constexpr std::uint32_t kHeaderFlagHasGroundTruth = 1U << 1U;
/// Header flag: fx/fy are calibrated (CameraIntrinsics::focal_known).
inline constexpr std::uint32_t kHeaderFlagFocalKnown = 1U << 2U;
/// Every header flag this version knows.
inline constexpr std::uint32_t kHeaderFlagsKnown =
    kHeaderFlagHasDepth | kHeaderFlagHasGroundTruth | kHeaderFlagFocalKnown;
/// Chunk flag: the chunk carries a ground-truth pose.
inline constexpr std::uint32_t kChunkFlagHasPose = 1U << 0U;
/// Every chunk flag this version knows.
inline constexpr std::uint32_t kChunkFlagsKnown = kChunkFlagHasPose;

/// Pixel format code of the image payload. Only kGrey8 is written and read today; the
/// other codes are reserved so that raw camera formats can be recorded later.
enum class RecPixelFormat : std::uint32_t {
  kGrey8 = 1,  ///< 8-bit grey, width*height bytes
  kYuyv = 2,   ///< reserved: packed YUV 4:2:2, width*height*2 bytes
  kNv12 = 3,   ///< reserved: Y plane + interleaved UV, width*height*3/2 bytes
};

/// Incremental CRC32 (IEEE, table-driven): pass the previous result as `crc` to continue a
/// running checksum over several buffers (0 starts a new one), like zlib's crc32().
std::uint32_t crc32(std::span<const std::uint8_t> bytes, std::uint32_t crc = 0) noexcept;

/// What the file header describes.
struct RecordingHeader {
  std::uint32_t version = kRecordingVersion;  ///< format version (read from the file)
  std::string description;                    ///< camera description (describe() of the source)
  RecPixelFormat pixel_format = RecPixelFormat::kGrey8;  ///< payload image format
  CameraIntrinsics intrinsics;                           ///< image size, calibration, focal_known
  double nominal_fps = 0.0;                              ///< frame rate of the source (0: unknown)
  bool has_depth = false;         ///< every chunk carries an f32 depth image after the image
  bool has_ground_truth = false;  ///< chunks may carry a ground-truth pose
};

/// Bytes of one frame's payload for `header` (image + depth), or 0 when the header's
/// image size or pixel format is unsupported.
std::uint64_t frame_payload_size(const RecordingHeader& header) noexcept;

/// Metadata of one frame chunk (everything but the payload).
struct RecordedFrameInfo {
  std::uint64_t offset = 0;                 ///< byte offset of the chunk in the file
  std::uint32_t length = 0;                 ///< chunk length C, bytes
  std::uint64_t seq = 0;                    ///< source sequence number
  std::int64_t t_ns = 0;                    ///< capture time, ns
  bool has_pose = false;                    ///< the chunk carries a ground-truth pose
  std::array<double, kPoseDoubles> pose{};  ///< tx ty tz qx qy qz qw as stored
  std::uint64_t payload_offset = 0;         ///< byte offset of the payload in the file
};

/// Camera-to-world pose from the stored 7 doubles (tx ty tz qx qy qz qw).
SE3d pose_from_stored(const std::array<double, kPoseDoubles>& pose);
/// The 7 doubles stored for `T_w_c` (quaternion from the rotation, then TUM order).
std::array<double, kPoseDoubles> stored_from_pose(const SE3d& T_w_c);

/// What kind of damage ended a recording early.
enum class DamageKind {
  kTruncatedChunk,  ///< the file ends inside a chunk
  kBadChunkMagic,   ///< a chunk does not start with kChunkMagic
  kBadLength,       ///< chunk or payload length inconsistent with the header (absurd length)
  kBadFlags,        ///< unknown chunk flag bits, or a pose in a recording without ground truth
  kCrcMismatch,     ///< the chunk's bytes do not match its CRC32
  kBadPose,         ///< the stored pose is not finite or its quaternion is not unit length
  kIoError,         ///< the file could not be read at that offset
};

/// Short name of a damage kind ("truncated chunk", "CRC mismatch", ...).
std::string_view damage_kind_name(DamageKind kind) noexcept;

/// Where and why a recording stops before its end. Frames [0, frame_index) are intact.
struct RecordingDamage {
  DamageKind kind = DamageKind::kTruncatedChunk;  ///< what was wrong
  std::uint64_t offset = 0;                       ///< byte offset of the damaged chunk
  std::uint64_t frame_index = 0;                  ///< index of the damaged chunk's frame
  std::string message;  ///< one line naming the file, frame index, offset and detail
};

/// Builds the header bytes for `header` (description truncated to kMaxDescriptionLength).
std::vector<std::uint8_t> encode_header(const RecordingHeader& header);

/// Appends the chunk of `frame` to `out` (in place; no allocation when `out` has the
/// capacity). The frame must match the header: gray CV_8UC1 of the header's size, depth
/// CV_32FC1 of the same size when has_depth. The pose is stored when both the header and
/// the frame have ground truth. Errors name the frame's seq and what did not match.
Status encode_chunk(const RecordingHeader& header, const Frame& frame,
                    std::vector<std::uint8_t>& out);

/// Copies a chunk payload (`frame_payload_size(header)` bytes) into `out.gray` (and
/// `out.depth` when has_depth), (re)allocating them only when their size or type differs.
Status decode_payload(const RecordingHeader& header, std::span<const std::uint8_t> payload,
                      Frame& out);

/// Result of parse_recording(): the header, every intact frame and the damage, if any.
struct ParsedRecording {
  RecordingHeader header;                 ///< the validated header
  std::vector<RecordedFrameInfo> frames;  ///< intact frames in file order (CRC-checked)
  std::optional<RecordingDamage> damage;  ///< set when the bytes end in damage
};

/// Parses a whole recording held in memory (the fuzzing entry point; also used by tests).
/// Header errors are a kInputError Status naming `name` and the byte offset; damage after
/// the header is reported in ParsedRecording::damage. Never reads outside `bytes`,
/// allocates at most a small constant per intact frame.
Result<ParsedRecording> parse_recording(std::span<const std::uint8_t> bytes,
                                        std::string_view name = "<memory>");

/// Options of RecordingWriter.
struct RecordingWriterOptions {
  /// fdatasync() at most this often (ns) so that a power loss loses at most this much; each
  /// chunk is handed to the kernel with write(2) at once, so a killed process loses at most
  /// the chunk being written. 0: sync after every chunk.
  std::int64_t sync_period_ns = 1'000'000'000;
};

/// Writes a recording. Not thread-safe: one writer thread calls open/append/close.
///
/// Each chunk is encoded into a buffer allocated at open() and handed to the kernel with
/// write(2) before append() returns (no user-space buffering to lose), then fdatasync()ed
/// every `sync_period_ns`. A process killed at any point leaves a file whose every chunk
/// but possibly the last is complete; the reader stops at the incomplete one.
class RecordingWriter {
 public:
  /// Closed writer.
  RecordingWriter() = default;
  RecordingWriter(const RecordingWriter&) = delete;
  RecordingWriter& operator=(const RecordingWriter&) = delete;
  /// Closes the file (errors are ignored; call close() to see them).
  ~RecordingWriter();

  /// Creates (truncates) `path`, writes and syncs the header. Errors name the file.
  Status open(const std::string& path, const RecordingHeader& header,
              const RecordingWriterOptions& options = {});
  /// Writes one frame chunk (see encode_chunk() for what the frame must match).
  Status append(const Frame& frame);
  /// fdatasync() now.
  Status sync();
  /// Syncs and closes the file. Idempotent; a closed writer returns ok.
  Status close();

  /// True between a successful open() and close().
  bool is_open() const { return fd_ >= 0; }
  /// Chunks written so far.
  std::uint64_t frames_written() const { return frames_written_; }
  /// Bytes written so far (header included).
  std::uint64_t bytes_written() const { return bytes_written_; }
  /// The header written by open().
  const RecordingHeader& header() const { return header_; }
  /// Path given to open().
  const std::string& path() const { return path_; }

 private:
  Status write_all(std::span<const std::uint8_t> bytes);

  int fd_ = -1;
  std::string path_;
  RecordingHeader header_;
  RecordingWriterOptions options_;
  std::vector<std::uint8_t> chunk_;  // encode buffer, capacity reserved at open()
  std::uint64_t frames_written_ = 0;
  std::uint64_t bytes_written_ = 0;
  std::int64_t last_sync_ns_ = 0;
};

/// Outcome of RecordingReader::read_frame().
enum class ReadStatus {
  kFrame,    ///< the frame was decoded
  kEnd,      ///< clean end of the recording: no frame at this index
  kDamaged,  ///< the recording is damaged at or before this index; see damage()
};

/// Reads a recording file frame by frame (random access by index).
///
/// open() validates the header and scans the chunk structure (magic, lengths, flags, pose;
/// one small read per chunk, no payload read), so frame_count() and the ground truth are
/// known without reading the images; read_frame() reads one chunk, checks its CRC and
/// decodes it. A CRC mismatch found by read_frame() ends the recording at that frame.
class RecordingReader {
 public:
  /// Closed reader.
  RecordingReader() = default;
  RecordingReader(const RecordingReader&) = delete;
  RecordingReader& operator=(const RecordingReader&) = delete;
  /// Takes over `other`'s file.
  RecordingReader(RecordingReader&& other) noexcept;
  /// Closes the current file and takes over `other`'s.
  RecordingReader& operator=(RecordingReader&& other) noexcept;
  /// Closes the file.
  ~RecordingReader();

  /// Opens `path`, validates the header and scans the chunks. Header errors (empty file,
  /// bad magic, future version, CRC mismatch, ...) are kInputError naming the file and
  /// offset; damage after the header is not an error (see damage()).
  Status open(const std::string& path);
  /// The validated header (valid after open()).
  const RecordingHeader& header() const { return header_; }
  /// Frames whose chunk structure is intact (an upper bound until every CRC is checked).
  std::size_t frame_count() const { return frames_.size(); }
  /// Metadata of frame `index` < frame_count() (the pose is CRC-checked once read_frame()
  /// returned kFrame for it).
  const RecordedFrameInfo& frame_info(std::size_t index) const { return frames_[index]; }
  /// Ground-truth poses of the frames that carry one (up to the first known damage).
  std::vector<StampedPose> ground_truth() const;

  /// Reads and CRC-checks frame `index`, decodes it into `out` (seq, t_ns, gray, depth,
  /// ground truth; see decode_payload() about buffers). `info` (optional) receives the
  /// chunk metadata with the pose exactly as stored.
  ReadStatus read_frame(std::size_t index, Frame& out, RecordedFrameInfo* info = nullptr);

  /// The first damage found so far (by the scan or by read_frame()), if any.
  const std::optional<RecordingDamage>& damage() const { return damage_; }
  /// Path given to open().
  const std::string& path() const { return path_; }
  /// File size at open(), bytes.
  std::uint64_t file_size() const { return file_size_; }

 private:
  void close_file() noexcept;
  void set_damage(RecordingDamage damage);

  int fd_ = -1;
  std::string path_;
  RecordingHeader header_;
  std::uint64_t file_size_ = 0;
  std::vector<RecordedFrameInfo> frames_;  // structurally intact chunks
  std::optional<RecordingDamage> damage_;
  std::vector<std::uint8_t> scratch_;  // one chunk
};

}  // namespace mer::hal
