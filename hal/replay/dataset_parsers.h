#pragma once
/// @file dataset_parsers.h
/// Pure parsers of the text files of the dataset layouts replay reads (TUM RGB-D, EuRoC,
/// KITTI odometry). Each takes the whole file as in-memory text plus the name to use in
/// messages, and returns the parsed content or an error naming `name:line` and what was
/// expected and found.
///
/// Contract (a libFuzzer harness relies on it): for ANY byte string these functions
/// return (a value or an error) without crashing, hanging, reading out of bounds or
/// allocating more than a small multiple of the input size. Numbers must be finite;
/// timestamps must be strictly increasing and within +-9.2e9 s; lines may end in "\r\n".
/// Empty lines and lines starting with '#' (after leading blanks) are ignored; a file with
/// no entries is an error.

#include <array>
#include <cstdint>
#include <string>
#include <string_view>
#include <vector>

#include "core/pose.h"
#include "core/status.h"
#include "core/timestamp.h"
#include "hal/ground_truth.h"

namespace mer::hal {

/// One entry of an image index: a timestamp and a file name relative to the dataset root.
struct TimedFile {
  std::int64_t t_ns = 0;  ///< timestamp, ns
  std::string file;       ///< path as written in the index (relative to the dataset folder)
  int line = 0;           ///< 1-based line of the index it came from (for messages)
};

/// Intrinsics from a KITTI `calib.txt` (`P0:` row-major 3x4 projection matrix).
struct KittiCalib {
  double fx = 0.0;  ///< P0[0][0], px
  double fy = 0.0;  ///< P0[1][1], px
  double cx = 0.0;  ///< P0[0][2], px
  double cy = 0.0;  ///< P0[1][2], px
};

/// What replay needs from a EuRoC `mav0/cam0/sensor.yaml`.
struct EurocSensor {
  int width = 0;                  ///< `resolution: [w, h]`, px
  int height = 0;                 ///< `resolution: [w, h]`, px
  double fu = 0.0;                ///< `intrinsics: [fu, fv, cu, cv]`, px
  double fv = 0.0;                ///< focal length y, px
  double cu = 0.0;                ///< principal point x, px
  double cv = 0.0;                ///< principal point y, px
  std::array<double, 4> dist{};   ///< `distortion_coefficients: [k1, k2, p1, p2]` (radtan)
  double rate_hz = 0.0;           ///< `rate_hz` (0 when absent)
  SE3d T_b_s = SE3d::Identity();  ///< `T_BS: data: [16 numbers]`, sensor (camera) to body
};

/// Seconds in decimal to integer nanoseconds (core/timestamp.h).
using mer::parse_seconds_ns;

/// TUM image list (`rgb.txt`, `depth.txt`): `timestamp filename` per line.
/// Errors: a line without exactly two fields, a bad timestamp, a timestamp not strictly
/// greater than the previous one, no entries.
Result<std::vector<TimedFile>> parse_tum_list(std::string_view text, const std::string& name);

/// EuRoC camera index (`mav0/cam0/data.csv`): `timestamp_ns,filename` per line (blanks
/// around fields allowed). `file` is returned as written (relative to `cam0/data/`).
/// Errors as parse_tum_list(); the timestamp must be a non-negative integer.
Result<std::vector<TimedFile>> parse_euroc_csv(std::string_view text, const std::string& name);

/// KITTI `calib.txt`: the `P0:` line with 12 numbers. Errors: no P0 line, a P0 line without
/// 12 finite numbers, fx or fy not > 0.
Result<KittiCalib> parse_kitti_calib(std::string_view text, const std::string& name);

/// KITTI `times.txt`: one time in seconds per line, strictly increasing.
Result<std::vector<double>> parse_kitti_times(std::string_view text, const std::string& name);

/// KITTI `poses.txt`: 12 numbers per line, row-major 3x4 T_w_c. Errors: a line without
/// 12 finite numbers, a rotation block that is not a rotation (|R^T R - I| > 1e-2 or
/// det(R) <= 0).
Result<std::vector<SE3d>> parse_kitti_poses(std::string_view text, const std::string& name);

/// TUM trajectory (`t tx ty tz qx qy qz qw`). Errors: a line without 8 finite numbers, a
/// quaternion whose norm is not within 1e-2 of 1, a decreasing timestamp, no entries. A
/// sample repeating the previous timestamp is dropped and counted (duplicates_dropped,
/// first_duplicate_line), not an error: published ground truth contains such repeats.
/// `source` of the result is `name`.
Result<Trajectory> parse_tum_trajectory(std::string_view text, const std::string& name);

/// EuRoC ground truth (`mav0/state_groundtruth_estimate0/data.csv`):
/// `timestamp_ns, p_x, p_y, p_z, q_w, q_x, q_y, q_z, ...` (body pose T_w_b; further
/// columns ignored). Errors and repeated timestamps as parse_tum_trajectory().
Result<Trajectory> parse_euroc_groundtruth(std::string_view text, const std::string& name);

/// EuRoC `sensor.yaml` (a tolerant reader of the keys listed in EurocSensor, not a YAML
/// parser). Errors: a missing key `resolution`, `intrinsics` or `T_BS` data, a list of the
/// wrong length, non-finite numbers, a distortion model other than radial-tangential, a
/// camera model other than pinhole. `distortion_coefficients` and `rate_hz` are optional.
Result<EurocSensor> parse_euroc_sensor(std::string_view text, const std::string& name);

/// Reads a whole (index) file into memory. Not pure: the one file-reading helper the
/// loaders share. Errors name the file (missing, unreadable, larger than 1 GiB).
Result<std::string> read_text_file(const std::string& path);

}  // namespace mer::hal
