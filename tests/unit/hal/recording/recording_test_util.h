#pragma once
// Test helpers: small deterministic recordings built in memory with the format's encoders.

#include <cstdint>
#include <filesystem>
#include <fstream>
#include <span>
#include <string>
#include <vector>

#include <gtest/gtest.h>

#include "hal/replay/recording.h"

namespace mer::hal::testing {

/// A recording in memory: the header, the frames that went in, the encoded bytes and where
/// each chunk starts (chunk_offsets.back() == bytes.size() marks the end).
struct MemRecording {
  RecordingHeader header;
  std::vector<Frame> frames;
  std::vector<std::uint8_t> bytes;
  std::vector<std::size_t> chunk_offsets;  ///< start of each chunk, then the file size
};

/// Deterministic frame `k` of a w x h recording: patterned pixels and depth, a pose, seq
/// with gaps and 30 Hz timestamps.
inline Frame make_frame(int k, int w, int h, bool depth, bool gt) {
  constexpr std::int64_t kT0Ns = 1'000'000'000;
  constexpr std::int64_t kPeriodNs = 33'333'333;
  Frame f;
  f.seq = static_cast<std::uint64_t>(2 * k + 1);
  f.t_ns = kT0Ns + k * kPeriodNs;
  f.gray = cv::Mat(h, w, CV_8UC1);
  for (int r = 0; r < h; ++r) {
    for (int c = 0; c < w; ++c)
      f.gray.at<std::uint8_t>(r, c) = static_cast<std::uint8_t>((r * 31 + c * 7 + k * 13) & 0xFF);
  }
  if (depth) {
    f.depth = cv::Mat(h, w, CV_32FC1);
    for (int r = 0; r < h; ++r) {
      for (int c = 0; c < w; ++c)
        f.depth.at<float>(r, c) = 0.5F + 0.01F * r + 0.001F * c + static_cast<float>(k);
    }
  }
  f.has_ground_truth = gt;
  f.T_w_c_gt = look_at(Eigen::Vector3d(0.1 * k, -0.2, 1.3 + 0.01 * k),
                       Eigen::Vector3d(1.0, 2.0 - 0.1 * k, 1.2), Eigen::Vector3d::UnitZ());
  return f;
}

/// Header of a w x h test recording.
inline RecordingHeader make_header(int w, int h, bool depth, bool gt) {
  RecordingHeader hd;
  hd.description = "test camera " + std::to_string(w) + "x" + std::to_string(h);
  hd.intrinsics = CameraIntrinsics{
      w, h, 50.5, 51.25, 0.5 * (w - 1), 0.5 * (h - 1), {0.01, -0.002, 0.0003, -0.0004}, true};
  hd.nominal_fps = 30.0;
  hd.has_depth = depth;
  hd.has_ground_truth = gt;
  return hd;
}

/// `n` frames of w x h encoded in memory.
inline MemRecording make_mem_recording(int n, int w = 8, int h = 6, bool depth = true,
                                       bool gt = true) {
  MemRecording m;
  m.header = make_header(w, h, depth, gt);
  m.bytes = encode_header(m.header);
  for (int k = 0; k < n; ++k) {
    m.frames.push_back(make_frame(k, w, h, depth, gt));
    m.chunk_offsets.push_back(m.bytes.size());
    const Status s = encode_chunk(m.header, m.frames.back(), m.bytes);
    EXPECT_TRUE(s.is_ok()) << s.message();
  }
  m.chunk_offsets.push_back(m.bytes.size());
  return m;
}

/// A fresh path in the temp directory.
inline std::string temp_path(const std::string& name) {
  const auto p = std::filesystem::temp_directory_path() / ("mer_rec_test_" + name);
  std::filesystem::remove_all(p);
  return p.string();
}

/// Writes `bytes` to `path` (replacing it).
inline void write_bytes(const std::string& path, std::span<const std::uint8_t> bytes) {
  std::ofstream f(path, std::ios::binary | std::ios::trunc);
  f.write(reinterpret_cast<const char*>(bytes.data()), static_cast<std::streamsize>(bytes.size()));
}

/// Reads a whole file.
inline std::vector<std::uint8_t> read_bytes(const std::string& path) {
  std::ifstream f(path, std::ios::binary);
  return {std::istreambuf_iterator<char>(f), std::istreambuf_iterator<char>()};
}

/// True when the two Mats have the same size, type and bytes.
inline bool same_bytes(const cv::Mat& a, const cv::Mat& b) {
  if (a.size() != b.size() || a.type() != b.type()) return false;
  const std::size_t row = static_cast<std::size_t>(a.cols) * a.elemSize();
  for (int r = 0; r < a.rows; ++r) {
    if (std::memcmp(a.ptr(r), b.ptr(r), row) != 0) return false;
  }
  return true;
}

/// Reads every frame of `path` with RecordingReader until it stops; returns the number read
/// (and the reader's final damage in `damage`).
inline std::size_t read_all(RecordingReader& reader, std::optional<RecordingDamage>& damage) {
  Frame f;
  std::size_t n = 0;
  while (reader.read_frame(n, f) == ReadStatus::kFrame) ++n;
  damage = reader.damage();
  return n;
}

}  // namespace mer::hal::testing
