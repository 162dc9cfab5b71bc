#pragma once
/// @file depth_map_folder.h
/// A folder of per-frame depth maps named by capture time: the files behind the `external`
/// depth backend (src/depth/external_depth.h), e.g. a learned model's output recorded
/// offline, or the `depth/` folder of a TUM RGB-D sequence.
///
/// - Names: `<timestamp>.<ext>`; the timestamp is decimal seconds (`1305031102.175304`,
///   time unit `s`) or integer nanoseconds (`1403636579763555584`, `ns`); `auto` takes a
///   name with a decimal point as seconds and a name of digits only as nanoseconds.
/// - Formats: `png16` (`.png`, 16-bit single-channel; depth = value / depth_scale, 0 = none),
///   `float32` (`.pfm`, single-channel PFM, hal/replay/pfm.h; non-finite or negative = none);
///   `auto` takes both, by extension (case-insensitive). Files with other extensions and
///   hidden files are ignored.
/// - The folder is listed once, in open(); reading a map decodes its file then.
/// Errors: the folder missing or not a folder, no map file in it, a map file whose name is
/// not a timestamp, two files with the same timestamp (each naming the file(s)); read(): a
/// missing, unreadable, truncated or wrong-type file (naming it).

#include <cstddef>
#include <cstdint>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include <opencv2/core/mat.hpp>

#include "core/status.h"

namespace mer::hal {

/// What a DepthMapFolder reads.
struct DepthMapFolderOptions {
  std::string folder;              ///< the folder
  std::string format = "auto";     ///< auto, png16, float32
  std::string time_unit = "auto";  ///< auto, s, ns
  double depth_scale = 5000.0;     ///< png16: stored value per depth unit
};

/// The timestamp, ns, a depth-map file name stem gives under `time_unit` (auto, s, ns), or
/// false when it is not one (see the file comment).
bool parse_depth_map_time(std::string_view stem, std::string_view time_unit, std::int64_t& t_ns);

/// An indexed folder of depth maps.
class DepthMapFolder {
 public:
  /// Lists and indexes the folder.
  static Result<DepthMapFolder> open(const DepthMapFolderOptions& opts);

  /// The folder, as given.
  const std::string& folder() const { return opts_.folder; }
  /// Map timestamps, ns, strictly increasing.
  std::span<const std::int64_t> timestamps() const { return t_ns_; }
  /// Path of map `i`.
  const std::string& file(std::size_t i) const { return files_[i]; }
  /// Reads map `i` (< timestamps().size()) as CV_32FC1 depth, 0 = none. Allocates.
  Status read(std::size_t i, cv::Mat& depth) const;

 private:
  explicit DepthMapFolder(DepthMapFolderOptions opts) : opts_(std::move(opts)) {}

  DepthMapFolderOptions opts_;
  std::vector<std::int64_t> t_ns_;
  std::vector<std::string> files_;
};

}  // namespace mer::hal
