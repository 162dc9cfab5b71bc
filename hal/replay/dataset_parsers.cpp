#include "hal/replay/dataset_parsers.h"

#include <algorithm>
#include <charconv>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <sstream>

namespace mer::hal {
namespace {

constexpr std::int64_t kNsPerS = 1'000'000'000;
constexpr double kMaxAbsSeconds = 9.2e9;        // |t| * 1e9 must fit an int64
constexpr std::size_t kMaxShownChars = 60;      // of offending text quoted in messages
constexpr double kQuatNormTolerance = 1e-2;     // |‖q‖ - 1| accepted before normalizing
constexpr double kRotationTolerance = 1e-2;     // max |R^T R - I| entry for a rotation
constexpr std::size_t kKittiPoseFields = 12;    // row-major 3x4
constexpr std::size_t kTumPoseFields = 8;       // t tx ty tz qx qy qz qw
constexpr std::size_t kEurocGtMinFields = 8;    // t p_xyz q_wxyz
constexpr std::size_t kEurocSensorMatrix = 16;  // T_BS 4x4
constexpr std::uintmax_t kMaxTextFileBytes = std::uintmax_t{1} << 30;

// Offending text, shortened and with control/non-ASCII bytes replaced (fuzzed input).
std::string shown(std::string_view s) {
  std::string out;
  const std::size_t n = std::min(s.size(), kMaxShownChars);
  out.reserve(n + 3);
  for (std::size_t i = 0; i < n; ++i) {
    const auto c = static_cast<unsigned char>(s[i]);
    out.push_back(c >= 0x20 && c < 0x7f ? static_cast<char>(c) : '?');
  }
  if (s.size() > n) out += "...";
  return out;
}

Status line_error(const std::string& name, int line, const std::string& what) {
  return input_error(name + ":" + std::to_string(line) + ": " + what);
}

std::string_view trim(std::string_view s) {
  const auto is_blank = [](char c) {
    return c == ' ' || c == '\t' || c == '\r' || c == '\v' || c == '\f';
  };
  while (!s.empty() && is_blank(s.front())) s.remove_prefix(1);
  while (!s.empty() && is_blank(s.back())) s.remove_suffix(1);
  return s;
}

// Calls f(line_number, trimmed_line) for every line that is neither blank nor a comment;
// stops early and returns the first non-ok Status f returns.
template <class F>
Status for_each_entry(std::string_view text, F&& f) {
  int line_no = 0;
  std::size_t pos = 0;
  while (pos < text.size()) {
    std::size_t end = text.find('\n', pos);
    if (end == std::string_view::npos) end = text.size();
    ++line_no;
    const std::string_view line = trim(text.substr(pos, end - pos));
    pos = end + 1;
    if (line.empty() || line.front() == '#') continue;
    if (Status s = f(line_no, line); !s.is_ok()) return s;
  }
  return Status::ok();
}

std::vector<std::string_view> split_blanks(std::string_view s) {
  std::vector<std::string_view> out;
  std::size_t i = 0;
  while (i < s.size()) {
    while (i < s.size() && (s[i] == ' ' || s[i] == '\t')) ++i;
    const std::size_t b = i;
    while (i < s.size() && s[i] != ' ' && s[i] != '\t') ++i;
    if (i > b) out.push_back(s.substr(b, i - b));
  }
  return out;
}

std::vector<std::string_view> split_commas(std::string_view s) {
  std::vector<std::string_view> out;
  std::size_t b = 0;
  for (;;) {
    const std::size_t e = s.find(',', b);
    out.push_back(trim(s.substr(b, e == std::string_view::npos ? std::string_view::npos : e - b)));
    if (e == std::string_view::npos) break;
    b = e + 1;
  }
  return out;
}

bool parse_double(std::string_view tok, double& out) {
  if (!tok.empty() && tok.front() == '+') tok.remove_prefix(1);
  if (tok.empty()) return false;
  double v = 0.0;
  const auto [ptr, ec] = std::from_chars(tok.data(), tok.data() + tok.size(), v);
  if (ec != std::errc() || ptr != tok.data() + tok.size() || !std::isfinite(v)) return false;
  out = v;
  return true;
}

bool parse_int64(std::string_view tok, std::int64_t& out) {
  if (tok.empty()) return false;
  std::int64_t v = 0;
  const auto [ptr, ec] = std::from_chars(tok.data(), tok.data() + tok.size(), v);
  if (ec != std::errc() || ptr != tok.data() + tok.size()) return false;
  out = v;
  return true;
}

bool seconds_to_ns(double t_s, std::int64_t& t_ns) {
  if (!std::isfinite(t_s) || std::abs(t_s) >= kMaxAbsSeconds) return false;
  t_ns = std::llround(t_s * static_cast<double>(kNsPerS));
  return true;
}

Status check_increasing(const std::string& name, int line, std::int64_t t_ns, std::int64_t prev_ns,
                        int prev_line) {
  if (prev_line == 0 || t_ns > prev_ns) return Status::ok();
  return line_error(name, line,
                    std::string(t_ns == prev_ns ? "duplicate" : "non-monotonic") +
                        " timestamp (not after the one on line " + std::to_string(prev_line) + ")");
}

Status no_entries(const std::string& name, const std::string& expected) {
  return input_error(name + ": no entries (empty file? expected lines of '" + expected + "')");
}

// A unit quaternion from (w, x, y, z) or an error when its norm is far from 1.
bool unit_quaternion(double w, double x, double y, double z, Eigen::Quaterniond& q) {
  q = Eigen::Quaterniond(w, x, y, z);
  const double n = q.norm();
  if (!(std::abs(n - 1.0) <= kQuatNormTolerance)) return false;
  q.normalize();
  return true;
}

// Appends a trajectory sample: a repeated timestamp is dropped and counted, a decreasing
// one is an error.
Status add_sample(Trajectory& traj, const StampedPose& p, const std::string& name, int line,
                  int& prev_line) {
  if (!traj.poses.empty() && p.t_ns == traj.poses.back().t_ns) {
    if (traj.duplicates_dropped++ == 0) traj.first_duplicate_line = line;
    return Status::ok();
  }
  const std::int64_t prev_ns = traj.poses.empty() ? 0 : traj.poses.back().t_ns;
  if (Status m = check_increasing(name, line, p.t_ns, prev_ns, prev_line); !m.is_ok()) return m;
  prev_line = line;
  traj.poses.push_back(p);
  return Status::ok();
}

// ---- sensor.yaml helpers: find "key:" at the start of a line (after blanks) -------------

struct KeyHit {
  std::size_t value_pos = std::string_view::npos;  // just after the ':'
  int line = 0;
};

KeyHit find_key(std::string_view text, std::string_view key, std::size_t from = 0) {
  int line_no = 1;
  for (std::size_t i = 0; i < from && i < text.size(); ++i) line_no += text[i] == '\n' ? 1 : 0;
  std::size_t pos = from;
  while (pos < text.size()) {
    std::size_t end = text.find('\n', pos);
    if (end == std::string_view::npos) end = text.size();
    std::string_view line = text.substr(pos, end - pos);
    std::size_t b = 0;
    while (b < line.size() && (line[b] == ' ' || line[b] == '\t')) ++b;
    if (line.substr(b).starts_with(key)) {
      std::size_t c = b + key.size();
      while (c < line.size() && (line[c] == ' ' || line[c] == '\t')) ++c;
      if (c < line.size() && line[c] == ':') return {pos + c + 1, line_no};
    }
    pos = end + 1;
    ++line_no;
  }
  return {};
}

// Reads "[a, b, c]" (may span lines; '#' comments inside are skipped) at `pos`.
Status read_list(std::string_view text, KeyHit hit, const std::string& name, std::string_view key,
                 std::size_t expected, std::vector<double>& out) {
  std::size_t p = hit.value_pos;
  while (p < text.size() &&
         (text[p] == ' ' || text[p] == '\t' || text[p] == '\r' || text[p] == '\n')) {
    ++p;
  }
  if (p >= text.size() || text[p] != '[') {
    return line_error(name, hit.line, "key '" + std::string(key) + "': expected a list [..]");
  }
  const std::size_t close = text.find(']', p);
  if (close == std::string_view::npos) {
    return line_error(name, hit.line, "key '" + std::string(key) + "': list without ']'");
  }
  std::string body(text.substr(p + 1, close - p - 1));
  // Drop comments, then treat commas and line breaks as blanks.
  for (std::size_t i = 0; i < body.size(); ++i) {
    if (body[i] == '#') {
      while (i < body.size() && body[i] != '\n') body[i++] = ' ';
      if (i >= body.size()) break;
    }
    if (body[i] == ',' || body[i] == '\n' || body[i] == '\r') body[i] = ' ';
  }
  out.clear();
  for (std::string_view tok : split_blanks(body)) {
    double v = 0.0;
    if (!parse_double(tok, v)) {
      return line_error(
          name, hit.line,
          "key '" + std::string(key) + "': expected numbers, found '" + shown(tok) + "'");
    }
    out.push_back(v);
    if (out.size() > expected) break;
  }
  if (out.size() != expected) {
    return line_error(name, hit.line,
                      "key '" + std::string(key) + "': expected " + std::to_string(expected) +
                          " numbers, found " +
                          (out.size() > expected ? "more" : std::to_string(out.size())));
  }
  return Status::ok();
}

// The scalar after "key:" up to the end of the line or a '#'.
std::string_view read_scalar(std::string_view text, KeyHit hit) {
  std::size_t end = text.find('\n', hit.value_pos);
  if (end == std::string_view::npos) end = text.size();
  std::string_view v = text.substr(hit.value_pos, end - hit.value_pos);
  if (const std::size_t hash = v.find('#'); hash != std::string_view::npos) v = v.substr(0, hash);
  v = trim(v);
  if (v.size() >= 2 && (v.front() == '"' || v.front() == '\'') && v.back() == v.front()) {
    v = v.substr(1, v.size() - 2);
  }
  return v;
}

}  // namespace

Result<std::vector<TimedFile>> parse_tum_list(std::string_view text, const std::string& name) {
  std::vector<TimedFile> out;
  Status s = for_each_entry(text, [&](int line, std::string_view l) -> Status {
    const auto f = split_blanks(l);
    if (f.size() != 2) {
      return line_error(name, line, "expected 'timestamp filename', found '" + shown(l) + "'");
    }
    TimedFile tf;
    if (!parse_seconds_ns(f[0], tf.t_ns)) {
      return line_error(name, line, "bad timestamp '" + shown(f[0]) + "' (expected seconds)");
    }
    if (Status m = check_increasing(name, line, tf.t_ns, out.empty() ? 0 : out.back().t_ns,
                                    out.empty() ? 0 : out.back().line);
        !m.is_ok()) {
      return m;
    }
    tf.file = std::string(f[1]);
    tf.line = line;
    out.push_back(std::move(tf));
    return Status::ok();
  });
  if (!s.is_ok()) return s;
  if (out.empty()) return no_entries(name, "timestamp filename");
  return out;
}

Result<std::vector<TimedFile>> parse_euroc_csv(std::string_view text, const std::string& name) {
  std::vector<TimedFile> out;
  Status s = for_each_entry(text, [&](int line, std::string_view l) -> Status {
    const auto f = split_commas(l);
    if (f.size() != 2 || f[1].empty()) {
      return line_error(name, line, "expected 'timestamp_ns,filename', found '" + shown(l) + "'");
    }
    TimedFile tf;
    if (!parse_int64(f[0], tf.t_ns) || tf.t_ns < 0) {
      return line_error(name, line,
                        "bad timestamp '" + shown(f[0]) + "' (expected integer nanoseconds)");
    }
    if (Status m = check_increasing(name, line, tf.t_ns, out.empty() ? 0 : out.back().t_ns,
                                    out.empty() ? 0 : out.back().line);
        !m.is_ok()) {
      return m;
    }
    tf.file = std::string(f[1]);
    tf.line = line;
    out.push_back(std::move(tf));
    return Status::ok();
  });
  if (!s.is_ok()) return s;
  if (out.empty()) return no_entries(name, "timestamp_ns,filename");
  return out;
}

Result<KittiCalib> parse_kitti_calib(std::string_view text, const std::string& name) {
  KittiCalib k;
  int p0_line = 0;
  Status s = for_each_entry(text, [&](int line, std::string_view l) -> Status {
    const auto f = split_blanks(l);
    if (f.empty() || f[0] != "P0:") return Status::ok();
    if (p0_line != 0) {
      return line_error(name, line,
                        "second P0 line (first on line " + std::to_string(p0_line) + ")");
    }
    if (f.size() != 1 + kKittiPoseFields) {
      return line_error(
          name, line,
          "expected 'P0:' and 12 numbers, found " + std::to_string(f.size() - 1) + " fields");
    }
    std::array<double, kKittiPoseFields> p{};
    for (std::size_t i = 0; i < kKittiPoseFields; ++i) {
      if (!parse_double(f[i + 1], p[i])) {
        return line_error(name, line, "P0: bad number '" + shown(f[i + 1]) + "'");
      }
    }
    k = KittiCalib{p[0], p[5], p[2], p[6]};
    if (!(k.fx > 0.0) || !(k.fy > 0.0)) {
      return line_error(name, line,
                        "P0: focal lengths must be > 0 (found fx " + std::to_string(k.fx) +
                            ", fy " + std::to_string(k.fy) + ")");
    }
    p0_line = line;
    return Status::ok();
  });
  if (!s.is_ok()) return s;
  if (p0_line == 0)
    return input_error(name + ": no 'P0:' line (expected the left camera's 3x4 projection)");
  return k;
}

Result<std::vector<double>> parse_kitti_times(std::string_view text, const std::string& name) {
  std::vector<double> out;
  std::int64_t prev_ns = 0;
  int prev_line = 0;
  Status s = for_each_entry(text, [&](int line, std::string_view l) -> Status {
    const auto f = split_blanks(l);
    double t = 0.0;
    std::int64_t t_ns = 0;
    if (f.size() != 1 || !parse_double(f[0], t) || !seconds_to_ns(t, t_ns)) {
      return line_error(name, line, "expected one time in seconds, found '" + shown(l) + "'");
    }
    if (Status m = check_increasing(name, line, t_ns, prev_ns, prev_line); !m.is_ok()) return m;
    prev_ns = t_ns;
    prev_line = line;
    out.push_back(t);
    return Status::ok();
  });
  if (!s.is_ok()) return s;
  if (out.empty()) return no_entries(name, "seconds");
  return out;
}

Result<std::vector<SE3d>> parse_kitti_poses(std::string_view text, const std::string& name) {
  std::vector<SE3d> out;
  Status s = for_each_entry(text, [&](int line, std::string_view l) -> Status {
    const auto f = split_blanks(l);
    if (f.size() != kKittiPoseFields) {
      return line_error(name, line,
                        "expected 12 numbers (row-major 3x4 T_w_c), found " +
                            std::to_string(f.size()) + " fields");
    }
    Eigen::Matrix<double, 3, 4> m;
    for (std::size_t i = 0; i < kKittiPoseFields; ++i) {
      if (!parse_double(f[i],
                        m(static_cast<Eigen::Index>(i / 4), static_cast<Eigen::Index>(i % 4)))) {
        return line_error(name, line, "bad number '" + shown(f[i]) + "'");
      }
    }
    const Eigen::Matrix3d r = m.leftCols<3>();
    const double err = (r.transpose() * r - Eigen::Matrix3d::Identity()).cwiseAbs().maxCoeff();
    if (!(err <= kRotationTolerance) || !(r.determinant() > 0.0)) {
      return line_error(name, line, "the 3x3 block is not a rotation matrix");
    }
    SE3d T = SE3d::Identity();
    T.linear() = r;
    T.translation() = m.col(3);
    out.push_back(T);
    return Status::ok();
  });
  if (!s.is_ok()) return s;
  if (out.empty()) return no_entries(name, "12 numbers");
  return out;
}

Result<Trajectory> parse_tum_trajectory(std::string_view text, const std::string& name) {
  Trajectory traj;
  traj.source = name;
  int prev_line = 0;
  Status s = for_each_entry(text, [&](int line, std::string_view l) -> Status {
    const auto f = split_blanks(l);
    if (f.size() != kTumPoseFields) {
      return line_error(
          name, line,
          "expected 't tx ty tz qx qy qz qw', found " + std::to_string(f.size()) + " fields");
    }
    StampedPose p;
    if (!parse_seconds_ns(f[0], p.t_ns)) {
      return line_error(name, line, "bad timestamp '" + shown(f[0]) + "'");
    }
    std::array<double, kTumPoseFields - 1> v{};
    for (std::size_t i = 0; i < v.size(); ++i) {
      if (!parse_double(f[i + 1], v[i])) {
        return line_error(name, line, "bad number '" + shown(f[i + 1]) + "'");
      }
    }
    Eigen::Quaterniond q;
    if (!unit_quaternion(v[6], v[3], v[4], v[5], q)) {
      return line_error(name, line, "quaternion (qx qy qz qw) is not of unit norm");
    }
    p.T_w_c = make_se3(q, Eigen::Vector3d(v[0], v[1], v[2]));
    return add_sample(traj, p, name, line, prev_line);
  });
  if (!s.is_ok()) return s;
  if (traj.poses.empty()) return no_entries(name, "t tx ty tz qx qy qz qw");
  return traj;
}

Result<Trajectory> parse_euroc_groundtruth(std::string_view text, const std::string& name) {
  Trajectory traj;
  traj.source = name;
  int prev_line = 0;
  Status s = for_each_entry(text, [&](int line, std::string_view l) -> Status {
    const auto f = split_commas(l);
    if (f.size() < kEurocGtMinFields) {
      return line_error(name, line,
                        "expected 'timestamp_ns, p_x, p_y, p_z, q_w, q_x, q_y, q_z, "
                        "...', found " +
                            std::to_string(f.size()) + " fields");
    }
    StampedPose p;
    if (!parse_int64(f[0], p.t_ns) || p.t_ns < 0) {
      return line_error(name, line, "bad timestamp '" + shown(f[0]) + "' (expected integer ns)");
    }
    std::array<double, kEurocGtMinFields - 1> v{};
    for (std::size_t i = 0; i < v.size(); ++i) {
      if (!parse_double(f[i + 1], v[i])) {
        return line_error(name, line, "bad number '" + shown(f[i + 1]) + "'");
      }
    }
    Eigen::Quaterniond q;
    if (!unit_quaternion(v[3], v[4], v[5], v[6], q)) {
      return line_error(name, line, "quaternion (q_w q_x q_y q_z) is not of unit norm");
    }
    p.T_w_c = make_se3(q, Eigen::Vector3d(v[0], v[1], v[2]));
    return add_sample(traj, p, name, line, prev_line);
  });
  if (!s.is_ok()) return s;
  if (traj.poses.empty())
    return no_entries(name, "timestamp_ns, p_x, p_y, p_z, q_w, q_x, q_y, q_z");
  return traj;
}

Result<EurocSensor> parse_euroc_sensor(std::string_view text, const std::string& name) {
  EurocSensor out;
  std::vector<double> v;

  const KeyHit model = find_key(text, "camera_model");
  if (model.line != 0 && read_scalar(text, model) != "pinhole") {
    return line_error(
        name, model.line,
        "camera_model: expected 'pinhole', found '" + shown(read_scalar(text, model)) + "'");
  }
  const KeyHit res = find_key(text, "resolution");
  if (res.line == 0) return input_error(name + ": missing key 'resolution' ([width, height])");
  if (Status s = read_list(text, res, name, "resolution", 2, v); !s.is_ok()) return s;
  if (!(v[0] >= 1.0 && v[0] <= 1e5 && v[1] >= 1.0 && v[1] <= 1e5) || v[0] != std::floor(v[0]) ||
      v[1] != std::floor(v[1])) {
    return line_error(name, res.line, "resolution: expected two positive integers");
  }
  out.width = static_cast<int>(v[0]);
  out.height = static_cast<int>(v[1]);

  const KeyHit intr = find_key(text, "intrinsics");
  if (intr.line == 0) return input_error(name + ": missing key 'intrinsics' ([fu, fv, cu, cv])");
  if (Status s = read_list(text, intr, name, "intrinsics", 4, v); !s.is_ok()) return s;
  if (!(v[0] > 0.0) || !(v[1] > 0.0)) {
    return line_error(name, intr.line, "intrinsics: focal lengths must be > 0");
  }
  out.fu = v[0];
  out.fv = v[1];
  out.cu = v[2];
  out.cv = v[3];

  const KeyHit dmodel = find_key(text, "distortion_model");
  if (dmodel.line != 0 && read_scalar(text, dmodel) != "radial-tangential") {
    return line_error(name, dmodel.line,
                      "distortion_model: expected 'radial-tangential', found '" +
                          shown(read_scalar(text, dmodel)) + "'");
  }
  const KeyHit dist = find_key(text, "distortion_coefficients");
  if (dist.line != 0) {
    if (Status s = read_list(text, dist, name, "distortion_coefficients", 4, v); !s.is_ok())
      return s;
    std::copy(v.begin(), v.end(), out.dist.begin());
  }

  const KeyHit rate = find_key(text, "rate_hz");
  if (rate.line != 0) {
    double r = 0.0;
    if (!parse_double(read_scalar(text, rate), r) || r < 0.0) {
      return line_error(
          name, rate.line,
          "rate_hz: expected a number >= 0, found '" + shown(read_scalar(text, rate)) + "'");
    }
    out.rate_hz = r;
  }

  const KeyHit tbs = find_key(text, "T_BS");
  if (tbs.line == 0) return input_error(name + ": missing key 'T_BS' (body-sensor extrinsic)");
  const KeyHit data = find_key(text, "data", tbs.value_pos);
  if (data.line == 0) return line_error(name, tbs.line, "T_BS: missing 'data: [16 numbers]'");
  if (Status s = read_list(text, data, name, "T_BS.data", kEurocSensorMatrix, v); !s.is_ok()) {
    return s;
  }
  Eigen::Matrix4d m;
  for (std::size_t i = 0; i < kEurocSensorMatrix; ++i) {
    m(static_cast<Eigen::Index>(i / 4), static_cast<Eigen::Index>(i % 4)) = v[i];
  }
  const Eigen::Matrix3d r = m.topLeftCorner<3, 3>();
  const double err = (r.transpose() * r - Eigen::Matrix3d::Identity()).cwiseAbs().maxCoeff();
  if (!(err <= kRotationTolerance) || !(r.determinant() > 0.0)) {
    return line_error(name, data.line, "T_BS: the 3x3 block is not a rotation matrix");
  }
  out.T_b_s = SE3d::Identity();
  out.T_b_s.linear() = r;
  out.T_b_s.translation() = m.topRightCorner<3, 1>();
  return out;
}

Result<std::string> read_text_file(const std::string& path) {
  std::error_code ec;
  if (!std::filesystem::exists(path, ec)) return input_error(path + ": file not found");
  if (std::filesystem::is_directory(path, ec))
    return input_error(path + ": is a directory, expected a file");
  const std::uintmax_t size = std::filesystem::file_size(path, ec);
  if (!ec && size > kMaxTextFileBytes) {
    return input_error(path + ": too large for an index file (" + std::to_string(size) + " bytes)");
  }
  std::ifstream in(path, std::ios::binary);
  if (!in) return input_error(path + ": cannot open for reading");
  std::ostringstream ss;
  ss << in.rdbuf();
  if (in.bad()) return input_error(path + ": read error");
  return ss.str();
}

}  // namespace mer::hal
