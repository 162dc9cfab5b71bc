// mer_record end to end with the real binary: a 30-frame recording replays 30 frames
// bit-exactly against the synthetic camera; SIGINT stops cleanly with the file matching the
// printed summary; SIGKILL leaves a file replayable up to the last complete chunk; usage
// and input errors give the documented exit codes; mer_slam replays the file (once rec: is
// wired into the camera factory).
#include <fcntl.h>
#include <sys/stat.h>
#include <sys/wait.h>
#include <unistd.h>

#include <chrono>
#include <csignal>
#include <filesystem>
#include <fstream>
#include <regex>
#include <thread>

#include <gtest/gtest.h>

#include "hal/replay/recording.h"
#include "hal/synthetic/synthetic_camera.h"
#include "recording_test_util.h"
#include "support/run_command.h"

namespace mer::hal {
namespace {

using mer::testing::quote;
using mer::testing::read_text;
using mer::testing::run_command;

const std::string kRecord = MER_RECORD_EXE;
const std::string kSlam = MER_SLAM_EXE;

std::string fresh(const std::string& name) {
  const auto p = std::filesystem::temp_directory_path() / ("mer_rec_e2e_" + name);
  std::filesystem::remove_all(p);
  return p.string();
}

/// Removes a (large) recording when the test ends, pass or fail.
struct RemoveAtExit {
  std::string path;
  ~RemoveAtExit() {
    std::error_code ec;
    std::filesystem::remove(path, ec);
  }
};

/// The value of "  key: value" in mer_record's summary, or -1.
long summary_value(const std::string& text, const std::string& key) {
  const std::regex re("\\b" + key + ":\\s+(\\d+)");
  std::smatch m;
  if (!std::regex_search(text, m, re)) return -1;
  return std::stol(m[1].str());
}

/// A small, fast configuration for the long-running recordings (320x240, no depth).
std::string small_config() {
  const std::string path = fresh("small.yaml");
  std::ofstream(path) << "camera:\n  synthetic:\n    width: 320\n    height: 240\n"
                         "    render_depth: false\n    num_frames: 100000\n";
  return path;
}

TEST(MerRecordE2E, ThirtyFramesReplayBitExact) {
  const std::string out = fresh("30.merrec");
  const RemoveAtExit cleanup_out{out};
  const auto r = run_command(
      quote(kRecord) + " --input synthetic:room_orbit --max-frames 30 --output " + quote(out));
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_EQ(summary_value(r.output, "frames_recorded"), 30) << r.output;
  EXPECT_EQ(summary_value(r.output, "frames_dropped"), 0) << r.output;
  EXPECT_NE(r.output.find("end_reason:      max_frames"), std::string::npos) << r.output;

  RecordingReader reader;
  const Status s = reader.open(out);
  ASSERT_TRUE(s.is_ok()) << s.message();
  EXPECT_TRUE(reader.header().has_depth);
  EXPECT_TRUE(reader.header().has_ground_truth);
  EXPECT_NE(reader.header().description.find("synthetic:room_orbit"), std::string::npos);
  ASSERT_EQ(reader.frame_count(), 30U);

  // The synthetic camera is deterministic: re-render and compare every frame bit for bit.
  SyntheticCamera cam("room_orbit", SyntheticOptions{}, false);
  ASSERT_TRUE(cam.open(2).is_ok());
  ASSERT_TRUE(cam.start().is_ok());
  Frame f;
  for (std::size_t i = 0; i < 30; ++i) {
    ASSERT_EQ(reader.read_frame(i, f), ReadStatus::kFrame) << i;
    FrameHandle ref;
    ASSERT_EQ(cam.acquire(ref, 0), AcquireStatus::kFrame);
    EXPECT_EQ(f.seq, ref->seq);
    EXPECT_EQ(f.t_ns, ref->t_ns);
    EXPECT_TRUE(testing::same_bytes(f.gray, ref->gray)) << "frame " << i;
    EXPECT_TRUE(testing::same_bytes(f.depth, ref->depth)) << "frame " << i;
    EXPECT_TRUE(f.T_w_c_gt.isApprox(ref->T_w_c_gt, 1e-12));
  }
  EXPECT_EQ(reader.read_frame(30, f), ReadStatus::kEnd);
  EXPECT_FALSE(reader.damage().has_value());
}

/// Starts mer_record in the background with stdout to `stdout_path`.
pid_t spawn_record(const std::string& out, const std::string& config,
                   const std::string& stdout_path) {
  const pid_t pid = fork();
  if (pid == 0) {
    const int fd = ::open(stdout_path.c_str(), O_WRONLY | O_CREAT | O_TRUNC, 0644);
    ::dup2(fd, 1);
    ::execl(kRecord.c_str(), kRecord.c_str(), "--input", "synthetic:room_orbit", "--config",
            config.c_str(), "--output", out.c_str(), static_cast<char*>(nullptr));
    _exit(127);
  }
  return pid;
}

// Waits (up to a generous deadline, for loaded CI machines) until `path` exceeds `bytes`.
bool wait_for_file_size(const std::string& path, std::uint64_t bytes) {
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(60);
  while (std::chrono::steady_clock::now() < deadline) {
    struct stat st {};
    if (::stat(path.c_str(), &st) == 0 && static_cast<std::uint64_t>(st.st_size) > bytes) {
      return true;
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  }
  return false;
}

TEST(MerRecordE2E, SigintStopsCleanlyAndTheFileMatchesTheSummary) {
  const std::string out = fresh("sigint.merrec");
  const RemoveAtExit cleanup_out{out};
  const std::string log = fresh("sigint.out");
  const pid_t pid = spawn_record(out, small_config(), log);
  ASSERT_GT(pid, 0);
  // Some frames on disk first (a 320x240 chunk is ~77 KB: 800 KB is about 10 frames).
  EXPECT_TRUE(wait_for_file_size(out, 800'000)) << "mer_record wrote nothing in 60 s";
  ASSERT_EQ(::kill(pid, SIGINT), 0);
  int status = 0;
  ASSERT_EQ(::waitpid(pid, &status, 0), pid);
  ASSERT_TRUE(WIFEXITED(status));
  EXPECT_EQ(WEXITSTATUS(status), 0);
  const std::string text = read_text(log);
  EXPECT_NE(text.find("end_reason:      signal"), std::string::npos) << text;
  const long recorded = summary_value(text, "frames_recorded");
  EXPECT_GT(recorded, 5) << text;
  EXPECT_LT(recorded, 1000) << text;
  EXPECT_EQ(summary_value(text, "bytes"), static_cast<long>(std::filesystem::file_size(out)));

  RecordingReader reader;
  ASSERT_TRUE(reader.open(out).is_ok());
  std::size_t n = 0;
  Frame f;
  while (reader.read_frame(n, f) == ReadStatus::kFrame) ++n;
  EXPECT_EQ(static_cast<long>(n), recorded);
  EXPECT_FALSE(reader.damage().has_value()) << reader.damage()->message;
}

TEST(MerRecordE2E, SigkillLeavesAFileReplayableUpToTheLastCompleteChunk) {
  const std::string out = fresh("sigkill.merrec");
  const RemoveAtExit cleanup_out{out};
  const pid_t pid = spawn_record(out, small_config(), "/dev/null");
  ASSERT_GT(pid, 0);
  EXPECT_TRUE(wait_for_file_size(out, 800'000)) << "mer_record wrote nothing in 60 s";
  // Everything written before this size was handed to the kernel: it must survive.
  struct stat st {};
  ASSERT_EQ(::stat(out.c_str(), &st), 0);
  const auto size_before_kill = static_cast<std::uint64_t>(st.st_size);
  ASSERT_EQ(::kill(pid, SIGKILL), 0);
  int status = 0;
  ASSERT_EQ(::waitpid(pid, &status, 0), pid);
  ASSERT_TRUE(WIFSIGNALED(status));

  RecordingReader reader;
  const Status s = reader.open(out);
  ASSERT_TRUE(s.is_ok()) << s.message();
  const std::uint64_t header = encode_header(reader.header()).size();
  const std::uint64_t chunk =
      kChunkPrefixSize + kChunkPoseSize + frame_payload_size(reader.header()) + kChunkCrcSize;
  const std::uint64_t flushed = (size_before_kill - header) / chunk;
  EXPECT_GT(flushed, 0U) << "no complete frame before the kill";
  std::size_t n = 0;
  Frame f;
  while (reader.read_frame(n, f) == ReadStatus::kFrame) ++n;
  EXPECT_GE(n, flushed) << "frames written before the kill were lost";
  EXPECT_EQ(n, reader.frame_count());
  if (reader.damage()) {
    EXPECT_EQ(reader.damage()->kind, DamageKind::kTruncatedChunk) << reader.damage()->message;
    EXPECT_EQ(reader.damage()->frame_index, n);
  }
}

TEST(MerRecordE2E, DurationStopsTheRecording) {
  const std::string out = fresh("duration.merrec");
  const RemoveAtExit cleanup_out{out};
  const auto r =
      run_command(quote(kRecord) + " --input synthetic:room_orbit --duration 0.5 --config " +
                  quote(small_config()) + " --output " + quote(out));
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_NE(r.output.find("end_reason:      duration"), std::string::npos) << r.output;
  const long n = summary_value(r.output, "frames_recorded");
  EXPECT_GT(n, 3) << r.output;  // 30 Hz for 0.5 s
  EXPECT_LT(n, 30) << r.output;
}

TEST(MerRecordE2E, UsageAndInputErrorsHaveTheDocumentedExitCodes) {
  const std::string out = fresh("err.merrec");
  EXPECT_EQ(run_command(quote(kRecord)).exit_code, 2);
  EXPECT_EQ(run_command(quote(kRecord) + " --input synthetic:room_orbit").exit_code, 2);
  EXPECT_EQ(run_command(quote(kRecord) + " --input synthetic:room_orbit --output " + quote(out) +
                        " --max-frames -3")
                .exit_code,
            2);
  EXPECT_EQ(run_command(quote(kRecord) + " --bogus").exit_code, 2);
  EXPECT_EQ(run_command(quote(kRecord) + " --input nope:x --output " + quote(out)).exit_code, 2);
  const auto unwritable = run_command(quote(kRecord) +
                                      " --input synthetic:room_orbit --max-frames 1 --output "
                                      "/proc/mer_cannot_write/x.merrec");
  EXPECT_EQ(unwritable.exit_code, 2) << unwritable.output;
  EXPECT_NE(unwritable.output.find("/proc/mer_cannot_write/x.merrec"), std::string::npos);
  const auto scenario =
      run_command(quote(kRecord) + " --input synthetic:no_such_scene --output " + quote(out));
  EXPECT_EQ(scenario.exit_code, 3) << scenario.output;
  const std::string bad_config = fresh("bad.yaml");
  std::ofstream(bad_config) << "camera:\n  pool_sizee: 3\n";
  const auto cfg = run_command(quote(kRecord) + " --input synthetic:room_orbit --config " +
                               quote(bad_config) + " --output " + quote(out));
  EXPECT_EQ(cfg.exit_code, 2) << cfg.output;
  EXPECT_NE(cfg.output.find("pool_sizee"), std::string::npos) << cfg.output;
  const auto help = run_command(quote(kRecord) + " --help");
  EXPECT_EQ(help.exit_code, 0);
  EXPECT_NE(help.output.find("--max-frames"), std::string::npos);
}

// mer_slam --input rec:FILE replays the recording; a truncated one replays its intact
// frames and summary.json reports the damage.
TEST(MerRecordE2E, MerSlamReplaysTheRecording) {
  const std::string rec = fresh("slam.merrec");
  const RemoveAtExit cleanup_rec{rec};
  const auto r = run_command(quote(kRecord) + " --input synthetic:room_orbit --max-frames 20 " +
                             "--no-depth --quiet --output " + quote(rec));
  ASSERT_EQ(r.exit_code, 0) << r.output;
  const std::string dir = fresh("slam_out");
  const auto s = run_command(quote(kSlam) + " --lockstep --quiet --input rec:" + quote(rec) +
                             " --output " + quote(dir));
  ASSERT_EQ(s.exit_code, 0) << s.output;
  EXPECT_EQ(mer::testing::count_lines(dir + "/frames.csv"), 21);
  EXPECT_NE(mer::testing::read_text(dir + "/summary.json").find("\"damage\": \"\""),
            std::string::npos)
      << "an intact recording reports no damage";

  // Cut into the last chunk: 19 frames replay and the damage is reported, exit 0.
  std::filesystem::resize_file(rec, std::filesystem::file_size(rec) - 100);
  const std::string dir2 = fresh("slam_out_cut");
  const auto c = run_command(quote(kSlam) + " --lockstep --quiet --input rec:" + quote(rec) +
                             " --output " + quote(dir2));
  ASSERT_EQ(c.exit_code, 0) << c.output;
  EXPECT_EQ(mer::testing::count_lines(dir2 + "/frames.csv"), 20);
  const std::string summary = mer::testing::read_text(dir2 + "/summary.json");
  EXPECT_EQ(summary.find("\"damage\": \"\""), std::string::npos) << summary;
  EXPECT_NE(summary.find("\"damage\": \""), std::string::npos) << summary;
}

}  // namespace
}  // namespace mer::hal
