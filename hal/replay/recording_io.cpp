// The native recording's files (recording.h): RecordingWriter appends frames with a CRC per
// chunk and syncs; RecordingReader indexes a file once, reads frames by index and reports the
// first damaged chunk.
#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cstring>
#include <filesystem>
#include <utility>

#include "hal/replay/recording.h"
#include "hal/replay/recording_internal.h"
#include "platform/clock.h"

namespace mer::hal {
namespace {

using recording_detail::check_chunk_crc;
using recording_detail::check_chunk_structure;
using recording_detail::decode_header;
using recording_detail::kChunkProbeSize;
using recording_detail::make_damage;

// ---- POSIX helpers ---------------------------------------------------------------------------

std::string errno_text(int err) {
  return std::strerror(err);
}

// Reads exactly `out.size()` bytes at `offset`; false on error or end of file.
bool pread_all(int fd, std::span<std::uint8_t> out, std::uint64_t offset, int& err) {
  std::size_t done = 0;
  while (done < out.size()) {
    const ssize_t n =
        ::pread(fd, out.data() + done, out.size() - done, static_cast<off_t>(offset + done));
    if (n < 0) {
      if (errno == EINTR) continue;
      err = errno;
      return false;
    }
    if (n == 0) {
      err = 0;
      return false;
    }
    done += static_cast<std::size_t>(n);
  }
  return true;
}

}  // namespace

RecordingWriter::~RecordingWriter() {
  static_cast<void>(close());
}

Status RecordingWriter::write_all(std::span<const std::uint8_t> bytes) {
  std::size_t done = 0;
  while (done < bytes.size()) {
    const ssize_t n = ::write(fd_, bytes.data() + done, bytes.size() - done);
    if (n < 0) {
      if (errno == EINTR) continue;
      const int err = errno;
      // Cut a partial chunk off so the file ends on a chunk boundary (best effort; the
      // reader copes with a partial chunk anyway).
      static_cast<void>(::ftruncate(fd_, static_cast<off_t>(bytes_written_)));
      static_cast<void>(::lseek(fd_, static_cast<off_t>(bytes_written_), SEEK_SET));
      return runtime_error("recording '" + path_ + "': write failed at byte offset " +
                           std::to_string(bytes_written_ + done) + ": " + errno_text(err));
    }
    done += static_cast<std::size_t>(n);
  }
  bytes_written_ += bytes.size();
  return Status::ok();
}

Status RecordingWriter::open(const std::string& path, const RecordingHeader& header,
                             const RecordingWriterOptions& options) {
  if (is_open())
    return runtime_error("recording '" + path + "': writer already open on '" + path_ + "'");
  const std::uint64_t payload = frame_payload_size(header);
  if (payload == 0) {
    return invalid_argument("recording '" + path + "': unsupported image " +
                            std::to_string(header.intrinsics.width) + "x" +
                            std::to_string(header.intrinsics.height) + " / pixel format " +
                            std::to_string(static_cast<std::uint32_t>(header.pixel_format)));
  }
  constexpr mode_t kFileMode = 0644;
  const int fd = ::open(path.c_str(), O_WRONLY | O_CREAT | O_TRUNC | O_CLOEXEC, kFileMode);
  if (fd < 0) {
    return invalid_argument("recording '" + path + "': cannot create: " + errno_text(errno));
  }
  fd_ = fd;
  path_ = path;
  header_ = header;
  header_.version = kRecordingVersion;
  if (header_.description.size() > kMaxDescriptionLength)
    header_.description.resize(kMaxDescriptionLength);
  options_ = options;
  frames_written_ = 0;
  bytes_written_ = 0;
  chunk_.clear();
  chunk_.reserve(kChunkPrefixSize + kChunkPoseSize + payload + kChunkCrcSize);
  const std::vector<std::uint8_t> bytes = encode_header(header_);
  Status s = write_all(bytes);
  if (s.is_ok()) s = sync();
  if (!s.is_ok()) {
    ::close(fd_);
    fd_ = -1;
    return s;
  }
  // Make the new directory entry durable too (best effort: some filesystems refuse).
  const std::filesystem::path parent = std::filesystem::absolute(path).parent_path();
  const int dir = ::open(parent.c_str(), O_RDONLY | O_DIRECTORY | O_CLOEXEC);
  if (dir >= 0) {
    static_cast<void>(::fsync(dir));
    ::close(dir);
  }
  last_sync_ns_ = platform::monotonic_now_ns();
  return Status::ok();
}

Status RecordingWriter::append(const Frame& frame) {
  if (!is_open()) return runtime_error("recording: append() on a closed writer");
  chunk_.clear();
  if (Status s = encode_chunk(header_, frame, chunk_); !s.is_ok()) return s;
  if (Status s = write_all(chunk_); !s.is_ok()) return s;
  ++frames_written_;
  const std::int64_t now = platform::monotonic_now_ns();
  if (now - last_sync_ns_ >= options_.sync_period_ns) {
    last_sync_ns_ = now;
    return sync();
  }
  return Status::ok();
}

Status RecordingWriter::sync() {
  if (!is_open()) return Status::ok();
  if (::fdatasync(fd_) != 0 && errno != EINVAL && errno != EROFS) {
    return runtime_error("recording '" + path_ + "': fdatasync failed: " + errno_text(errno));
  }
  return Status::ok();
}

Status RecordingWriter::close() {
  if (!is_open()) return Status::ok();
  Status s = sync();
  if (::close(fd_) != 0 && s.is_ok()) {
    s = runtime_error("recording '" + path_ + "': close failed: " + errno_text(errno));
  }
  fd_ = -1;
  return s;
}

// ---- RecordingReader -------------------------------------------------------------------------

RecordingReader::RecordingReader(RecordingReader&& other) noexcept
    : fd_(std::exchange(other.fd_, -1)),
      path_(std::move(other.path_)),
      header_(std::move(other.header_)),
      file_size_(other.file_size_),
      frames_(std::move(other.frames_)),
      damage_(std::move(other.damage_)),
      scratch_(std::move(other.scratch_)) {}

RecordingReader& RecordingReader::operator=(RecordingReader&& other) noexcept {
  if (this != &other) {
    close_file();
    fd_ = std::exchange(other.fd_, -1);
    path_ = std::move(other.path_);
    header_ = std::move(other.header_);
    file_size_ = other.file_size_;
    frames_ = std::move(other.frames_);
    damage_ = std::move(other.damage_);
    scratch_ = std::move(other.scratch_);
  }
  return *this;
}

RecordingReader::~RecordingReader() {
  close_file();
}

void RecordingReader::close_file() noexcept {
  if (fd_ >= 0) ::close(fd_);
  fd_ = -1;
}

void RecordingReader::set_damage(RecordingDamage damage) {
  if (!damage_ || damage.frame_index < damage_->frame_index) damage_ = std::move(damage);
  if (frames_.size() > damage_->frame_index) frames_.resize(damage_->frame_index);
}

Status RecordingReader::open(const std::string& path) {
  close_file();
  path_ = path;
  frames_.clear();
  damage_.reset();
  file_size_ = 0;
  const int fd = ::open(path.c_str(), O_RDONLY | O_CLOEXEC);
  if (fd < 0) return input_error(path + ": cannot open recording: " + errno_text(errno));
  fd_ = fd;
  struct stat st {};
  if (::fstat(fd_, &st) != 0) {
    const int err = errno;
    close_file();
    return input_error(path + ": cannot stat recording: " + errno_text(err));
  }
  if (!S_ISREG(st.st_mode)) {
    close_file();
    return input_error(path + ": not a regular file");
  }
  file_size_ = static_cast<std::uint64_t>(st.st_size);

  std::vector<std::uint8_t> head(std::min<std::uint64_t>(file_size_, kMaxHeaderSize));
  int err = 0;
  if (!pread_all(fd_, head, 0, err)) {
    close_file();
    return input_error(path + ": cannot read the recording header: " +
                       (err != 0 ? errno_text(err) : std::string("file shrank while reading")));
  }
  std::size_t header_size = 0;
  auto header = decode_header(head, file_size_, path, header_size);
  if (!header.is_ok()) {
    close_file();
    return header.status();
  }
  header_ = std::move(header).value();

  // Structure scan: one small read per chunk; the payload is read (and CRC-checked) by
  // read_frame().
  std::uint64_t offset = header_size;
  std::array<std::uint8_t, kChunkProbeSize> probe{};
  for (std::uint64_t index = 0; offset < file_size_; ++index) {
    const std::uint64_t avail = file_size_ - offset;
    const auto n = static_cast<std::size_t>(std::min<std::uint64_t>(avail, kChunkProbeSize));
    if (!pread_all(fd_, std::span(probe).first(n), offset, err)) {
      set_damage(
          make_damage(DamageKind::kIoError, path, offset, index,
                      err != 0 ? errno_text(err) : std::string("file shrank while reading")));
      break;
    }
    RecordedFrameInfo info;
    if (auto d = check_chunk_structure(header_, std::span(probe).first(n), offset, avail, index,
                                       path, info)) {
      set_damage(std::move(*d));
      break;
    }
    frames_.push_back(info);
    offset += info.length;
  }
  return Status::ok();
}

std::vector<StampedPose> RecordingReader::ground_truth() const {
  std::vector<StampedPose> out;
  for (const RecordedFrameInfo& f : frames_) {
    if (f.has_pose) out.push_back(StampedPose{f.t_ns, pose_from_stored(f.pose)});
  }
  return out;
}

ReadStatus RecordingReader::read_frame(std::size_t index, Frame& out, RecordedFrameInfo* info) {
  if (index >= frames_.size()) return damage_ ? ReadStatus::kDamaged : ReadStatus::kEnd;
  const RecordedFrameInfo f = frames_[index];
  scratch_.resize(f.length);  // bounded: the scan checked the chunk lies inside the file
  int err = 0;
  if (fd_ < 0 || !pread_all(fd_, scratch_, f.offset, err)) {
    set_damage(make_damage(DamageKind::kIoError, path_, f.offset, index,
                           err != 0 ? errno_text(err) : std::string("file shrank while reading")));
    return ReadStatus::kDamaged;
  }
  if (auto d = check_chunk_crc(scratch_, f.offset, index, path_)) {
    set_damage(std::move(*d));
    return ReadStatus::kDamaged;
  }
  const std::size_t start = f.payload_offset - f.offset;
  const std::size_t payload = f.length - start - kChunkCrcSize;
  if (Status s = decode_payload(header_, std::span(scratch_).subspan(start, payload), out);
      !s.is_ok()) {
    set_damage(make_damage(DamageKind::kBadLength, path_, f.offset, index, s.message()));
    return ReadStatus::kDamaged;
  }
  out.seq = f.seq;
  out.t_ns = f.t_ns;
  out.has_ground_truth = f.has_pose;
  out.T_w_c_gt = f.has_pose ? pose_from_stored(f.pose) : SE3d::Identity();
  if (info != nullptr) *info = f;
  return ReadStatus::kFrame;
}

}  // namespace mer::hal
