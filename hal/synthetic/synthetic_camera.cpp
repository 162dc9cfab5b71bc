#include "hal/synthetic/synthetic_camera.h"

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cmath>
#include <numbers>
#include <random>
#include <thread>

#include "platform/clock.h"

namespace mer::hal {
namespace {

constexpr std::array<std::string_view, 1> kScenarios{"room_orbit"};
constexpr std::size_t kNoiseTableSize = 1 << 16;  // noise values, cycled with a per-frame offset
constexpr int kShapesPerWall = 160;               // texture primitives per wall
constexpr double kNsPerS = 1e9;

// Portable normal deviates (std::normal_distribution differs between standard libraries).
double normal_deviate(std::mt19937& rng) {
  constexpr double kTwoPi = 2.0 * std::numbers::pi;
  const double u1 = (static_cast<double>(rng()) + 1.0) / 4294967297.0;
  const double u2 = static_cast<double>(rng()) / 4294967296.0;
  return std::sqrt(-2.0 * std::log(u1)) * std::cos(kTwoPi * u2);
}

double uniform(std::mt19937& rng, double lo, double hi) {
  return lo + (hi - lo) * (static_cast<double>(rng()) / 4294967296.0);
}

// A wall texture: smooth gradient plus random rectangles and discs of random grey levels.
std::vector<std::uint8_t> make_texture(int size, std::mt19937& rng) {
  std::vector<std::uint8_t> tex(static_cast<std::size_t>(size) * static_cast<std::size_t>(size));
  const double g0 = uniform(rng, 60, 190);
  const double gx = uniform(rng, -60, 60);
  const double gy = uniform(rng, -60, 60);
  for (int y = 0; y < size; ++y) {
    for (int x = 0; x < size; ++x) {
      const double v = g0 + gx * x / size + gy * y / size;
      tex[static_cast<std::size_t>(y * size + x)] =
          static_cast<std::uint8_t>(std::clamp(v, 0.0, 255.0));
    }
  }
  for (int k = 0; k < kShapesPerWall; ++k) {
    const auto level = static_cast<std::uint8_t>(uniform(rng, 0, 256));
    const double cx = uniform(rng, 0, size);
    const double cy = uniform(rng, 0, size);
    const double r = uniform(rng, 0.01, 0.06) * size;
    const bool disc = (rng() & 1U) != 0U;
    const double ax = r * uniform(rng, 0.5, 1.5);
    const double ay = r * uniform(rng, 0.5, 1.5);
    const int x0 = std::max(0, static_cast<int>(cx - ax));
    const int x1 = std::min(size - 1, static_cast<int>(cx + ax));
    const int y0 = std::max(0, static_cast<int>(cy - ay));
    const int y1 = std::min(size - 1, static_cast<int>(cy + ay));
    for (int y = y0; y <= y1; ++y) {
      for (int x = x0; x <= x1; ++x) {
        if (disc) {
          const double dx = (x - cx) / ax;
          const double dy = (y - cy) / ay;
          if (dx * dx + dy * dy > 1.0) continue;
        }
        tex[static_cast<std::size_t>(y * size + x)] = level;
      }
    }
  }
  return tex;
}

}  // namespace

std::span<const std::string_view> synthetic_scenarios() {
  return kScenarios;
}

SyntheticCamera::SyntheticCamera(std::string scenario, const SyntheticOptions& opts, bool paced)
    : scenario_(std::move(scenario)), opts_(opts), paced_(paced) {}

Status SyntheticCamera::open(std::size_t pool_size) {
  if (std::find(kScenarios.begin(), kScenarios.end(), scenario_) == kScenarios.end()) {
    std::string names;
    for (auto s : kScenarios) names += (names.empty() ? "" : ", ") + std::string(s);
    return input_error("synthetic:" + scenario_ + ": unknown scenario (available: " + names + ")");
  }
  if (Status s = options::validate(opts_); !s.is_ok()) return s;
  if (pool_size == 0) return invalid_argument("synthetic camera: pool size must be > 0");

  const int w = opts_.width;
  const int h = opts_.height;
  const double f = 0.5 * w / std::tan(0.5 * opts_.fov_x_deg * std::numbers::pi / 180.0);
  intrinsics_ = CameraIntrinsics{w, h, f, f, 0.5 * (w - 1), 0.5 * (h - 1), {}, true};

  rays_.resize(static_cast<std::size_t>(w) * static_cast<std::size_t>(h) * 2);
  for (int v = 0; v < h; ++v) {
    for (int u = 0; u < w; ++u) {
      const std::size_t i = (static_cast<std::size_t>(v) * static_cast<std::size_t>(w) +
                             static_cast<std::size_t>(u)) *
                            2;
      rays_[i] = static_cast<float>((u - intrinsics_.cx) / f);
      rays_[i + 1] = static_cast<float>((v - intrinsics_.cy) / f);
    }
  }
  std::mt19937 rng(static_cast<std::uint32_t>(opts_.seed));
  for (auto& tex : textures_) tex = make_texture(opts_.texture_size, rng);
  noise_.resize(kNoiseTableSize);
  for (auto& n : noise_) {
    n = static_cast<std::int8_t>(
        std::clamp(std::lround(normal_deviate(rng) * opts_.noise_sigma), -127L, 127L));
  }
  const bool depth = opts_.render_depth;
  pool_ = std::make_unique<FramePool>(pool_size, [w, h, depth](Frame& fr, std::size_t) {
    fr.gray = cv::Mat(h, w, CV_8UC1);
    if (depth) fr.depth = cv::Mat(h, w, CV_32FC1);
  });
  return Status::ok();
}

Status SyntheticCamera::start() {
  if (!pool_) return runtime_error("synthetic camera: start() before open()");
  next_seq_ = 0;
  start_wall_ns_ = platform::monotonic_now_ns();
  started_ = true;
  return Status::ok();
}

void SyntheticCamera::stop() {
  started_ = false;
}

CameraCapabilities SyntheticCamera::capabilities() const {
  return CameraCapabilities{paced_, opts_.render_depth, true, opts_.fps};
}

std::string SyntheticCamera::describe() const {
  char buf[160];
  std::snprintf(buf, sizeof buf, "synthetic:%s (%dx%d @ %g Hz, %d frames, seed %d)",
                scenario_.c_str(), opts_.width, opts_.height, opts_.fps, opts_.num_frames,
                opts_.seed);
  return buf;
}

SE3d SyntheticCamera::pose_at(double t_s) const {
  // room_orbit: a handheld-like orbit around the room centre, looking across the room,
  // one revolution every 20 s, with slow height and look-at wobble.
  constexpr double kPeriodS = 20.0;
  constexpr double kRadius = 0.8;
  constexpr double kEyeHeight = 1.3;
  const double a = 2.0 * std::numbers::pi * t_s / kPeriodS;
  const Eigen::Vector3d eye(kRadius * std::cos(a), kRadius * std::sin(a),
                            kEyeHeight + 0.1 * std::sin(2.3 * a));
  const Eigen::Vector3d target(eye.x() + std::cos(a + 1.2), eye.y() + std::sin(a + 1.2),
                               kEyeHeight + 0.15 * std::sin(1.7 * a));
  return look_at(eye, target, Eigen::Vector3d::UnitZ());
}

void SyntheticCamera::render(const SE3d& T_w_c, cv::Mat& gray, cv::Mat* depth,
                             std::uint64_t noise_offset) const {
  const Eigen::Matrix3f R = T_w_c.linear().cast<float>();
  const Eigen::Vector3f o = T_w_c.translation().cast<float>();
  const std::array<float, 3> lo{static_cast<float>(-0.5 * opts_.room_size_x),
                                static_cast<float>(-0.5 * opts_.room_size_y), 0.0F};
  const std::array<float, 3> hi{static_cast<float>(0.5 * opts_.room_size_x),
                                static_cast<float>(0.5 * opts_.room_size_y),
                                static_cast<float>(opts_.room_height)};
  const int tsize = opts_.texture_size;
  const float tmax = static_cast<float>(tsize - 1) - 1e-3F;
  const std::size_t noise_mask = kNoiseTableSize - 1;
  std::size_t noise_i = static_cast<std::size_t>(noise_offset * 7919U) & noise_mask;
  const bool noisy = opts_.noise_sigma > 0.0;

  for (int v = 0; v < gray.rows; ++v) {
    std::uint8_t* row = gray.ptr<std::uint8_t>(v);
    float* drow = (depth != nullptr && !depth->empty()) ? depth->ptr<float>(v) : nullptr;
    const float* ray =
        rays_.data() + static_cast<std::size_t>(v) * static_cast<std::size_t>(gray.cols) * 2;
    for (int u = 0; u < gray.cols; ++u, ray += 2) {
      const Eigen::Vector3f d = R * Eigen::Vector3f(ray[0], ray[1], 1.0F);
      // Exit distance through the box along each axis; the smallest one is the wall hit.
      float t = std::numeric_limits<float>::max();
      int axis = 0;
      int side = 0;
      for (int a = 0; a < 3; ++a) {
        if (std::abs(d[a]) < 1e-9F) continue;
        const int s = d[a] > 0.0F ? 1 : 0;
        const float ta = ((s != 0 ? hi[a] : lo[a]) - o[a]) / d[a];
        if (ta < t) {
          t = ta;
          axis = a;
          side = s;
        }
      }
      const Eigen::Vector3f p = o + t * d;
      const int pa = axis == 0 ? 1 : 0;
      const int qa = axis == 2 ? 1 : 2;
      const float fu = std::clamp((p[pa] - lo[pa]) / (hi[pa] - lo[pa]), 0.0F, 1.0F) * tmax;
      const float fv = std::clamp((p[qa] - lo[qa]) / (hi[qa] - lo[qa]), 0.0F, 1.0F) * tmax;
      const int iu = static_cast<int>(fu);
      const int iv = static_cast<int>(fv);
      const float au = fu - static_cast<float>(iu);
      const float av = fv - static_cast<float>(iv);
      const std::uint8_t* tex = textures_[static_cast<std::size_t>(axis * 2 + side)].data() +
                                static_cast<std::size_t>(iv) * static_cast<std::size_t>(tsize) +
                                static_cast<std::size_t>(iu);
      const float top = tex[0] + au * (static_cast<float>(tex[1]) - tex[0]);
      const float bot = tex[tsize] + au * (static_cast<float>(tex[tsize + 1]) - tex[tsize]);
      float value = top + av * (bot - top);
      if (noisy) {
        value += static_cast<float>(noise_[noise_i]);
        noise_i = (noise_i + 1) & noise_mask;
      }
      row[u] = static_cast<std::uint8_t>(std::clamp(value + 0.5F, 0.0F, 255.0F));
      if (drow != nullptr) drow[u] = t;  // ray has z = 1 in the camera: t is the depth
    }
  }
}

AcquireStatus SyntheticCamera::acquire(FrameHandle& out, std::int64_t timeout_ns) {
  if (!started_ || next_seq_ >= static_cast<std::uint64_t>(opts_.num_frames)) {
    return AcquireStatus::kEndOfStream;
  }
  const auto period_ns = static_cast<std::int64_t>(kNsPerS / opts_.fps);
  const std::int64_t t_ns = static_cast<std::int64_t>(next_seq_) * period_ns;
  if (paced_) {
    const std::int64_t due = start_wall_ns_ + t_ns;
    const std::int64_t wait = due - platform::monotonic_now_ns();
    if (wait > timeout_ns) {
      std::this_thread::sleep_for(std::chrono::nanoseconds(timeout_ns));
      return AcquireStatus::kTimeout;
    }
    if (wait > 0) std::this_thread::sleep_for(std::chrono::nanoseconds(wait));
  }
  const std::int64_t t_work = platform::monotonic_now_ns();
  FrameHandle h = pool_->acquire();
  if (!h) return AcquireStatus::kPoolEmpty;
  Frame& f = *h;
  f.seq = next_seq_;
  f.t_ns = t_ns;
  f.T_w_c_gt = pose_at(static_cast<double>(t_ns) / kNsPerS);
  f.has_ground_truth = true;
  render(f.T_w_c_gt, f.gray, opts_.render_depth ? &f.depth : nullptr, next_seq_);
  ++next_seq_;
  f.t_ready_ns = platform::monotonic_now_ns();
  f.produce_ns = f.t_ready_ns - t_work;
  out = std::move(h);
  return AcquireStatus::kFrame;
}

}  // namespace mer::hal
