#include "pipeline/output_stage.h"

#include <array>
#include <cerrno>
#include <cstring>
#include <filesystem>

#include "frontend/keyframe_policy.h"
#include "platform/clock.h"

namespace mer::pipeline {
namespace {
constexpr std::size_t kFileBuffer = 1 << 16;  // stdio buffer per output file
constexpr std::size_t kLineBuffer = 512;      // longest line we format
constexpr double kNsToMs = 1e-6;
}  // namespace

int format_seconds(char* buf, std::size_t size, std::int64_t t_ns) {
  const bool negative = t_ns < 0;
  const auto mag =
      negative ? -static_cast<unsigned long long>(t_ns) : static_cast<unsigned long long>(t_ns);
  return std::snprintf(buf, size, "%s%llu.%09llu", negative ? "-" : "", mag / 1'000'000'000ULL,
                       mag % 1'000'000'000ULL);
}

namespace {
// `<prefix> tx ty tz qx qy qz qw\n`, fixed formatting: deterministic; positions and
// quaternions to 1e-9.
int format_pose_line(char* buf, std::size_t size, const char* prefix, const SE3d& T) {
  const Eigen::Quaterniond q(T.linear());
  const Eigen::Vector3d& t = T.translation();
  return std::snprintf(buf, size, "%s %.9f %.9f %.9f %.9f %.9f %.9f %.9f\n", prefix, t.x(), t.y(),
                       t.z(), q.x(), q.y(), q.z(), q.w());
}
}  // namespace

int format_tum_line(char* buf, std::size_t size, std::int64_t t_ns, const SE3d& T_w_c) {
  char stamp[32];
  format_seconds(stamp, sizeof stamp, t_ns);
  return format_pose_line(buf, size, stamp, T_w_c);
}

int format_anchor_line(char* buf, std::size_t size, std::int64_t t_ns,
                       const std::int64_t* anchor_t_ns, std::uint16_t segment, const SE3d& T) {
  char stamps[80];
  int n = format_seconds(stamps, sizeof stamps, t_ns);
  if (anchor_t_ns == nullptr) {
    n += std::snprintf(stamps + n, sizeof stamps - static_cast<std::size_t>(n), " -");
  } else {
    stamps[n] = ' ';
    n += 1 + format_seconds(stamps + n + 1, sizeof stamps - static_cast<std::size_t>(n) - 1,
                            *anchor_t_ns);
  }
  std::snprintf(stamps + n, sizeof stamps - static_cast<std::size_t>(n), " %u", unsigned{segment});
  return format_pose_line(buf, size, stamps, T);
}

OutputStage::~OutputStage() {
  (void)close();
}

Status OutputStage::open_file(File& file, const std::string& path, const char* header) {
  file.path = path;
  file.f = std::fopen(path.c_str(), "w");
  if (file.f == nullptr) {
    return input_error("cannot write '" + path + "': " + std::strerror(errno));
  }
  std::setvbuf(file.f, nullptr, _IOFBF, kFileBuffer);
  if (header != nullptr) std::fputs(header, file.f);
  return Status::ok();
}

Status OutputStage::open(const std::string& dir, const OutputOptions& opts) {
  opts_ = opts;
  dir_ = dir;
  if (dir.empty()) return Status::ok();
  const std::filesystem::path d(dir);
  // Segment files of an earlier run in the same directory would read as this run's.
  std::error_code ec;
  for (const auto& e : std::filesystem::directory_iterator(d, ec)) {
    const std::string name = e.path().filename().string();
    if (name.starts_with("trajectory_segment_") || name.starts_with("keyframes_segment_")) {
      std::filesystem::remove(e.path(), ec);
    }
  }
  Status s = open_file(trajectory_, (d / "trajectory.txt").string(), nullptr);
  if (s.is_ok()) s = open_file(keyframes_, (d / "keyframes.txt").string(), nullptr);
  if (s.is_ok()) s = open_file(ground_truth_, (d / "groundtruth.txt").string(), nullptr);
  if (s.is_ok()) s = open_file(anchors_, (d / "frame_anchors.txt").string(), nullptr);
  if (s.is_ok()) s = open_file(orientation_, (d / "orientation.txt").string(), nullptr);
  orientation_written_ = false;
  if (s.is_ok()) {
    s = open_file(frames_csv_, (d / "frames.csv").string(),
                  "seq,t_s,state,keyframe,features,feature_hash,matches,inliers,query_t,query_s,"
                  "query_total,keyframe_reason,kl,focal,tracker_state,segment\n");
  }
  if (s.is_ok()) {
    s = open_file(latency_csv_, (d / "latency.csv").string(),
                  "seq,t_s,capture_ms,queue_ms,tracking_ms,end_to_end_ms,output_ms\n");
  }
  return s;
}

std::int64_t OutputStage::spin_once(const frontend::TrackingResult& r, std::int64_t end_to_end_ns) {
  const std::int64_t t0 = platform::monotonic_now_ns();
  ++frames_;
  if (trajectory_.f == nullptr) return platform::monotonic_now_ns() - t0;
  std::array<char, kLineBuffer> line{};
  if (r.state == frontend::TrackState::kTracked) {
    // Every segment's frames: after the run, those of the segments joined into trajectory.txt
    // are re-anchored with it (trajectory_final.txt).
    const int na = format_anchor_line(line.data(), line.size(), r.t_ns,
                                      r.has_anchor ? &r.anchor_t_ns : nullptr, r.segment,
                                      r.has_anchor ? r.T_kf_c : r.T_w_c);
    std::fwrite(line.data(), 1, static_cast<std::size_t>(na), anchors_.f);
  }
  if (r.state == frontend::TrackState::kTracked && r.segment != 0) {
    const int n = format_tum_line(line.data(), line.size(), r.t_ns, r.T_w_c);
    if (File* f = segment_file(r.segment, false); f != nullptr) {
      std::fwrite(line.data(), 1, static_cast<std::size_t>(n), f->f);
    }
    if (File* f = r.is_keyframe ? segment_file(r.segment, true) : nullptr; f != nullptr) {
      std::fwrite(line.data(), 1, static_cast<std::size_t>(n), f->f);
    }
  } else if (r.state == frontend::TrackState::kTracked) {
    const int n = format_tum_line(line.data(), line.size(), r.t_ns, r.T_w_c);
    std::fwrite(line.data(), 1, static_cast<std::size_t>(n), trajectory_.f);
    if (r.is_keyframe) std::fwrite(line.data(), 1, static_cast<std::size_t>(n), keyframes_.f);
  }
  if (r.has_orientation) {
    if (!orientation_written_ || r.orientation_chain != orientation_chain_) {
      std::fprintf(orientation_.f, "# chain %u\n", unsigned{r.orientation_chain});
      orientation_chain_ = r.orientation_chain;
      orientation_written_ = true;
    }
    SE3d T_chain_c = SE3d::Identity();
    T_chain_c.linear() = r.q_chain_c.toRotationMatrix();
    const int n = format_tum_line(line.data(), line.size(), r.t_ns, T_chain_c);
    std::fwrite(line.data(), 1, static_cast<std::size_t>(n), orientation_.f);
  }
  if (r.has_ground_truth) {
    const int n = format_tum_line(line.data(), line.size(), r.t_ns, r.T_w_c_gt);
    std::fwrite(line.data(), 1, static_cast<std::size_t>(n), ground_truth_.f);
  }
  char t_s[32];
  format_seconds(t_s, sizeof t_s, r.t_ns);
  std::fprintf(frames_csv_.f, "%llu,%s,%s,%d,%d,%016llx,%d,%d,%d,%d,%d,%s,%.4f,%.3f,%s,%u\n",
               static_cast<unsigned long long>(r.seq), t_s, frontend::to_string(r.state),
               r.is_keyframe ? 1 : 0, r.num_features,
               static_cast<unsigned long long>(r.feature_hash), r.num_matches, r.num_inliers,
               r.query_temporal, r.query_spatial, r.query_total,
               frontend::to_string(static_cast<frontend::KeyframeReason>(r.keyframe_reason)),
               static_cast<double>(r.kl), r.focal, frontend::to_string(r.tracker_state),
               unsigned{r.segment});
  if (frames_ % static_cast<std::uint64_t>(opts_.flush_every) == 0) flush_all();
  const std::int64_t out_ns = platform::monotonic_now_ns() - t0;
  using S = frontend::StageId;
  auto ms = [&r](S s) {
    return static_cast<double>(r.stage_ns[static_cast<std::size_t>(s)]) * kNsToMs;
  };
  std::fprintf(latency_csv_.f, "%llu,%s,%.4f,%.4f,%.4f,%.4f,%.4f\n",
               static_cast<unsigned long long>(r.seq), t_s, ms(S::kCapture), ms(S::kQueue),
               ms(S::kTracking), static_cast<double>(end_to_end_ns) * kNsToMs,
               static_cast<double>(out_ns) * kNsToMs);
  return out_ns;
}

OutputStage::File* OutputStage::segment_file(std::uint16_t s, bool keyframes) {
  const std::size_t i = 2 * (std::size_t{s} - 1) + (keyframes ? 1 : 0);
  if (segment_files_.size() <= i) segment_files_.resize(2 * std::size_t{s});
  File& f = segment_files_[i];
  if (f.f == nullptr && f.path.empty()) {
    const std::string name = std::string(keyframes ? "keyframes" : "trajectory") + "_segment_" +
                             std::to_string(s) + ".txt";
    if (!open_file(f, (std::filesystem::path(dir_) / name).string(), nullptr).is_ok()) {
      write_error_ = true;  // reported by close(), like any write error
    }
  }
  return f.f != nullptr ? &f : nullptr;
}

void OutputStage::flush_all() {
  for (File* f : {&trajectory_, &keyframes_, &ground_truth_, &anchors_, &frames_csv_, &latency_csv_,
                  &orientation_}) {
    if (f->f != nullptr && (std::fflush(f->f) != 0 || std::ferror(f->f) != 0)) write_error_ = true;
  }
  for (File& f : segment_files_) {
    if (f.f != nullptr && (std::fflush(f.f) != 0 || std::ferror(f.f) != 0)) write_error_ = true;
  }
}

Status OutputStage::close() {
  Status result;
  flush_all();
  for (File* f : {&trajectory_, &keyframes_, &ground_truth_, &anchors_, &frames_csv_, &latency_csv_,
                  &orientation_}) {
    if (f->f == nullptr) continue;
    const bool bad = std::ferror(f->f) != 0;
    if (std::fclose(f->f) != 0 || bad) {
      if (result.is_ok()) result = runtime_error("error writing '" + f->path + "'");
    }
    f->f = nullptr;
  }
  for (File& f : segment_files_) {
    if (f.f == nullptr) continue;
    const bool bad = std::ferror(f.f) != 0;
    if ((std::fclose(f.f) != 0 || bad) && result.is_ok()) {
      result = runtime_error("error writing '" + f.path + "'");
    }
    f.f = nullptr;
  }
  if (write_error_ && result.is_ok()) result = runtime_error("error writing output files");
  return result;
}

}  // namespace mer::pipeline
