// Fuzz target: the native recording parser. Each input is checked twice, as is and with
// its header and chunk CRCs recomputed (so the checks behind the CRCs are reached too), and
// through both entry points: parse_recording() on the bytes and RecordingReader on the same
// bytes as a file (a memfd). Both must agree on the header verdict, the intact frames and
// the damage; any disagreement aborts (a finding like a crash).
#include <sys/mman.h>
#include <unistd.h>

#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <span>
#include <string>
#include <vector>

#include "hal/replay/recording.h"

namespace {

using mer::hal::kChunkCrcSize;
using mer::hal::kChunkPrefixSize;
using mer::hal::kHeaderFixedSize;
using mer::hal::kHeaderOverhead;

/// Frames whose payload is decoded per input (decoding is linear in the input anyway).
constexpr std::size_t kMaxDecodedFrames = 8;
/// Offsets of the length fields used by repair_crcs() (see the tables in recording.h).
constexpr std::size_t kOffDescriptionLength = 104;
constexpr std::size_t kOffChunkLength = 4;

std::uint32_t get_u32(const std::vector<std::uint8_t>& b, std::size_t at) {
  return static_cast<std::uint32_t>(b[at]) | (static_cast<std::uint32_t>(b[at + 1]) << 8U) |
         (static_cast<std::uint32_t>(b[at + 2]) << 16U) |
         (static_cast<std::uint32_t>(b[at + 3]) << 24U);
}

void put_u32(std::vector<std::uint8_t>& b, std::size_t at, std::uint32_t v) {
  for (unsigned i = 0; i < 4; ++i) b[at + i] = static_cast<std::uint8_t>(v >> (8U * i));
}

// Recomputes the header CRC and the CRC of every chunk whose length field fits the data.
void repair_crcs(std::vector<std::uint8_t>& b) {
  if (b.size() < kHeaderFixedSize) return;
  const std::size_t header = kHeaderOverhead + get_u32(b, kOffDescriptionLength);
  if (header > b.size()) return;
  const std::span<const std::uint8_t> all(b);
  put_u32(b, header - kChunkCrcSize, mer::hal::crc32(all.first(header - kChunkCrcSize)));
  for (std::size_t off = header; off + kChunkPrefixSize <= b.size();) {
    const std::size_t len = get_u32(b, off + kOffChunkLength);
    if (len < kChunkPrefixSize + kChunkCrcSize || len > b.size() - off) return;
    put_u32(b, off + len - kChunkCrcSize, mer::hal::crc32(all.subspan(off, len - kChunkCrcSize)));
    off += len;
  }
}

[[noreturn]] void fail(const char* what) {
  std::fprintf(stderr, "recording_fuzz: %s\n", what);
  std::abort();
}

int memfd() {
  static const int kMemFd = ::memfd_create("mer_recording_fuzz", MFD_CLOEXEC);
  return kMemFd;
}

void check(std::span<const std::uint8_t> bytes) {
  auto parsed = mer::hal::parse_recording(bytes, "fuzz");
  if (parsed.is_ok()) {
    const auto& p = parsed.value();
    const std::uint64_t payload = mer::hal::frame_payload_size(p.header);
    mer::hal::Frame frame;
    for (std::size_t i = 0; i < p.frames.size() && i < kMaxDecodedFrames; ++i) {
      const auto& f = p.frames[i];
      if (f.payload_offset + payload + kChunkCrcSize != f.offset + f.length) {
        fail("payload span outside its chunk");
      }
      const mer::Status s =
          mer::hal::decode_payload(p.header, bytes.subspan(f.payload_offset, payload), frame);
      if (!s.is_ok()) fail("an intact frame's payload does not decode");
      static_cast<void>(mer::hal::pose_from_stored(f.pose));
    }
  }

  // The same bytes through the file reader.
  const int fd = memfd();
  if (fd < 0 || ::ftruncate(fd, 0) != 0) return;
  std::size_t done = 0;
  while (done < bytes.size()) {
    const ssize_t n =
        ::pwrite(fd, bytes.data() + done, bytes.size() - done, static_cast<off_t>(done));
    if (n <= 0) return;
    done += static_cast<std::size_t>(n);
  }
  mer::hal::RecordingReader reader;
  const mer::Status s = reader.open("/proc/self/fd/" + std::to_string(fd));
  if (s.is_ok() != parsed.is_ok()) fail("file reader and parser disagree on the header");
  if (!s.is_ok()) return;
  mer::hal::Frame frame;
  std::size_t n = 0;
  while (reader.read_frame(n, frame) == mer::hal::ReadStatus::kFrame) ++n;
  const auto& p = parsed.value();
  if (n != p.frames.size()) fail("file reader and parser disagree on the intact frames");
  if (reader.damage().has_value() != p.damage.has_value()) fail("disagreement on damage");
  if (p.damage &&
      (reader.damage()->kind != p.damage->kind || reader.damage()->offset != p.damage->offset ||
       reader.damage()->frame_index != p.damage->frame_index)) {
    fail("file reader and parser report different damage");
  }
}

}  // namespace

// NOLINTNEXTLINE(readability-identifier-naming): the name libFuzzer calls
extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  const std::span<const std::uint8_t> in(data, size);
  check(in);
  std::vector<std::uint8_t> repaired(in.begin(), in.end());
  repair_crcs(repaired);
  check(repaired);
  return 0;
}
