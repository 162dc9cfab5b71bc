// Writes the seed corpus of recording_fuzz (tests/fuzz/corpus/recording): tiny recordings,
// valid ones (valid_*) and typically damaged ones, each well under 8 KB.
//
//   mer_make_recording_corpus DIR           write the seeds into DIR
//   mer_make_recording_corpus --check DIR   exit 1 unless DIR holds exactly these bytes
//
// Regenerate the committed seeds after a format change:
//   build/<preset>/tests/fuzz/mer_make_recording_corpus tests/fuzz/corpus/recording
#include <cstdint>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <string>
#include <string_view>
#include <utility>
#include <vector>

#include "hal/replay/recording.h"

namespace {

using mer::hal::Frame;
using mer::hal::RecordingHeader;
using Bytes = std::vector<std::uint8_t>;

constexpr std::int64_t kPeriodNs = 33'333'333;

RecordingHeader header(int w, int h, bool depth, bool gt, bool focal_known) {
  RecordingHeader hd;
  hd.description = "seed " + std::to_string(w) + "x" + std::to_string(h);
  hd.intrinsics = mer::hal::CameraIntrinsics{
      w, h, 40.0, 40.0, 0.5 * (w - 1), 0.5 * (h - 1), {0.1, -0.01, 0.001, 0.002}, focal_known};
  hd.nominal_fps = 30.0;
  hd.has_depth = depth;
  hd.has_ground_truth = gt;
  return hd;
}

Frame frame(const RecordingHeader& hd, int k, bool pose) {
  const int w = hd.intrinsics.width;
  const int h = hd.intrinsics.height;
  Frame f;
  f.seq = static_cast<std::uint64_t>(k);
  f.t_ns = k * kPeriodNs;
  f.gray = cv::Mat(h, w, CV_8UC1);
  for (int r = 0; r < h; ++r) {
    for (int c = 0; c < w; ++c)
      f.gray.at<std::uint8_t>(r, c) = static_cast<std::uint8_t>(r * 16 + c + k);
  }
  if (hd.has_depth) f.depth = cv::Mat(h, w, CV_32FC1, cv::Scalar(1.0 + k));
  f.has_ground_truth = pose;
  f.T_w_c_gt.translation() = Eigen::Vector3d(0.1 * k, 0.0, 1.0);
  return f;
}

Bytes recording(const RecordingHeader& hd, int frames, bool all_poses = true) {
  Bytes b = mer::hal::encode_header(hd);
  for (int k = 0; k < frames; ++k) {
    const mer::Status s = mer::hal::encode_chunk(hd, frame(hd, k, all_poses || k % 2 == 0), b);
    if (!s.is_ok()) std::fprintf(stderr, "%s\n", s.message().c_str());
  }
  return b;
}

std::vector<std::pair<std::string, Bytes>> seeds() {
  std::vector<std::pair<std::string, Bytes>> out;
  const RecordingHeader rgbd = header(8, 6, true, true, true);
  const Bytes three = recording(rgbd, 3);
  out.emplace_back("valid_3frames_depth_gt.merrec", three);
  out.emplace_back("valid_2frames_grey.merrec", recording(header(16, 4, false, false, false), 2));
  out.emplace_back("valid_4frames_some_poses.merrec",
                   recording(header(5, 3, false, true, true), 4, false));
  out.emplace_back("valid_header_only.merrec", mer::hal::encode_header(rgbd));
  // The last 100 bytes cut off (a size GCC's sanitizer build can see cannot underflow).
  constexpr std::size_t kCut = 100;
  const Bytes cut(
      three.begin(),
      three.begin() + static_cast<std::ptrdiff_t>(three.size() > kCut ? three.size() - kCut : 0));
  out.emplace_back("truncated_mid_chunk.merrec", cut);
  Bytes crc = three;
  crc[crc.size() - 50] ^= 0x10;
  out.emplace_back("crc_damaged_last_frame.merrec", crc);
  Bytes tail = recording(rgbd, 1);
  tail.resize(tail.size() + 64, 0);
  out.emplace_back("zero_tail.merrec", tail);
  return out;
}

Bytes read_file(const std::filesystem::path& p) {
  std::ifstream f(p, std::ios::binary);
  return {std::istreambuf_iterator<char>(f), std::istreambuf_iterator<char>()};
}

}  // namespace

int main(int argc, char** argv) {
  const bool check = argc == 3 && std::string_view(argv[1]) == "--check";
  if (argc != 2 && !check) {
    std::fprintf(stderr, "usage: %s [--check] DIR\n", argv[0]);
    return 2;
  }
  const std::filesystem::path dir = argv[argc - 1];
  int bad = 0;
  for (const auto& [name, bytes] : seeds()) {
    const auto path = dir / name;
    if (check) {
      if (read_file(path) != bytes) {
        std::fprintf(stderr, "%s: differs from the generator's output (regenerate the corpus)\n",
                     path.c_str());
        ++bad;
      }
      continue;
    }
    std::filesystem::create_directories(dir);
    std::ofstream(path, std::ios::binary)
        .write(reinterpret_cast<const char*>(bytes.data()),
               static_cast<std::streamsize>(bytes.size()));
    std::printf("%s (%zu bytes)\n", path.c_str(), bytes.size());
  }
  return bad == 0 ? 0 : 1;
}
