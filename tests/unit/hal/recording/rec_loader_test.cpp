// RecLoader (`rec:FILE` as a FrameLoader): frames, intrinsics and ground truth from the
// file; kEndOfStream at the clean end and at the first damage, reported once.
#include "hal/replay/rec_loader.h"

#include <cstring>

#include <gtest/gtest.h>

#include "hal/replay/replay_camera.h"
#include "platform/log_ring.h"
#include "recording_test_util.h"

namespace mer::hal {
namespace {

using testing::make_mem_recording;
using testing::MemRecording;
using testing::same_bytes;
using testing::temp_path;
using testing::write_bytes;

/// Drains the default log ring; returns how many records contain `text`.
int drain_log_count(const char* text) {
  int n = 0;
  platform::default_log().drain([&](const platform::LogRecord& r) {
    if (std::strstr(r.text, text) != nullptr) ++n;
  });
  return n;
}

TEST(RecLoader, ReplaysFramesIntrinsicsAndGroundTruth) {
  const MemRecording m = make_mem_recording(4);
  const std::string path = temp_path("loader.merrec");
  write_bytes(path, m.bytes);
  auto made = make_rec_loader(path);
  ASSERT_TRUE(made.is_ok());
  FrameLoader& loader = *made.value();
  ASSERT_TRUE(loader.open().is_ok());
  EXPECT_EQ(loader.size(), 4U);
  EXPECT_TRUE(loader.has_depth());
  EXPECT_TRUE(loader.has_ground_truth());
  EXPECT_EQ(loader.nominal_fps(), 30.0);
  EXPECT_EQ(loader.intrinsics().width, 8);
  EXPECT_EQ(loader.intrinsics().fy, m.header.intrinsics.fy);
  EXPECT_EQ(loader.intrinsics().dist, m.header.intrinsics.dist);
  EXPECT_NE(loader.describe().find("rec:" + path), std::string::npos) << loader.describe();
  EXPECT_NE(loader.describe().find("4 frames"), std::string::npos) << loader.describe();
  ASSERT_EQ(loader.ground_truth().poses.size(), 4U);
  EXPECT_EQ(loader.ground_truth().poses[2].t_ns, m.frames[2].t_ns);
  EXPECT_TRUE(loader.ground_truth().poses[2].T_w_c.isApprox(m.frames[2].T_w_c_gt, 1e-12));

  Frame f;
  f.gray = cv::Mat(6, 8, CV_8UC1);  // as ReplayCamera sizes pool buffers
  f.depth = cv::Mat(6, 8, CV_32FC1);
  const std::uint8_t* buffer = f.gray.data;
  Status st;
  for (std::size_t i = 0; i < 4; ++i) {
    ASSERT_EQ(loader.load(i, f, st), LoadStatus::kOk) << st.message();
    EXPECT_EQ(f.gray.data, buffer) << "load() must decode into the slot's buffer";
    EXPECT_TRUE(same_bytes(f.gray, m.frames[i].gray));
    EXPECT_TRUE(same_bytes(f.depth, m.frames[i].depth));
    EXPECT_EQ(f.seq, m.frames[i].seq);
    EXPECT_EQ(f.t_ns, m.frames[i].t_ns);
    EXPECT_TRUE(f.has_ground_truth);
  }
  EXPECT_EQ(loader.load(4, f, st), LoadStatus::kEndOfStream);
  EXPECT_EQ(st.code(), StatusCode::kEndOfStream);
  EXPECT_FALSE(static_cast<RecLoader&>(loader).damage().has_value());
}

TEST(RecLoader, StopsAtTheFirstDamageAndReportsItOnce) {
  MemRecording m = make_mem_recording(5);
  m.bytes[m.chunk_offsets[3] + 200] ^= 0x01;  // payload of frame 3
  const std::string path = temp_path("loader_damaged.merrec");
  write_bytes(path, m.bytes);
  RecLoader loader(path);
  ASSERT_TRUE(loader.open().is_ok());
  EXPECT_EQ(loader.size(), 5U) << "structure intact: the CRC is checked when loading";
  drain_log_count("");  // start from an empty log
  Frame f;
  Status st;
  for (std::size_t i = 0; i < 3; ++i) ASSERT_EQ(loader.load(i, f, st), LoadStatus::kOk);
  EXPECT_EQ(loader.load(3, f, st), LoadStatus::kEndOfStream);
  EXPECT_EQ(st.code(), StatusCode::kInputError);
  EXPECT_NE(st.message().find("frame 3"), std::string::npos) << st.message();
  EXPECT_NE(st.message().find("CRC mismatch"), std::string::npos) << st.message();
  EXPECT_EQ(loader.load(4, f, st), LoadStatus::kEndOfStream);
  EXPECT_EQ(loader.load(3, f, st), LoadStatus::kEndOfStream);
  ASSERT_TRUE(loader.damage().has_value());
  EXPECT_EQ(loader.damage()->frame_index, 3U);
  EXPECT_EQ(loader.damage()->offset, m.chunk_offsets[3]);
  EXPECT_EQ(loader.damage()->kind, DamageKind::kCrcMismatch);
  EXPECT_EQ(drain_log_count("recording damaged at frame 3"), 1) << "logged exactly once";
  // Earlier frames stay readable (ReplayCamera may restart).
  EXPECT_EQ(loader.load(1, f, st), LoadStatus::kOk);
}

TEST(RecLoader, TruncatedFileReplaysTheCompleteFrames) {
  const MemRecording m = make_mem_recording(4);
  const std::string path = temp_path("loader_cut.merrec");
  write_bytes(path, std::span(m.bytes).first(m.chunk_offsets[3] - 10));
  RecLoader loader(path);
  ASSERT_TRUE(loader.open().is_ok());
  EXPECT_EQ(loader.size(), 2U);
  ASSERT_TRUE(loader.damage().has_value()) << "the scan finds the truncated chunk at open()";
  EXPECT_EQ(loader.damage()->kind, DamageKind::kTruncatedChunk);
  Frame f;
  Status st;
  EXPECT_EQ(loader.load(0, f, st), LoadStatus::kOk);
  EXPECT_EQ(loader.load(1, f, st), LoadStatus::kOk);
  EXPECT_EQ(loader.load(2, f, st), LoadStatus::kEndOfStream);
  EXPECT_NE(st.message().find("truncated chunk"), std::string::npos) << st.message();
  EXPECT_EQ(loader.ground_truth().poses.size(), 2U);
}

// What `rec:FILE` will be: a ReplayCamera over a RecLoader. A damaged file hands out its
// intact frames, then ends the stream (not an error).
TEST(RecLoader, ReplayCameraDeliversTheIntactFramesThenEnds) {
  constexpr std::int64_t kTimeoutNs = 2'000'000'000;
  constexpr std::size_t kPool = 8;
  MemRecording m = make_mem_recording(6);
  m.bytes[m.chunk_offsets[4] + 150] ^= 0x40;  // frame 4 damaged
  const std::string path = temp_path("replay_cam.merrec");
  write_bytes(path, m.bytes);
  auto loader = make_rec_loader(path);
  ASSERT_TRUE(loader.is_ok());
  ReplayCamera cam(std::move(loader).value(), ReplayOptions{}, false);
  const Status s = cam.open(kPool);
  ASSERT_TRUE(s.is_ok()) << s.message();
  EXPECT_TRUE(cam.capabilities().has_depth);
  EXPECT_TRUE(cam.capabilities().has_ground_truth);
  ASSERT_TRUE(cam.start().is_ok());
  std::size_t n = 0;
  for (;;) {
    FrameHandle f;
    const AcquireStatus a = cam.acquire(f, kTimeoutNs);
    if (a != AcquireStatus::kFrame) {
      EXPECT_EQ(a, AcquireStatus::kEndOfStream);
      break;
    }
    ASSERT_LT(n, 4U);
    EXPECT_TRUE(same_bytes(f->gray, m.frames[n].gray)) << n;
    EXPECT_TRUE(same_bytes(f->depth, m.frames[n].depth)) << n;
    EXPECT_EQ(f->t_ns, m.frames[n].t_ns);
    ++n;
  }
  EXPECT_EQ(n, 4U);
  cam.stop();
}

TEST(RecLoader, BadPathsAreErrors) {
  EXPECT_FALSE(make_rec_loader("").is_ok());
  RecLoader missing("/nonexistent/x.merrec");
  const Status s = missing.open();
  EXPECT_EQ(s.code(), StatusCode::kInputError);
  EXPECT_NE(s.message().find("/nonexistent/x.merrec"), std::string::npos);
  const std::string not_rec = temp_path("not_rec.merrec");
  write_bytes(not_rec, std::vector<std::uint8_t>(64, 'a'));
  RecLoader bad(not_rec);
  const Status b = bad.open();
  EXPECT_EQ(b.code(), StatusCode::kInputError);
  EXPECT_NE(b.message().find("bad magic"), std::string::npos) << b.message();
}

}  // namespace
}  // namespace mer::hal
