// Damaged recordings: truncation at every byte offset and a flipped byte at every offset,
// through both the in-memory parser and the file reader; absurd lengths; specific kinds.
#include <sys/resource.h>

#include <limits>

#include <gtest/gtest.h>

#include "hal/replay/recording.h"
#include "recording_test_util.h"

namespace mer::hal {
namespace {

using testing::make_header;
using testing::make_mem_recording;
using testing::MemRecording;
using testing::read_all;
using testing::same_bytes;
using testing::temp_path;
using testing::write_bytes;

/// Index of the chunk containing byte `pos` (chunk_offsets ends with the file size).
std::size_t chunk_of(const MemRecording& m, std::size_t pos) {
  std::size_t k = 0;
  while (k + 1 < m.chunk_offsets.size() && m.chunk_offsets[k + 1] <= pos) ++k;
  return k;
}

/// Checks a damaged reading: `frames` intact frames, damage at chunk `k` (or none when
/// `k` == frames count and `clean`).
void expect_damage_at(const std::optional<RecordingDamage>& d, const MemRecording& m, std::size_t k,
                      const std::string& where) {
  ASSERT_TRUE(d.has_value()) << where;
  EXPECT_EQ(d->frame_index, k) << where;
  EXPECT_EQ(d->offset, m.chunk_offsets[k]) << where;
  EXPECT_NE(d->message.find("frame " + std::to_string(k)), std::string::npos) << d->message;
  EXPECT_NE(d->message.find("byte offset " + std::to_string(m.chunk_offsets[k])), std::string::npos)
      << d->message;
}

// A 3-frame file cut at every byte offset: the frames fully before the cut replay (pixel
// for pixel), the damage is reported at the chunk the cut falls in; a cut inside the header
// is a header error; a cut on a chunk boundary is a clean shorter recording.
TEST(RecordingDamage, TruncationAtEveryByteOffset) {
  const MemRecording m = make_mem_recording(3);
  const std::size_t header = m.chunk_offsets.front();
  const std::string path = temp_path("trunc.merrec");
  for (std::size_t cut = 0; cut <= m.bytes.size(); ++cut) {
    const std::span<const std::uint8_t> prefix(m.bytes.data(), cut);
    const std::string where = "cut at " + std::to_string(cut);
    auto p = parse_recording(prefix, "mem");
    write_bytes(path, prefix);
    RecordingReader r;
    const Status s = r.open(path);
    if (cut < header) {
      ASSERT_FALSE(p.is_ok()) << where;
      ASSERT_FALSE(s.is_ok()) << where;
      EXPECT_EQ(s.code(), StatusCode::kInputError);
      EXPECT_NE(s.message().find(path), std::string::npos) << s.message();
      EXPECT_NE(s.message().find("byte offset"), std::string::npos) << s.message();
      continue;
    }
    ASSERT_TRUE(p.is_ok()) << where << ": " << p.status().message();
    ASSERT_TRUE(s.is_ok()) << where << ": " << s.message();
    const std::size_t k = chunk_of(m, cut);  // frames complete before the cut
    const bool on_boundary = m.chunk_offsets[k] == cut;
    EXPECT_EQ(p.value().frames.size(), k) << where;
    Frame f;
    std::size_t n = 0;
    for (; r.read_frame(n, f) == ReadStatus::kFrame; ++n) {
      ASSERT_LT(n, k) << where;
      EXPECT_TRUE(same_bytes(f.gray, m.frames[n].gray)) << where;
      EXPECT_TRUE(same_bytes(f.depth, m.frames[n].depth)) << where;
      EXPECT_EQ(f.seq, m.frames[n].seq);
    }
    EXPECT_EQ(n, k) << where;
    if (on_boundary) {
      EXPECT_FALSE(p.value().damage.has_value()) << where;
      EXPECT_FALSE(r.damage().has_value()) << where;
      EXPECT_EQ(r.read_frame(k, f), ReadStatus::kEnd);
    } else {
      expect_damage_at(p.value().damage, m, k, where + " (memory)");
      expect_damage_at(r.damage(), m, k, where + " (file)");
      EXPECT_EQ(r.damage()->kind, DamageKind::kTruncatedChunk) << where;
      EXPECT_EQ(p.value().damage->kind, DamageKind::kTruncatedChunk) << where;
      EXPECT_EQ(r.read_frame(k, f), ReadStatus::kDamaged);
    }
  }
}

// A flipped byte anywhere after the header: the frames before its chunk replay, the damage
// names that chunk (whatever field was hit), and nothing after it is handed out.
TEST(RecordingDamage, FlippedByteAtEveryOffsetAfterTheHeader) {
  const MemRecording m = make_mem_recording(3);
  const std::string path = temp_path("flip.merrec");
  for (std::size_t pos = m.chunk_offsets.front(); pos < m.bytes.size(); ++pos) {
    auto bytes = m.bytes;
    bytes[pos] ^= 0xFF;
    const std::size_t k = chunk_of(m, pos);
    const std::string where = "byte " + std::to_string(pos) + " (chunk " + std::to_string(k) + ")";
    auto p = parse_recording(bytes, "mem");
    ASSERT_TRUE(p.is_ok()) << where;
    EXPECT_EQ(p.value().frames.size(), k) << where;
    expect_damage_at(p.value().damage, m, k, where + " (memory)");

    write_bytes(path, bytes);
    RecordingReader r;
    ASSERT_TRUE(r.open(path).is_ok()) << where;
    std::optional<RecordingDamage> d;
    EXPECT_EQ(read_all(r, d), k) << where;
    expect_damage_at(d, m, k, where + " (file)");
    EXPECT_EQ(d->kind, p.value().damage->kind) << where;
  }
}

// A flipped byte in the header is always a header error (never frames from a bad header).
TEST(RecordingDamage, FlippedByteInTheHeaderIsAnError) {
  const MemRecording m = make_mem_recording(2);
  for (std::size_t pos = 0; pos < m.chunk_offsets.front(); ++pos) {
    auto bytes = m.bytes;
    bytes[pos] ^= 0x20;
    auto p = parse_recording(bytes, "mem");
    ASSERT_FALSE(p.is_ok()) << "byte " << pos;
    EXPECT_EQ(p.status().code(), StatusCode::kInputError);
    EXPECT_NE(p.status().message().find("byte offset"), std::string::npos) << p.status().message();
  }
}

void put_u32(std::vector<std::uint8_t>& b, std::size_t at, std::uint32_t v) {
  for (unsigned i = 0; i < 4; ++i) b[at + i] = static_cast<std::uint8_t>(v >> (8 * i));
}

TEST(RecordingDamage, EachKindIsNamedWithItsFrame) {
  const MemRecording m = make_mem_recording(3);
  const std::size_t c1 = m.chunk_offsets[1];
  const std::size_t c2 = m.chunk_offsets[2];
  struct Case {
    const char* name;
    std::size_t pos;
    DamageKind kind;
    std::size_t frame;
  };
  const Case cases[] = {
      {"chunk magic", c1, DamageKind::kBadChunkMagic, 1},
      {"chunk length", c1 + 4, DamageKind::kBadLength, 1},
      {"seq", c1 + 8, DamageKind::kCrcMismatch, 1},
      {"flags", c1 + 24, DamageKind::kBadFlags, 1},
      {"payload length", c1 + 28, DamageKind::kBadLength, 1},
      {"pose", c2 + 32, DamageKind::kCrcMismatch, 2},
      {"payload", c2 + 100, DamageKind::kCrcMismatch, 2},
      {"crc", m.chunk_offsets[3] - 1, DamageKind::kCrcMismatch, 2},
  };
  for (const Case& c : cases) {
    auto bytes = m.bytes;
    bytes[c.pos] ^= 0x5A;
    auto p = parse_recording(bytes, "mem");
    ASSERT_TRUE(p.is_ok());
    ASSERT_TRUE(p.value().damage.has_value()) << c.name;
    EXPECT_EQ(p.value().damage->kind, c.kind) << c.name << ": " << p.value().damage->message;
    EXPECT_EQ(p.value().damage->frame_index, c.frame) << c.name;
    EXPECT_NE(p.value().damage->message.find(damage_kind_name(c.kind)), std::string::npos);
  }
}

long max_rss_kib() {
  rusage u{};
  getrusage(RUSAGE_SELF, &u);
  return u.ru_maxrss;
}

// Length fields claiming gigabytes: the reader compares them with the header and the file
// size before allocating, so memory stays flat and the damage is reported.
// A chunk whose CRC is right but whose stored pose is NaN or not a rotation: the frames
// before it replay and the damage is named, instead of NaN poses reaching the evaluator.
TEST(RecordingDamage, InvalidStoredPoseEndsTheStream) {
  for (const bool nan_pose : {true, false}) {
    MemRecording m = make_mem_recording(3);
    Frame bad = m.frames[1];
    if (nan_pose) {
      bad.T_w_c_gt.translation().x() = std::numeric_limits<double>::quiet_NaN();
    } else {
      bad.T_w_c_gt.linear() *= 2.0;  // quaternion of a scaled matrix is not unit length
    }
    std::vector<std::uint8_t> bytes = encode_header(m.header);
    for (int k = 0; k < 3; ++k) {
      ASSERT_TRUE(encode_chunk(m.header, k == 1 ? bad : m.frames[k], bytes).is_ok());
    }
    auto parsed = parse_recording(bytes);
    ASSERT_TRUE(parsed.is_ok()) << parsed.status().message();
    EXPECT_EQ(parsed.value().frames.size(), 1U) << (nan_pose ? "NaN" : "scaled");
    ASSERT_TRUE(parsed.value().damage.has_value());
    EXPECT_EQ(parsed.value().damage->kind, DamageKind::kBadPose);
    EXPECT_EQ(parsed.value().damage->frame_index, 1U);
  }
}

TEST(RecordingDamage, AbsurdLengthsDoNotAllocate) {
  constexpr long kMaxGrowthKib = 64 * 1024;
  const long rss0 = max_rss_kib();
  // Chunk lengths inconsistent with the header.
  MemRecording m = make_mem_recording(2);
  auto bytes = m.bytes;
  put_u32(bytes, m.chunk_offsets[1] + 4, 0xFFFFFFF0U);
  put_u32(bytes, m.chunk_offsets[1] + 28, 0xFFFFFF00U);
  auto p = parse_recording(bytes, "mem");
  ASSERT_TRUE(p.is_ok());
  EXPECT_EQ(p.value().frames.size(), 1U);
  EXPECT_EQ(p.value().damage->kind, DamageKind::kBadLength);

  // A consistent header and chunk of 16384 x 16384 with depth (1.3 GB per frame) in a file
  // of a few hundred bytes: a truncated chunk, nothing allocated.
  const RecordingHeader big = make_header(static_cast<int>(kMaxImageDimension),
                                          static_cast<int>(kMaxImageDimension), true, true);
  std::vector<std::uint8_t> b = encode_header(big);
  const std::size_t at = b.size();
  b.resize(at + kChunkPrefixSize + kChunkPoseSize + 100, 0);
  const auto payload = static_cast<std::uint32_t>(frame_payload_size(big));
  put_u32(b, at, kChunkMagic);
  put_u32(b, at + 4, static_cast<std::uint32_t>(kChunkPrefixSize + kChunkPoseSize + payload + 4));
  put_u32(b, at + 24, kChunkFlagHasPose);
  put_u32(b, at + 28, payload);
  auto q = parse_recording(b, "mem");
  ASSERT_TRUE(q.is_ok()) << q.status().message();
  ASSERT_TRUE(q.value().damage.has_value());
  EXPECT_EQ(q.value().damage->kind, DamageKind::kTruncatedChunk);
  const std::string path = temp_path("absurd.merrec");
  write_bytes(path, b);
  RecordingReader r;
  ASSERT_TRUE(r.open(path).is_ok());
  std::optional<RecordingDamage> d;
  EXPECT_EQ(read_all(r, d), 0U);
  ASSERT_TRUE(d.has_value());
  EXPECT_EQ(d->kind, DamageKind::kTruncatedChunk);
  EXPECT_LT(max_rss_kib() - rss0, kMaxGrowthKib) << "the reader allocated for an absurd length";
}

// Garbage after valid frames (e.g. a preallocated tail of zeros after a power cut).
TEST(RecordingDamage, ZeroTailAfterFramesIsBadMagic) {
  MemRecording m = make_mem_recording(2);
  m.bytes.resize(m.bytes.size() + 4096, 0);
  auto p = parse_recording(m.bytes, "mem");
  ASSERT_TRUE(p.is_ok());
  EXPECT_EQ(p.value().frames.size(), 2U);
  ASSERT_TRUE(p.value().damage.has_value());
  EXPECT_EQ(p.value().damage->kind, DamageKind::kBadChunkMagic);
  EXPECT_EQ(p.value().damage->frame_index, 2U);
}

}  // namespace
}  // namespace mer::hal
