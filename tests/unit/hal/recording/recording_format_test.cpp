// The recording format: CRC32, bit-exact round trips through RecordingWriter and
// RecordingReader (synthetic frames with depth and ground truth), header validation errors.
#include <cstdlib>
#include <filesystem>
#include <string_view>

#include <gtest/gtest.h>

#include "hal/replay/recording.h"
#include "hal/synthetic/synthetic_camera.h"
#include "recording_test_util.h"

namespace mer::hal {
namespace {

using testing::make_frame;
using testing::make_header;
using testing::make_mem_recording;
using testing::read_all;
using testing::read_bytes;
using testing::same_bytes;
using testing::temp_path;
using testing::write_bytes;

std::span<const std::uint8_t> as_bytes(std::string_view s) {
  return {reinterpret_cast<const std::uint8_t*>(s.data()), s.size()};
}

TEST(Crc32, MatchesTheIeeeCheckValueAndIsIncremental) {
  EXPECT_EQ(crc32(as_bytes("123456789")), 0xCBF43926U);
  EXPECT_EQ(crc32(as_bytes("")), 0U);
  EXPECT_EQ(crc32(as_bytes("The quick brown fox jumps over the lazy dog")), 0x414FA339U);
  const std::string_view s = "123456789";
  for (std::size_t cut = 0; cut <= s.size(); ++cut) {
    EXPECT_EQ(crc32(as_bytes(s.substr(cut)), crc32(as_bytes(s.substr(0, cut)))), 0xCBF43926U)
        << "split at " << cut;
  }
}

// Records frames of the synthetic camera with the writer, reads them back: every pixel,
// depth value, seq, t_ns, stored pose, the intrinsics and the header fields identical.
void round_trip_synthetic(bool depth, int n) {
  SyntheticOptions o;
  o.width = 96;
  o.height = 64;
  o.render_depth = depth;
  o.num_frames = n;
  SyntheticCamera cam("room_orbit", o, false);
  ASSERT_TRUE(cam.open(4).is_ok());
  ASSERT_TRUE(cam.start().is_ok());

  RecordingHeader h;
  h.description = cam.describe();
  h.intrinsics = cam.intrinsics();
  h.nominal_fps = cam.capabilities().nominal_fps;
  h.has_depth = depth;
  h.has_ground_truth = true;
  const std::string path = temp_path(depth ? "roundtrip_depth.merrec" : "roundtrip.merrec");
  RecordingWriter w;
  ASSERT_TRUE(w.open(path, h).is_ok());
  std::vector<Frame> sent;
  FrameHandle fh;
  while (cam.acquire(fh, 0) == AcquireStatus::kFrame) {
    ASSERT_TRUE(w.append(*fh).is_ok());
    Frame copy;
    copy.seq = fh->seq;
    copy.t_ns = fh->t_ns;
    copy.gray = fh->gray.clone();
    if (depth) copy.depth = fh->depth.clone();
    copy.has_ground_truth = fh->has_ground_truth;
    copy.T_w_c_gt = fh->T_w_c_gt;
    sent.push_back(std::move(copy));
    fh.reset();
  }
  ASSERT_EQ(sent.size(), static_cast<std::size_t>(n));
  EXPECT_EQ(w.frames_written(), static_cast<std::uint64_t>(n));
  ASSERT_TRUE(w.close().is_ok());
  EXPECT_EQ(w.bytes_written(), std::filesystem::file_size(path));

  RecordingReader r;
  const Status s = r.open(path);
  ASSERT_TRUE(s.is_ok()) << s.message();
  const RecordingHeader& g = r.header();
  EXPECT_EQ(g.version, kRecordingVersion);
  EXPECT_EQ(g.description, h.description);
  EXPECT_EQ(g.pixel_format, RecPixelFormat::kGrey8);
  EXPECT_EQ(g.nominal_fps, h.nominal_fps);
  EXPECT_EQ(g.has_depth, depth);
  EXPECT_TRUE(g.has_ground_truth);
  const CameraIntrinsics& a = g.intrinsics;
  const CameraIntrinsics& b = h.intrinsics;
  EXPECT_EQ(a.width, b.width);
  EXPECT_EQ(a.height, b.height);
  EXPECT_EQ(a.fx, b.fx);
  EXPECT_EQ(a.fy, b.fy);
  EXPECT_EQ(a.cx, b.cx);
  EXPECT_EQ(a.cy, b.cy);
  EXPECT_EQ(a.dist, b.dist);
  EXPECT_EQ(a.focal_known, b.focal_known);
  ASSERT_EQ(r.frame_count(), sent.size());

  Frame f;
  for (std::size_t i = 0; i < sent.size(); ++i) {
    RecordedFrameInfo info;
    ASSERT_EQ(r.read_frame(i, f, &info), ReadStatus::kFrame) << i;
    EXPECT_EQ(f.seq, sent[i].seq);
    EXPECT_EQ(f.t_ns, sent[i].t_ns);
    EXPECT_TRUE(same_bytes(f.gray, sent[i].gray)) << "frame " << i << " pixels differ";
    if (depth) {
      EXPECT_TRUE(same_bytes(f.depth, sent[i].depth)) << "frame " << i << " depth differs";
    }
    EXPECT_TRUE(f.has_ground_truth);
    ASSERT_TRUE(info.has_pose);
    EXPECT_EQ(info.pose, stored_from_pose(sent[i].T_w_c_gt)) << "stored pose must be bit-exact";
    EXPECT_TRUE(f.T_w_c_gt.isApprox(sent[i].T_w_c_gt, 1e-12)) << i;
  }
  EXPECT_EQ(r.read_frame(sent.size(), f), ReadStatus::kEnd);
  EXPECT_FALSE(r.damage().has_value());
  EXPECT_EQ(r.ground_truth().size(), sent.size());

  // The in-memory parser sees the same frames.
  const auto bytes = read_bytes(path);
  auto p = parse_recording(bytes, path);
  ASSERT_TRUE(p.is_ok()) << p.status().message();
  EXPECT_EQ(p.value().frames.size(), sent.size());
  EXPECT_FALSE(p.value().damage.has_value());
}

TEST(RecordingRoundTrip, SyntheticFramesWithDepthAreBitExact) {
  round_trip_synthetic(true, 12);
}

TEST(RecordingRoundTrip, SyntheticFramesWithoutDepthAreBitExact) {
  round_trip_synthetic(false, 20);
}

TEST(RecordingRoundTrip, FramesWithoutGroundTruthCarryNoPose) {
  const std::string path = temp_path("nogt.merrec");
  RecordingHeader h = make_header(10, 4, false, true);
  h.intrinsics.focal_known = false;
  RecordingWriter w;
  ASSERT_TRUE(w.open(path, h).is_ok());
  Frame with = make_frame(0, 10, 4, false, true);
  Frame without = make_frame(1, 10, 4, false, false);
  ASSERT_TRUE(w.append(with).is_ok());
  ASSERT_TRUE(w.append(without).is_ok());
  ASSERT_TRUE(w.close().is_ok());
  RecordingReader r;
  ASSERT_TRUE(r.open(path).is_ok());
  EXPECT_FALSE(r.header().intrinsics.focal_known);
  Frame f;
  RecordedFrameInfo info;
  ASSERT_EQ(r.read_frame(0, f, &info), ReadStatus::kFrame);
  EXPECT_TRUE(info.has_pose);
  EXPECT_TRUE(f.has_ground_truth);
  ASSERT_EQ(r.read_frame(1, f, &info), ReadStatus::kFrame);
  EXPECT_FALSE(info.has_pose);
  EXPECT_FALSE(f.has_ground_truth);
  EXPECT_TRUE(same_bytes(f.gray, without.gray));
  EXPECT_EQ(r.ground_truth().size(), 1U);
}

TEST(RecordingRoundTrip, HeaderOnlyRecordingHasNoFramesAndNoDamage) {
  const std::string path = temp_path("empty_rec.merrec");
  RecordingWriter w;
  ASSERT_TRUE(w.open(path, make_header(8, 6, true, true)).is_ok());
  ASSERT_TRUE(w.close().is_ok());
  RecordingReader r;
  ASSERT_TRUE(r.open(path).is_ok());
  EXPECT_EQ(r.frame_count(), 0U);
  Frame f;
  EXPECT_EQ(r.read_frame(0, f), ReadStatus::kEnd);
  EXPECT_FALSE(r.damage().has_value());
}

TEST(RecordingRoundTrip, LongDescriptionIsTruncatedToTheLimit) {
  RecordingHeader h = make_header(8, 6, false, false);
  h.description.assign(kMaxDescriptionLength + 100, 'x');
  const auto bytes = encode_header(h);
  EXPECT_EQ(bytes.size(), kMaxHeaderSize);
  auto p = parse_recording(bytes);
  ASSERT_TRUE(p.is_ok()) << p.status().message();
  EXPECT_EQ(p.value().header.description.size(), kMaxDescriptionLength);
}

TEST(RecordingWriter, RejectsFramesThatDoNotMatchTheHeader) {
  const std::string path = temp_path("mismatch.merrec");
  RecordingWriter w;
  ASSERT_TRUE(w.open(path, make_header(8, 6, true, true)).is_ok());
  Frame wrong_size = make_frame(0, 9, 6, true, true);
  Status s = w.append(wrong_size);
  EXPECT_FALSE(s.is_ok());
  EXPECT_NE(s.message().find("seq 1"), std::string::npos) << s.message();
  Frame no_depth = make_frame(0, 8, 6, false, true);
  EXPECT_FALSE(w.append(no_depth).is_ok());
  EXPECT_EQ(w.frames_written(), 0U);
  ASSERT_TRUE(w.close().is_ok());
  // Nothing but the header was written: the file is a valid empty recording.
  RecordingReader r;
  ASSERT_TRUE(r.open(path).is_ok());
  EXPECT_EQ(r.frame_count(), 0U);
  EXPECT_FALSE(r.damage().has_value());
}

TEST(RecordingWriter, UncreatableFileAndBadHeaderAreErrors) {
  RecordingWriter w;
  Status s = w.open("/proc/mer_no_such_dir/x.merrec", make_header(8, 6, false, false));
  EXPECT_FALSE(s.is_ok());
  EXPECT_NE(s.message().find("/proc/mer_no_such_dir/x.merrec"), std::string::npos);
  s = w.open(temp_path("bad.merrec"), make_header(0, 6, false, false));
  EXPECT_FALSE(s.is_ok());
  EXPECT_FALSE(w.is_open());
}

// ---- Header errors -----------------------------------------------------------------------

/// Rewrites the header CRC of `bytes` after a deliberate field change.
void fix_header_crc(std::vector<std::uint8_t>& bytes) {
  const std::size_t n = encode_header(make_header(8, 6, true, true)).size();
  const std::uint32_t c = crc32(std::span<const std::uint8_t>(bytes).first(n - kChunkCrcSize));
  for (unsigned i = 0; i < 4; ++i) bytes[n - 4 + i] = static_cast<std::uint8_t>(c >> (8 * i));
}

Status open_bytes(const std::string& name, std::span<const std::uint8_t> bytes) {
  const std::string path = temp_path(name);
  write_bytes(path, bytes);
  RecordingReader r;
  return r.open(path);
}

void expect_header_error(const std::vector<std::uint8_t>& bytes, const std::string& name,
                         std::string_view words) {
  const std::string path = temp_path(name);
  const Status s = open_bytes(name, bytes);
  ASSERT_FALSE(s.is_ok()) << name;
  EXPECT_EQ(s.code(), StatusCode::kInputError) << name;
  EXPECT_NE(s.message().find(path), std::string::npos) << s.message();
  EXPECT_NE(s.message().find(words), std::string::npos) << s.message();
  auto p = parse_recording(bytes, name);
  ASSERT_FALSE(p.is_ok()) << name;
  EXPECT_NE(p.status().message().find(words), std::string::npos) << p.status().message();
}

TEST(RecordingHeaderErrors, EmptyFileWrongMagicFutureVersionAndCrcAreClearErrors) {
  expect_header_error({}, "empty.merrec", "empty file");
  const auto good = make_mem_recording(1).bytes;

  auto bad_magic = good;
  bad_magic[3] = 'X';
  expect_header_error(bad_magic, "magic.merrec", "bad magic");
  expect_header_error(std::vector<std::uint8_t>{'P', 'N', 'G'}, "tiny.merrec", "bad magic");

  auto future = good;
  future[8] = 2;
  fix_header_crc(future);
  expect_header_error(future, "future.merrec", "newer than this reader");
  expect_header_error(future, "future2.merrec", "byte offset 8");

  auto zero_version = good;
  zero_version[8] = 0;
  fix_header_crc(zero_version);
  expect_header_error(zero_version, "v0.merrec", "unsupported format version 0");

  auto crc = good;
  crc[40] ^= 0x01;  // fx
  expect_header_error(crc, "crc.merrec", "header CRC mismatch");

  auto yuyv = good;
  yuyv[20] = 2;
  fix_header_crc(yuyv);
  expect_header_error(yuyv, "yuyv.merrec", "YUYV");

  auto huge = good;
  huge[24 + 3] = 0x7F;  // width ~2^31
  fix_header_crc(huge);
  expect_header_error(huge, "huge.merrec", "out of range");

  auto desc = good;
  desc[104 + 3] = 0x10;  // description length 2^28
  expect_header_error(desc, "desc.merrec", "description length");

  auto header_len = good;
  header_len[12] ^= 0x04;
  expect_header_error(header_len, "hlen.merrec", "header length");

  auto flags = good;
  flags[16 + 2] = 0x01;  // an unknown flag bit
  fix_header_crc(flags);
  expect_header_error(flags, "flags.merrec", "unknown header flags");
}

TEST(RecordingHeaderErrors, MissingFileAndDirectoryAreErrors) {
  RecordingReader r;
  Status s = r.open("/nonexistent/mer.merrec");
  EXPECT_EQ(s.code(), StatusCode::kInputError);
  EXPECT_NE(s.message().find("/nonexistent/mer.merrec"), std::string::npos);
  s = r.open(std::filesystem::temp_directory_path().string());
  EXPECT_EQ(s.code(), StatusCode::kInputError);
  EXPECT_NE(s.message().find("not a regular file"), std::string::npos) << s.message();
}

// The seed corpus of the fuzz targets (tests/fuzz/corpus/recording) must stay readable by
// the current format: its valid_* files parse without damage.
TEST(RecordingCorpus, CommittedValidSeedsParseCleanly) {
  const char* src = std::getenv("MER_SOURCE_DIR");
  if (src == nullptr) GTEST_SKIP() << "MER_SOURCE_DIR not set";
  const auto dir = std::filesystem::path(src) / "tests/fuzz/corpus/recording";
  if (!std::filesystem::is_directory(dir)) GTEST_SKIP() << dir << " absent";
  int valid = 0;
  std::size_t frames = 0;
  for (const auto& e : std::filesystem::directory_iterator(dir)) {
    if (e.path().filename().string().rfind("valid_", 0) != 0) continue;
    ++valid;
    const auto bytes = read_bytes(e.path().string());
    auto p = parse_recording(bytes, e.path().string());
    ASSERT_TRUE(p.is_ok()) << p.status().message();
    EXPECT_FALSE(p.value().damage.has_value()) << p.value().damage->message;
    frames += p.value().frames.size();
  }
  EXPECT_GT(valid, 0) << "no valid_* seeds in " << dir;
  EXPECT_GT(frames, 0U) << "the valid seeds hold no frame";
}

}  // namespace
}  // namespace mer::hal
