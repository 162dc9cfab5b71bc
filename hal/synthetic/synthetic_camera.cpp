#include "hal/synthetic/synthetic_camera.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <numbers>
#include <random>
#include <thread>

#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "hal/synthetic/synthetic_internal.h"
#include "platform/clock.h"

namespace mer::hal {
namespace {

using synthetic_detail::kMinMipSize;
using synthetic_detail::kTwoPi;
using synthetic_detail::uniform;

constexpr std::array<std::string_view, 12> kScenarios{
    "room_orbit", "room_loop",           "room_kidnap",   "room_fast_rotation",
    "hall_drive", "hall_turn",           "room_explore",  "room_rotation",
    "corridor",   "room_kidnap_unknown", "room_repeated", "hall_repeated"};
constexpr std::size_t kNoiseTableSize = 1 << 16;  // noise values, cycled with a per-frame offset
constexpr int kShapesPerWall = 160;               // texture primitives per wall
constexpr double kNsPerS = 1e9;
constexpr double kBoxTextureMetres = 2.0;  // a texture tile spans this many metres on a box
constexpr std::size_t kMaxBoxes = 16;      // upper bound of num_boxes (options range)
constexpr float kTiny = 1e-9F;       // ray direction components below this: parallel to an axis
constexpr float kHuge = 1e30F;       // "no hit" distance and projection bound
constexpr float kNearPlane = 1e-3F;  // box corners closer than this count as behind
constexpr double kShapeRadiusMin = 0.01;  // texture shapes' radius, fraction of the texture side
constexpr double kShapeRadiusMax = 0.06;
constexpr double kHallBoxTextureMetres = 8.0;  // hall_drive: texture tile on a box, m
constexpr int kHallTextureScale = 4;           // hall_drive: texture_size multiplier
constexpr int kHallShapesPerWall = 3000;       // hall_drive: texture primitives per wall
constexpr double kHallShapeRadiusMin = 0.004;  // hall_drive: shape radius, fraction of the side
constexpr double kHallShapeRadiusMax = 0.02;
constexpr float kMinObliqueCos = 0.25F;  // obliquity taken into a pixel footprint at most 4x

// Portable normal deviates (std::normal_distribution differs between standard libraries).
double normal_deviate(std::mt19937& rng) {
  const double u1 = (static_cast<double>(rng()) + 1.0) / 4294967297.0;
  const double u2 = static_cast<double>(rng()) / 4294967296.0;
  return std::sqrt(-2.0 * std::log(u1)) * std::cos(kTwoPi * u2);
}

// A wall texture: smooth gradient plus random rectangles and discs of random grey levels.
std::vector<std::uint8_t> make_texture(int size, int shapes, double r_min, double r_max,
                                       std::mt19937& rng) {
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
  for (int k = 0; k < shapes; ++k) {
    const auto level = static_cast<std::uint8_t>(uniform(rng, 0, 256));
    const double cx = uniform(rng, 0, size);
    const double cy = uniform(rng, 0, size);
    const double r = uniform(rng, r_min, r_max) * size;
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

// The texture's mip pyramid: level 0 is `tex`, each next level a 2x2 box average.
std::vector<std::vector<std::uint8_t>> make_mips(std::vector<std::uint8_t> tex, int size) {
  std::vector<std::vector<std::uint8_t>> levels;
  levels.push_back(std::move(tex));
  for (int s = size / 2; s >= kMinMipSize; s /= 2) {
    const std::vector<std::uint8_t>& src = levels.back();
    const auto n = static_cast<std::size_t>(s);
    std::vector<std::uint8_t> dst(n * n);
    for (std::size_t y = 0; y < n; ++y) {
      for (std::size_t x = 0; x < n; ++x) {
        const std::size_t i = 2 * y * 2 * n + 2 * x;
        const int sum = src[i] + src[i + 1] + src[i + 2 * n] + src[i + 2 * n + 1];
        dst[y * n + x] = static_cast<std::uint8_t>((sum + 2) / 4);
      }
    }
    levels.push_back(std::move(dst));
  }
  return levels;
}

// A 64-bit mix (splitmix64): exposure-step signs from (seed, step index), no state.
std::uint64_t mix64(std::uint64_t x) {
  x += 0x9E3779B97F4A7C15ULL;
  x = (x ^ (x >> 30U)) * 0xBF58476D1CE4E5B9ULL;
  x = (x ^ (x >> 27U)) * 0x94D049BB133111EBULL;
  return x ^ (x >> 31U);
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
  kind_ = scenario_ == "room_loop"             ? Scenario::kLoop
          : scenario_ == "room_kidnap"         ? Scenario::kKidnap
          : scenario_ == "room_fast_rotation"  ? Scenario::kFastRotation
          : scenario_ == "hall_drive"          ? Scenario::kHallDrive
          : scenario_ == "hall_turn"           ? Scenario::kHallTurn
          : scenario_ == "room_explore"        ? Scenario::kRoomExplore
          : scenario_ == "room_rotation"       ? Scenario::kRoomRotation
          : scenario_ == "corridor"            ? Scenario::kCorridor
          : scenario_ == "room_kidnap_unknown" ? Scenario::kKidnapUnknown
          : scenario_ == "room_repeated"       ? Scenario::kRoomRepeated
          : scenario_ == "hall_repeated"       ? Scenario::kHallRepeated
                                               : Scenario::kOrbit;
  const bool hall = kind_ == Scenario::kHallDrive || kind_ == Scenario::kHallTurn ||
                    kind_ == Scenario::kHallRepeated;
  const bool corridor = kind_ == Scenario::kCorridor;
  // The scenarios before hall_turn keep their procedural textures and boxes bit for bit.
  const bool reproduction = static_cast<int>(kind_) >= static_cast<int>(Scenario::kHallTurn);
  const double sx = hall ? opts_.hall_size_x : corridor ? opts_.corridor_length : opts_.room_size_x;
  const double sy = hall ? opts_.hall_size_y : corridor ? opts_.corridor_width : opts_.room_size_y;
  const double sz = hall ? opts_.hall_height : corridor ? opts_.corridor_height : opts_.room_height;
  room_lo_ = {static_cast<float>(-0.5 * sx), static_cast<float>(-0.5 * sy), 0.0F};
  room_hi_ = {static_cast<float>(0.5 * sx), static_cast<float>(0.5 * sy), static_cast<float>(sz)};
  texture_size_ = opts_.texture_size * (hall ? kHallTextureScale : 1);
  box_texture_metres_ = static_cast<float>(hall ? kHallBoxTextureMetres : kBoxTextureMetres);
  // The rooms are seen at about one texel per pixel; the hall spans 1-60 m of depth and the
  // corridor 0.5-20 m: they would alias without levels.
  use_mips_ = hall || corridor;
  if (pool_size == 0) return invalid_argument("synthetic camera: pool size must be > 0");
  if (kind_ == Scenario::kHallTurn) {
    if (Status s = make_turn_path_checked(); !s.is_ok()) return s;
  }
  if (Status s = check_repeated_script(); !s.is_ok()) return s;

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
  const bool photo = opts_.texture == "photo" || (opts_.texture == "auto" && reproduction);
  photo_files_.clear();
  std::vector<cv::Mat> photos;
  if (photo) {
    if (Status s = load_wall_photos(rng, photos); !s.is_ok()) return s;
  }
  if (corridor) {
    if (!photo) {
      for (std::size_t k = 0; k < textures_.size(); ++k) {
        std::vector<std::uint8_t> tex =
            make_texture(texture_size_, kShapesPerWall, kShapeRadiusMin, kShapeRadiusMax, rng);
        photos.push_back(cv::Mat(texture_size_, texture_size_, CV_8UC1, tex.data()).clone());
      }
    }
    make_corridor_textures(photos, rng);
  } else if (photo) {
    make_photo_textures(photos, rng);
  } else {
    for (auto& tex : textures_) {
      tex.w = texture_size_;
      tex.h = texture_size_;
      tex.levels = make_mips(
          hall ? make_texture(texture_size_, kHallShapesPerWall, kHallShapeRadiusMin,
                              kHallShapeRadiusMax, rng)
               : make_texture(texture_size_, kShapesPerWall, kShapeRadiusMin, kShapeRadiusMax, rng),
          texture_size_);
    }
  }
  for (std::size_t k = 0; k < textures_.size(); ++k) {
    const auto a = k / 2;
    const std::size_t pa = a == 0 ? 1 : 0;
    const std::size_t qa = a == 2 ? 1 : 2;
    wall_texels_per_m_[k] =
        std::max(static_cast<float>(textures_[k].w) / (room_hi_[pa] - room_lo_[pa]),
                 static_cast<float>(textures_[k].h) / (room_hi_[qa] - room_lo_[qa]));
  }
  // Look-alike places: the panel is cut from the first wall's photo (or its texture).
  if (photos.empty()) {
    std::vector<std::uint8_t>& level0 = textures_[0].levels.front();
    const cv::Mat first(textures_[0].h, textures_[0].w, CV_8UC1, level0.data());
    make_panels(first);
  } else {
    make_panels(photos.front());
  }
  if (kind_ == Scenario::kHallDrive) {
    place_hall_boxes(rng());
  } else if (!reproduction) {
    place_boxes(rng());
  } else if (corridor) {
    boxes_.clear();
  } else {
    place_boxes_clear_of_path(rng(), hall);
  }
  if (!panels_.empty()) {
    for (std::size_t b = 1; b < boxes_.size(); b += 2) boxes_[b].texture = kPanelTexture;
  }
  noise_.resize(kNoiseTableSize);
  for (auto& n : noise_) {
    n = static_cast<std::int8_t>(
        std::clamp(std::lround(normal_deviate(rng) * opts_.noise_sigma), -127L, 127L));
  }
  if (opts_.exposure_time_s > 0.0) {
    blur_scratch_ = cv::Mat(h, w, CV_8UC1);
    blur_sum_.assign(static_cast<std::size_t>(w) * static_cast<std::size_t>(h), 0);
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

void SyntheticCamera::render(const SE3d& T_w_c, cv::Mat& gray, cv::Mat* depth,
                             std::uint64_t noise_offset, float gain) const {
  render_impl(T_w_c, gray, depth, noise_offset, gain, true);
}

float SyntheticCamera::sample_texture(const Texture& texture, int level, float fu, float fv) {
  const int wl = texture.w >> level;
  const int hl = texture.h >> level;
  const float scale = 1.0F / static_cast<float>(1 << level);
  const float lmax_u = static_cast<float>(wl - 1) - 1e-3F;
  const float lmax_v = static_cast<float>(hl - 1) - 1e-3F;
  fu = std::min(std::max(fu * scale - 0.5F * (1.0F - scale), 0.0F), lmax_u);
  fv = std::min(std::max(fv * scale - 0.5F * (1.0F - scale), 0.0F), lmax_v);
  const int iu = static_cast<int>(fu);
  const int iv = static_cast<int>(fv);
  const float au = fu - static_cast<float>(iu);
  const float av = fv - static_cast<float>(iv);
  const std::uint8_t* t = texture.levels[static_cast<std::size_t>(level)].data() +
                          static_cast<std::size_t>(iv) * static_cast<std::size_t>(wl) +
                          static_cast<std::size_t>(iu);
  const float top = t[0] + au * (static_cast<float>(t[1]) - t[0]);
  const float bot = t[wl] + au * (static_cast<float>(t[wl + 1]) - t[wl]);
  return top + av * (bot - top);
}

std::size_t SyntheticCamera::cull_boxes(const Eigen::Matrix3f& R, const Eigen::Vector3f& o,
                                        int cols, int rows, std::span<BoxWindow> out) const {
  std::size_t num_windows = 0;
  const Eigen::Matrix3f R_c_w = R.transpose();
  for (const SceneBox& b : boxes_) {
    if (num_windows == out.size()) break;
    float u_min = kHuge, u_max = -kHuge, v_min = kHuge, v_max = -kHuge;
    int behind = 0;
    for (int c = 0; c < 8; ++c) {
      const Eigen::Vector3f corner((c & 1) ? b.hi.x() : b.lo.x(), (c & 2) ? b.hi.y() : b.lo.y(),
                                   (c & 4) ? b.hi.z() : b.lo.z());
      const Eigen::Vector3f p_c = R_c_w * (corner - o);
      if (p_c.z() <= kNearPlane) {
        ++behind;
        continue;
      }
      const float u = static_cast<float>(intrinsics_.fx) * p_c.x() / p_c.z() +
                      static_cast<float>(intrinsics_.cx);
      const float v = static_cast<float>(intrinsics_.fy) * p_c.y() / p_c.z() +
                      static_cast<float>(intrinsics_.cy);
      u_min = std::min(u_min, u);
      u_max = std::max(u_max, u);
      v_min = std::min(v_min, v);
      v_max = std::max(v_max, v);
    }
    if (behind == 8) continue;
    BoxWindow w{&b, 0, cols - 1, 0, rows - 1};
    if (behind == 0) {
      w.u0 = static_cast<int>(std::max(0.0F, std::floor(u_min) - 1.0F));
      w.u1 = static_cast<int>(std::min(static_cast<float>(cols - 1), std::ceil(u_max) + 1.0F));
      w.v0 = static_cast<int>(std::max(0.0F, std::floor(v_min) - 1.0F));
      w.v1 = static_cast<int>(std::min(static_cast<float>(rows - 1), std::ceil(v_max) + 1.0F));
      if (w.u0 > w.u1 || w.v0 > w.v1) continue;
    }
    out[num_windows++] = w;
  }
  return num_windows;
}

void SyntheticCamera::render_impl(const SE3d& T_w_c, cv::Mat& gray, cv::Mat* depth,
                                  std::uint64_t noise_offset, float gain, bool add_noise) const {
  const Eigen::Matrix3f R = T_w_c.linear().cast<float>();
  const Eigen::Vector3f o = T_w_c.translation().cast<float>();
  const std::array<float, 3>& lo = room_lo_;
  const std::array<float, 3>& hi = room_hi_;
  const float inv_f = 1.0F / static_cast<float>(intrinsics_.fx);
  const std::size_t noise_mask = kNoiseTableSize - 1;
  std::size_t noise_i = static_cast<std::size_t>(noise_offset * 7919U) & noise_mask;
  const bool noisy = add_noise && opts_.noise_sigma > 0.0;

  // Mip level for ray `d` meeting, at depth t, a surface with `texels_per_m` level-0 texels
  // per metre whose normal is world axis `normal_axis` (0 without mips).
  auto level_for = [&](const Eigen::Vector3f& d, float t, float texels_per_m, int normal_axis,
                       int num_levels) {
    if (!use_mips_) return 0;
    const float cos_n = std::abs(d[normal_axis]) / d.norm();
    const float footprint = t * inv_f * texels_per_m / std::max(cos_n, kMinObliqueCos);
    if (footprint <= 1.0F) return 0;
    return std::min(static_cast<int>(std::log2(footprint)), num_levels - 1);
  };
  // Repeating texture coordinate for box faces, along a texture side of `size` texels.
  const float box_texture_metres = box_texture_metres_;
  // `texels_per_m` is the same along both sides (the smaller side spans box_texture_metres).
  auto wrap = [](float metres, float texels_per_m, int size) {
    const float tmax = static_cast<float>(size - 1) - 1e-3F;
    const float f = metres * texels_per_m;
    return f - tmax * std::floor(f / tmax);
  };

  // Per-frame culling: each box is only tested for the pixels inside its projected
  // bounding rectangle (the whole image when a corner is behind the camera).
  std::array<BoxWindow, kMaxBoxes> windows{};
  const std::size_t num_windows = cull_boxes(R, o, gray.cols, gray.rows, windows);

  for (int v = 0; v < gray.rows; ++v) {
    std::uint8_t* row = gray.ptr<std::uint8_t>(v);
    float* drow = (depth != nullptr && !depth->empty()) ? depth->ptr<float>(v) : nullptr;
    const float* ray =
        rays_.data() + static_cast<std::size_t>(v) * static_cast<std::size_t>(gray.cols) * 2;
    for (int u = 0; u < gray.cols; ++u, ray += 2) {
      const Eigen::Vector3f d = R * Eigen::Vector3f(ray[0], ray[1], 1.0F);
      const Eigen::Vector3f inv(std::abs(d.x()) > kTiny ? 1.0F / d.x() : kHuge,
                                std::abs(d.y()) > kTiny ? 1.0F / d.y() : kHuge,
                                std::abs(d.z()) > kTiny ? 1.0F / d.z() : kHuge);
      // Exit distance through the room along each axis; the smallest one is the wall hit.
      float t = kHuge;
      int axis = 0;
      int side = 0;
      for (int a = 0; a < 3; ++a) {
        const int s = d[a] > 0.0F ? 1 : 0;
        const float ta = ((s != 0 ? hi[a] : lo[a]) - o[a]) * inv[a];
        if (ta > 0.0F && ta < t) {
          t = ta;
          axis = a;
          side = s;
        }
      }
      // Nearest box in front of the wall (slab test).
      const SceneBox* hit_box = nullptr;
      int box_axis = 0;
      for (std::size_t k = 0; k < num_windows; ++k) {
        const BoxWindow& w = windows[k];
        if (u < w.u0 || u > w.u1 || v < w.v0 || v > w.v1) continue;
        const SceneBox& b = *w.box;
        float t_near = 0.0F;
        float t_far = kHuge;
        int near_axis = 0;
        for (int a = 0; a < 3; ++a) {
          float t1 = (b.lo[a] - o[a]) * inv[a];
          float t2 = (b.hi[a] - o[a]) * inv[a];
          if (t1 > t2) std::swap(t1, t2);
          if (t1 > t_near) {
            t_near = t1;
            near_axis = a;
          }
          t_far = std::min(t_far, t2);
        }
        if (t_near > 0.0F && t_near <= t_far && t_near < t) {
          t = t_near;
          hit_box = &b;
          box_axis = near_axis;
        }
      }
      const Eigen::Vector3f p = o + t * d;
      float value = 0.0F;
      if (hit_box != nullptr) {
        const int pa = box_axis == 0 ? 1 : 0;
        const int qa = box_axis == 2 ? 1 : 2;
        const Texture& tex = hit_box->texture == kPanelTexture
                                 ? panel_
                                 : textures_[static_cast<std::size_t>(hit_box->texture)];
        const float box_texels_per_m =
            static_cast<float>(std::min(tex.w, tex.h) - 1) / box_texture_metres;
        value = sample_texture(
            tex, level_for(d, t, box_texels_per_m, box_axis, static_cast<int>(tex.levels.size())),
            wrap(p[pa] - hit_box->lo[pa], box_texels_per_m, tex.w),
            wrap(p[qa] - hit_box->lo[qa], box_texels_per_m, tex.h));
      } else {
        const int pa = axis == 0 ? 1 : 0;
        const int qa = axis == 2 ? 1 : 2;
        const auto wall = static_cast<std::size_t>(axis * 2 + side);
        const WallPanel* panel = nullptr;
        for (std::size_t k = wall_panels_[wall]; k < wall_panels_[wall + 1]; ++k) {
          const WallPanel& pn = panels_[k];
          if (p[pa] >= pn.u0 && p[pa] < pn.u1 && p[qa] >= pn.v0 && p[qa] < pn.v1) {
            panel = &pn;
            break;
          }
        }
        if (panel == nullptr) {
          const Texture& tex = textures_[wall];
          const float tmax_u = static_cast<float>(tex.w - 1) - 1e-3F;
          const float tmax_v = static_cast<float>(tex.h - 1) - 1e-3F;
          const float fu = std::clamp((p[pa] - lo[pa]) / (hi[pa] - lo[pa]), 0.0F, 1.0F) * tmax_u;
          const float fv = std::clamp((p[qa] - lo[qa]) / (hi[qa] - lo[qa]), 0.0F, 1.0F) * tmax_v;
          value = sample_texture(
              tex,
              level_for(d, t, wall_texels_per_m_[wall], axis, static_cast<int>(tex.levels.size())),
              fu, fv);
        } else {
          const float tmax_u = static_cast<float>(panel_.w - 1) - 1e-3F;
          const float tmax_v = static_cast<float>(panel_.h - 1) - 1e-3F;
          float across = (p[pa] - panel->u0) / (panel->u1 - panel->u0);
          if (panel->mirror) across = 1.0F - across;
          const float fu = std::clamp(across, 0.0F, 1.0F) * tmax_u;
          const float fv =
              std::clamp((p[qa] - panel->v0) / (panel->v1 - panel->v0), 0.0F, 1.0F) * tmax_v;
          value = sample_texture(
              panel_,
              level_for(d, t, panel_texels_per_m_, axis, static_cast<int>(panel_.levels.size())),
              fu, fv);
        }
      }
      value *= gain;
      if (noisy) {
        value += static_cast<float>(noise_[noise_i]);
        noise_i = (noise_i + 1) & noise_mask;
      }
      row[u] = static_cast<std::uint8_t>(std::clamp(value + 0.5F, 0.0F, 255.0F));
      if (drow != nullptr) drow[u] = t;  // ray has z = 1 in the camera: t is the depth
    }
  }
}

double SyntheticCamera::gain_at(double t_s) const {
  double gain = 1.0 + opts_.exposure_amplitude * std::sin(kTwoPi * t_s / opts_.exposure_period_s);
  if (opts_.exposure_step_every_s > 0.0 && t_s > 0.0) {
    // Auto-exposure jumps: at each step the level moves one notch up or down (the sign from
    // the seed and the step index), kept within +-2 notches.
    const auto steps = static_cast<std::int64_t>(std::floor(t_s / opts_.exposure_step_every_s));
    int level = 0;
    for (std::int64_t i = 1; i <= steps; ++i) {
      const std::uint64_t key =
          (static_cast<std::uint64_t>(opts_.seed) << 32U) ^ static_cast<std::uint64_t>(i);
      int d = (mix64(key) & 1U) != 0U ? 1 : -1;
      if (std::abs(level + d) > 2) d = -d;
      level += d;
    }
    gain *= std::pow(1.0 + opts_.exposure_step_size, level);
  }
  return gain;
}

void SyntheticCamera::render_blurred(double t_s, Frame& f, float gain) {
  // The exposure [t - e/2, t + e/2] sampled at blur_samples evenly spaced instants, each
  // rendered without noise; the mean gets the noise a single render would. The middle
  // sample of an odd count is exactly t: it also renders the depth.
  const int k_samples = opts_.blur_samples;
  const double e = opts_.exposure_time_s;
  std::fill(blur_sum_.begin(), blur_sum_.end(), std::uint16_t{0});
  const bool depth = opts_.render_depth;
  const bool odd = (k_samples % 2) == 1;
  for (int k = 0; k < k_samples; ++k) {
    const double t_k = t_s + e * ((k + 0.5) / k_samples - 0.5);
    const ScenarioSample s = sample_at(t_k);
    if (!s.visible) continue;  // lens covered for part of the exposure: adds black
    const bool middle = odd && k == k_samples / 2;
    render_impl(middle ? f.T_w_c_gt : s.T_w_c, blur_scratch_,
                (depth && middle) ? &f.depth : nullptr, 0, gain, false);
    std::uint16_t* sum = blur_sum_.data();
    for (int v = 0; v < blur_scratch_.rows; ++v) {
      const std::uint8_t* row = blur_scratch_.ptr<std::uint8_t>(v);
      for (int u = 0; u < blur_scratch_.cols; ++u) *sum++ += row[u];
    }
  }
  if (depth && !odd) render_impl(f.T_w_c_gt, blur_scratch_, &f.depth, 0, gain, false);
  const std::size_t noise_mask = kNoiseTableSize - 1;
  std::size_t noise_i = static_cast<std::size_t>(f.seq * 7919U) & noise_mask;
  const bool noisy = opts_.noise_sigma > 0.0;
  const auto n = static_cast<float>(k_samples);
  const std::uint16_t* sum = blur_sum_.data();
  for (int v = 0; v < f.gray.rows; ++v) {
    std::uint8_t* row = f.gray.ptr<std::uint8_t>(v);
    for (int u = 0; u < f.gray.cols; ++u) {
      float value = static_cast<float>(*sum++) / n;
      if (noisy) {
        value += static_cast<float>(noise_[noise_i]);
        noise_i = (noise_i + 1) & noise_mask;
      }
      row[u] = static_cast<std::uint8_t>(std::clamp(value + 0.5F, 0.0F, 255.0F));
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
  const std::int64_t cpu_work = platform::thread_cpu_ns();
  FrameHandle h = pool_->acquire();
  if (!h) return AcquireStatus::kPoolEmpty;
  Frame& f = *h;
  f.seq = next_seq_;
  f.t_ns = t_ns;
  const double t_s = static_cast<double>(t_ns) / kNsPerS;
  const ScenarioSample sample = sample_at(t_s);
  f.T_w_c_gt = sample.T_w_c;
  f.has_ground_truth = sample.visible;
  if (sample.visible) {
    const double gain = gain_at(t_s);
    if (opts_.exposure_time_s > 0.0) {
      render_blurred(t_s, f, static_cast<float>(gain));
    } else {
      render(f.T_w_c_gt, f.gray, opts_.render_depth ? &f.depth : nullptr, next_seq_,
             static_cast<float>(gain));
    }
  } else {
    // Blacked out (lens covered): an all-black image and no depth.
    f.gray.setTo(0);
    if (opts_.render_depth) f.depth.setTo(0.0F);
  }
  ++next_seq_;
  f.t_ready_ns = platform::monotonic_now_ns();
  f.produce_ns = f.t_ready_ns - t_work;
  f.produce_cpu_ns = platform::thread_cpu_ns() - cpu_work;
  out = std::move(h);
  return AcquireStatus::kFrame;
}

}  // namespace mer::hal
