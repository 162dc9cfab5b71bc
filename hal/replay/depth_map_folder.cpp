#include "hal/replay/depth_map_folder.h"

#include <algorithm>
#include <cctype>
#include <charconv>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <utility>

#include <opencv2/imgcodecs.hpp>

#include "hal/replay/dataset_parsers.h"
#include "hal/replay/pfm.h"

namespace mer::hal {
namespace {

namespace fs = std::filesystem;

enum class Kind { kNone, kPng, kPfm };

std::string lower(std::string s) {
  std::transform(s.begin(), s.end(), s.begin(),
                 [](unsigned char c) { return static_cast<char>(std::tolower(c)); });
  return s;
}

Kind kind_of(const fs::path& p, std::string_view format) {
  const std::string ext = lower(p.extension().string());
  if (ext == ".png" && format != "float32") return Kind::kPng;
  if (ext == ".pfm" && format != "png16") return Kind::kPfm;
  return Kind::kNone;
}

std::string expected_names(std::string_view format) {
  if (format == "png16") return "<timestamp>.png";
  if (format == "float32") return "<timestamp>.pfm";
  return "<timestamp>.png or <timestamp>.pfm";
}

Status read_png(const std::string& file, double depth_scale, cv::Mat& depth) {
  cv::Mat raw;
  try {
    raw = cv::imread(file, cv::IMREAD_UNCHANGED);
  } catch (const cv::Exception& e) {
    return input_error("depth map '" + file + "': unreadable PNG (" + e.what() + ")");
  }
  if (raw.empty()) return input_error("depth map '" + file + "': unreadable or corrupt PNG");
  if (raw.type() != CV_16UC1) {
    return input_error("depth map '" + file + "': expected a 16-bit single-channel PNG, found " +
                       std::to_string(8 * static_cast<int>(raw.elemSize1())) + "-bit " +
                       std::to_string(raw.channels()) + "-channel");
  }
  raw.convertTo(depth, CV_32FC1, 1.0 / depth_scale);
  return Status::ok();
}

Status read_pfm(const std::string& file, cv::Mat& depth) {
  std::ifstream in(file, std::ios::binary);
  if (!in) return input_error("depth map '" + file + "': cannot open");
  const std::vector<char> data((std::istreambuf_iterator<char>(in)),
                               std::istreambuf_iterator<char>());
  if (in.bad()) return input_error("depth map '" + file + "': read error");
  Result<cv::Mat> m =
      parse_pfm(std::span<const std::uint8_t>(reinterpret_cast<const std::uint8_t*>(data.data()),
                                              data.size()),
                file);
  if (!m.is_ok()) return m.status();
  depth = std::move(m).value();
  // No depth where the value is not a positive finite number.
  for (int r = 0; r < depth.rows; ++r) {
    auto* row = depth.ptr<float>(r);
    for (int c = 0; c < depth.cols; ++c) {
      if (!std::isfinite(row[c]) || row[c] < 0.0F) row[c] = 0.0F;
    }
  }
  return Status::ok();
}

}  // namespace

bool parse_depth_map_time(std::string_view stem, std::string_view time_unit, std::int64_t& t_ns) {
  if (stem.empty()) return false;
  const bool seconds =
      time_unit == "s" || (time_unit == "auto" && stem.find('.') != std::string_view::npos);
  if (seconds) {
    // Decimal seconds only (no exponent, no sign): a name, not a number in any notation.
    const bool plain = std::all_of(stem.begin(), stem.end(),
                                   [](char c) { return (c >= '0' && c <= '9') || c == '.'; });
    return plain && parse_seconds_ns(stem, t_ns);
  }
  const auto [ptr, ec] = std::from_chars(stem.data(), stem.data() + stem.size(), t_ns);
  return ec == std::errc() && ptr == stem.data() + stem.size() && stem.front() != '-' &&
         stem.front() != '+';
}

Result<DepthMapFolder> DepthMapFolder::open(const DepthMapFolderOptions& opts) {
  const std::string& dir = opts.folder;
  if (dir.empty()) return invalid_argument("no depth map folder given (empty)");
  std::error_code ec;
  if (!fs::exists(dir, ec))
    return invalid_argument("depth map folder '" + dir + "' does not exist");
  if (!fs::is_directory(dir, ec)) {
    return invalid_argument("depth map folder '" + dir + "' is not a folder");
  }
  std::vector<std::pair<std::int64_t, std::string>> entries;
  fs::directory_iterator it(dir, ec);
  for (; !ec && it != fs::directory_iterator(); it.increment(ec)) {
    const fs::directory_entry& e = *it;
    const fs::path& p = e.path();
    const std::string name = p.filename().string();
    if (name.empty() || name.front() == '.') continue;
    std::error_code file_ec;
    if (!e.is_regular_file(file_ec)) continue;
    if (kind_of(p, opts.format) == Kind::kNone) continue;
    std::int64_t t_ns = 0;
    if (!parse_depth_map_time(p.stem().string(), opts.time_unit, t_ns)) {
      return invalid_argument("depth map '" + p.string() + "': the name is not a timestamp " +
                              "(expected " + expected_names(opts.format) +
                              ", the timestamp in decimal seconds or integer nanoseconds)");
    }
    entries.emplace_back(t_ns, p.string());
  }
  if (ec) {
    return invalid_argument("depth map folder '" + dir + "': cannot list (" + ec.message() + ")");
  }
  if (entries.empty()) {
    return invalid_argument("depth map folder '" + dir + "' holds no depth map (expected " +
                            expected_names(opts.format) + ")");
  }
  std::sort(entries.begin(), entries.end());
  DepthMapFolder f(opts);
  f.t_ns_.reserve(entries.size());
  f.files_.reserve(entries.size());
  for (std::size_t i = 0; i < entries.size(); ++i) {
    if (i > 0 && entries[i].first == entries[i - 1].first) {
      return invalid_argument("depth maps '" + entries[i - 1].second + "' and '" +
                              entries[i].second + "' have the same timestamp");
    }
    f.t_ns_.push_back(entries[i].first);
    f.files_.push_back(std::move(entries[i].second));
  }
  return f;
}

Status DepthMapFolder::read(std::size_t i, cv::Mat& depth) const {
  if (i >= files_.size()) {
    return invalid_argument("depth map folder '" + opts_.folder + "': no map " + std::to_string(i) +
                            " (" + std::to_string(files_.size()) + " maps)");
  }
  const std::string& file = files_[i];
  std::error_code ec;
  if (!fs::is_regular_file(file, ec)) {
    return input_error("depth map '" + file + "': missing (removed after the folder was listed)");
  }
  return kind_of(file, opts_.format) == Kind::kPfm ? read_pfm(file, depth)
                                                   : read_png(file, opts_.depth_scale, depth);
}

}  // namespace mer::hal
