// The synthetic camera's scenes (SyntheticCamera, synthetic_camera.h): boxes placed clear of
// the camera's path, look-alike panels, and textures made from the wall photographs.
#include <algorithm>
#include <cmath>
#include <filesystem>
#include <numbers>
#include <random>

#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "hal/synthetic/synthetic_camera.h"
#include "hal/synthetic/synthetic_internal.h"

namespace mer::hal {
namespace {

using synthetic_detail::kLoopSemiAxisX;
using synthetic_detail::kLoopSemiAxisY;
using synthetic_detail::kMinMipSize;
using synthetic_detail::uniform;

constexpr double kBoxClearance = 0.45;      // boxes stay this far outside the camera paths, m
constexpr double kWallMargin = 0.1;         // boxes stay this far from the walls, m
constexpr int kBoxPlacementTries = 200;     // rejection-sampling budget per box
constexpr double kDriveBoxClearance = 3.0;  // hall_drive: boxes stay this far from the path, m
constexpr double kDriveBoxMinSide = 2.0;    // hall_drive: box footprint side range, m
constexpr double kDriveBoxMaxSide = 8.0;
constexpr double kDriveBoxMinHeight = 2.0;  // hall_drive: box height range, m
constexpr double kDriveBoxMaxHeight = 6.0;
constexpr double kBoxPathSampleS = 0.05;    // boxes are kept clear of the camera sampled so
constexpr double kBoxPathMaxS = 120.0;      // ... over at most this much of the sequence, s
constexpr double kRoomPathClearance = 0.6;  // new room scenarios: box clearance, m
constexpr double kFurnitureMinSide = 0.4;   // new room scenarios: box footprint side, m
constexpr double kFurnitureMaxSide = 1.2;
constexpr double kFurnitureMinHeight = 0.4;  // new room scenarios: box height, m
constexpr double kFurnitureMaxHeight = 1.8;
constexpr double kCorridorTexelsPerM = 160.0;  // corridor: texture density, texels per metre
constexpr double kCorridorWhite = 200.0;       // corridor: grey level of the painted walls
// Look-alike places (repeat_texture, room_repeated, hall_repeated).
constexpr double kRoomPanelW = 2.0;        // rooms and the corridor: panel width, m
constexpr double kRoomPanelH = 1.4;        // ... height, m
constexpr double kRoomPanelZ = 0.7;        // ... height of its lower edge, m
constexpr double kHallPanelW = 3.0;        // halls: panel width, m
constexpr double kHallPanelH = 2.4;        // ... height, m
constexpr double kHallPanelZ = 0.6;        // ... height of its lower edge, m
constexpr double kPanelFill = 0.9;         // copies sharing a wall fill at most this fraction
constexpr double kPanelFrameM = 0.05;      // the panel's dark frame, m
constexpr double kPanelFrameGrey = 30.0;   // ... its grey level
constexpr double kPanelKeepOut = 3.5;      // boxes keep off the floor this far out of a panel, m
constexpr double kPanelKeepOutSide = 0.3;  // ... and this far beyond its sides, m
constexpr std::uint32_t kPanelSalt = 0x2545F491U;  // the panel's crop: its own random stream

// A box standing on the floor: footprint centre (cx, cy), sides sx, sy, height sz, m.
SceneBox box_on_floor(double cx, double cy, double sx, double sy, double sz, int texture) {
  return SceneBox{
      Eigen::Vector3f(static_cast<float>(cx - 0.5 * sx), static_cast<float>(cy - 0.5 * sy), 0.0F),
      Eigen::Vector3f(static_cast<float>(cx + 0.5 * sx), static_cast<float>(cy + 0.5 * sy),
                      static_cast<float>(sz)),
      texture};
}

// Distance in the plane from (x, y) to the rectangle [-hx, hx] x [-hy, hy] (0 inside).
double rect_distance(double x, double y, double hx, double hy) {
  return std::hypot(std::max(std::abs(x) - hx, 0.0), std::max(std::abs(y) - hy, 0.0));
}

// Mip pyramid of a w x h texture: each next level a 2x2 box average, down to kMinMipSize.
std::vector<std::vector<std::uint8_t>> make_mips_rect(std::vector<std::uint8_t> tex, int w, int h) {
  std::vector<std::vector<std::uint8_t>> levels;
  levels.push_back(std::move(tex));
  for (int l = 1; (w >> l) >= kMinMipSize && (h >> l) >= kMinMipSize; ++l) {
    const std::vector<std::uint8_t>& src = levels.back();
    const auto sw = static_cast<std::size_t>(w >> (l - 1));
    const auto dw = static_cast<std::size_t>(w >> l);
    const auto dh = static_cast<std::size_t>(h >> l);
    std::vector<std::uint8_t> dst(dw * dh);
    for (std::size_t y = 0; y < dh; ++y) {
      for (std::size_t x = 0; x < dw; ++x) {
        const std::size_t i = 2 * y * sw + 2 * x;
        const int sum = src[i] + src[i + 1] + src[i + sw] + src[i + sw + 1];
        dst[y * dw + x] = static_cast<std::uint8_t>((sum + 2) / 4);
      }
    }
    levels.push_back(std::move(dst));
  }
  return levels;
}

// A random crop of `photo` with side `frac` of its smaller side and the aspect w : h,
// resized to w x h (grey, CV_8UC1).
cv::Mat photo_crop(const cv::Mat& photo, int w, int h, double frac, std::mt19937& rng) {
  const double aspect = static_cast<double>(w) / static_cast<double>(h);
  double ch = frac * std::min(photo.rows, static_cast<int>(photo.cols / aspect));
  ch = std::max(ch, 2.0);
  const double cw = std::min(static_cast<double>(photo.cols), ch * aspect);
  const int x0 = static_cast<int>(uniform(rng, 0.0, std::max(0.0, photo.cols - cw)));
  const int y0 = static_cast<int>(uniform(rng, 0.0, std::max(0.0, photo.rows - ch)));
  cv::Mat out;
  cv::resize(
      photo(cv::Rect(x0, y0, std::max(1, static_cast<int>(cw)), std::max(1, static_cast<int>(ch)))),
      out, cv::Size(w, h), 0.0, 0.0, cv::INTER_AREA);
  return out;
}

// True for file stems like "Name_3840x2160" (a resolution variant of another photo).
bool is_resolution_variant(const std::string& stem) {
  const std::size_t us = stem.rfind('_');
  if (us == std::string::npos) return false;
  const std::string tail = stem.substr(us + 1);
  const std::size_t x = tail.find('x');
  if (x == std::string::npos || x == 0 || x + 1 == tail.size()) return false;
  for (std::size_t i = 0; i < tail.size(); ++i) {
    if (i != x && (tail[i] < '0' || tail[i] > '9')) return false;
  }
  return true;
}

}  // namespace

void SyntheticCamera::make_panels(const cv::Mat& first) {
  // One framed panel, cut from `first`, and its copies: in rooms centred on the -x, +x, -y,
  // +y walls in turn, in halls and the corridor on the two long walls; copies sharing a wall
  // spread evenly along it. Every copy has the same size and texels.
  panels_.clear();
  wall_panels_.fill(0);
  panel_ = Texture{};
  const int n = opts_.repeat_texture;
  if (n <= 0) return;
  const bool hall = kind_ == Scenario::kHallDrive || kind_ == Scenario::kHallTurn ||
                    kind_ == Scenario::kHallRepeated;
  const bool corridor = kind_ == Scenario::kCorridor;
  std::array<double, 3> ext{};
  for (std::size_t a = 0; a < 3; ++a) ext[a] = room_hi_[a] - room_lo_[a];
  std::array<int, 4> order{0, 1, 2, 3};
  std::size_t num_walls = 4;
  if (hall || corridor) {
    order = ext[0] >= ext[1] ? std::array<int, 4>{2, 3, 0, 1} : std::array<int, 4>{0, 1, 2, 3};
    num_walls = 2;
  }
  std::array<int, 4> count{};
  for (int i = 0; i < n; ++i) ++count[static_cast<std::size_t>(order[i % num_walls])];
  double width = hall ? kHallPanelW : kRoomPanelW;
  for (std::size_t k = 0; k < 4; ++k) {
    if (count[k] > 0) width = std::min(width, kPanelFill * ext[k < 2 ? 1 : 0] / count[k]);
  }
  const double z0 = hall ? kHallPanelZ : kRoomPanelZ;
  const double z1 = std::min(z0 + (hall ? kHallPanelH : kRoomPanelH), ext[2] - 0.1);
  // The texture, at the walls' density.
  const double density = corridor ? kCorridorTexelsPerM : opts_.texture_size / ext[2];
  const int tw = std::max(kMinMipSize, static_cast<int>(std::lround(width * density)));
  const int th = std::max(kMinMipSize, static_cast<int>(std::lround((z1 - z0) * density)));
  std::mt19937 rng(static_cast<std::uint32_t>(opts_.seed) ^ kPanelSalt);
  cv::Mat canvas = photo_crop(first, tw, th, uniform(rng, 0.5, 0.9), rng);
  const int frame = std::max(1, static_cast<int>(std::lround(kPanelFrameM * density)));
  canvas.rowRange(0, std::min(frame, th)).setTo(kPanelFrameGrey);
  canvas.rowRange(std::max(0, th - frame), th).setTo(kPanelFrameGrey);
  canvas.colRange(0, std::min(frame, tw)).setTo(kPanelFrameGrey);
  canvas.colRange(std::max(0, tw - frame), tw).setTo(kPanelFrameGrey);
  cv::flip(canvas, canvas, 0);  // row 0 at the bottom, as on the walls
  panel_.w = tw;
  panel_.h = th;
  panel_.levels =
      make_mips_rect(std::vector<std::uint8_t>(canvas.datastart, canvas.dataend), tw, th);
  panel_texels_per_m_ = static_cast<float>(std::max(tw / width, th / (z1 - z0)));
  for (std::size_t k = 0; k < 4; ++k) {
    wall_panels_[k] = panels_.size();
    const std::size_t pa = k < 2 ? 1 : 0;
    for (int j = 0; j < count[k]; ++j) {
      const double centre = room_lo_[pa] + ext[pa] * (j + 0.5) / count[k];
      // Seen from inside, +u runs to the right on the -x and +y walls, to the left on the
      // others: their copies are mirrored so that every copy reads the same.
      panels_.push_back(WallPanel{static_cast<int>(k), static_cast<float>(centre - 0.5 * width),
                                  static_cast<float>(centre + 0.5 * width), static_cast<float>(z0),
                                  static_cast<float>(z1), k == 1 || k == 2});
    }
  }
  for (std::size_t k = 4; k < wall_panels_.size(); ++k) wall_panels_[k] = panels_.size();
}

void SyntheticCamera::place_boxes(std::uint32_t seed) {
  // Boxes stand on the floor, inside the room, and clear of every scripted camera path
  // (the orbit circle lies inside the loop ellipse, so clearing the ellipse clears both).
  std::mt19937 rng(seed);
  boxes_.clear();
  const double hx = 0.5 * opts_.room_size_x - kWallMargin;
  const double hy = 0.5 * opts_.room_size_y - kWallMargin;
  const double ax = kLoopSemiAxisX + kBoxClearance;
  const double ay = kLoopSemiAxisY + kBoxClearance;
  for (int b = 0; b < opts_.num_boxes; ++b) {
    for (int attempt = 0; attempt < kBoxPlacementTries; ++attempt) {
      const double sx = uniform(rng, 0.3, 0.8);
      const double sy = uniform(rng, 0.3, 0.8);
      const double sz = uniform(rng, 0.3, 1.2);
      const double cx = uniform(rng, -hx + 0.5 * sx, hx - 0.5 * sx);
      const double cy = uniform(rng, -hy + 0.5 * sy, hy - 0.5 * sy);
      // In ellipse-normalized coordinates the footprint is still an axis-aligned rectangle;
      // it clears the ellipse when its point closest to the centre lies outside it.
      const double nx = std::clamp(0.0, (cx - 0.5 * sx) / ax, (cx + 0.5 * sx) / ax);
      const double ny = std::clamp(0.0, (cy - 0.5 * sy) / ay, (cy + 0.5 * sy) / ay);
      const bool clear = nx * nx + ny * ny > 1.0;
      if (!clear) continue;
      boxes_.push_back(
          box_on_floor(cx, cy, sx, sy, sz, static_cast<int>(rng() % textures_.size())));
      break;
    }
  }
}

void SyntheticCamera::place_hall_boxes(std::uint32_t seed) {
  // Buildings and parked vehicles: boxes on the floor, clear of the drive by
  // kDriveBoxClearance on either side (inside the block or outside it).
  std::mt19937 rng(seed);
  boxes_.clear();
  const double hx = 0.5 * opts_.hall_size_x - kWallMargin;
  const double hy = 0.5 * opts_.hall_size_y - kWallMargin;
  const double r = drive_radius();
  const double ix = drive_half_x() - r;  // the path is the set at distance r from this rectangle
  const double iy = drive_half_y() - r;
  for (int b = 0; b < opts_.num_boxes; ++b) {
    for (int attempt = 0; attempt < kBoxPlacementTries; ++attempt) {
      const double sx = uniform(rng, kDriveBoxMinSide, kDriveBoxMaxSide);
      const double sy = uniform(rng, kDriveBoxMinSide, kDriveBoxMaxSide);
      const double sz = uniform(rng, kDriveBoxMinHeight, kDriveBoxMaxHeight);
      const double cx = uniform(rng, -hx + 0.5 * sx, hx - 0.5 * sx);
      const double cy = uniform(rng, -hy + 0.5 * sy, hy - 0.5 * sy);
      // Distance from the footprint to the inner rectangle (per-axis gaps), and from its
      // farthest corner.
      const double gap_x = std::max(0.0, std::abs(cx) - 0.5 * sx - ix);
      const double gap_y = std::max(0.0, std::abs(cy) - 0.5 * sy - iy);
      const double d_min = std::hypot(gap_x, gap_y);
      double d_max = 0.0;
      for (int c = 0; c < 4; ++c) {
        const double x = cx + ((c & 1) != 0 ? 0.5 : -0.5) * sx;
        const double y = cy + ((c & 2) != 0 ? 0.5 : -0.5) * sy;
        d_max = std::max(d_max, rect_distance(x, y, ix, iy));
      }
      const bool clear = d_min > r + kDriveBoxClearance || d_max < r - kDriveBoxClearance;
      if (!clear) continue;
      boxes_.push_back(
          box_on_floor(cx, cy, sx, sy, sz, static_cast<int>(rng() % textures_.size())));
      break;
    }
  }
}

void SyntheticCamera::place_boxes_clear_of_path(std::uint32_t seed, bool hall) {
  // Boxes on the floor, clear of every camera position of the sequence (sampled).
  std::mt19937 rng(seed);
  boxes_.clear();
  std::vector<Eigen::Vector2d> path;
  const double duration = std::min(kBoxPathMaxS, opts_.num_frames / opts_.fps);
  for (double t = 0.0; t <= duration + 1e-9; t += kBoxPathSampleS) {
    path.push_back(sample_at(t).T_w_c.translation().head<2>());
  }
  const double clearance = hall ? kDriveBoxClearance : kRoomPathClearance;
  const double side_lo = hall ? kDriveBoxMinSide : kFurnitureMinSide;
  const double side_hi = hall ? kDriveBoxMaxSide : kFurnitureMaxSide;
  const double z_lo = hall ? kDriveBoxMinHeight : kFurnitureMinHeight;
  const double z_hi = hall ? kDriveBoxMaxHeight : kFurnitureMaxHeight;
  const double hx = 0.5 * (room_hi_[0] - room_lo_[0]) - kWallMargin;
  const double hy = 0.5 * (room_hi_[1] - room_lo_[1]) - kWallMargin;
  for (int b = 0; b < opts_.num_boxes; ++b) {
    for (int attempt = 0; attempt < kBoxPlacementTries; ++attempt) {
      const double bx = uniform(rng, side_lo, side_hi);
      const double by = uniform(rng, side_lo, side_hi);
      const double bz = uniform(rng, z_lo, std::min(z_hi, 0.8 * (room_hi_[2] - room_lo_[2])));
      const double cx = uniform(rng, -hx + 0.5 * bx, hx - 0.5 * bx);
      const double cy = uniform(rng, -hy + 0.5 * by, hy - 0.5 * by);
      bool clear = true;
      // Not in front of a panel (repeat_texture): the copies are seen unoccluded.
      for (const WallPanel& pn : panels_) {
        const auto a = static_cast<std::size_t>(pn.wall / 2);
        const std::size_t pa = a == 0 ? 1 : 0;
        const double depth = std::min(kPanelKeepOut, 0.5 * (room_hi_[a] - room_lo_[a]));
        const double n0 = pn.wall % 2 == 0 ? room_lo_[a] : room_hi_[a] - depth;
        const std::array<double, 2> c{cx, cy};
        const std::array<double, 2> half{0.5 * bx, 0.5 * by};
        const bool along = c[pa] + half[pa] > pn.u0 - kPanelKeepOutSide &&
                           c[pa] - half[pa] < pn.u1 + kPanelKeepOutSide;
        const bool out = c[a] + half[a] > n0 && c[a] - half[a] < n0 + depth;
        if (along && out) clear = false;
      }
      for (const Eigen::Vector2d& c : path) {
        if (!clear) break;
        const double gx = std::max(0.0, std::abs(c.x() - cx) - 0.5 * bx);
        const double gy = std::max(0.0, std::abs(c.y() - cy) - 0.5 * by);
        if (gx * gx + gy * gy < clearance * clearance) {
          clear = false;
          break;
        }
      }
      if (!clear) continue;
      boxes_.push_back(
          box_on_floor(cx, cy, bx, by, bz, static_cast<int>(rng() % textures_.size())));
      break;
    }
  }
}

Status SyntheticCamera::list_photos(const SyntheticOptions& opts, std::vector<std::string>& out) {
  namespace fs = std::filesystem;
  out.clear();
  const std::string hint = "install the Debian package " + std::string(kPhotoPackage) +
                           " (apt-get install " + std::string(kPhotoPackage) +
                           "), set camera.synthetic.photo_dir, or use texture: procedural";
  std::error_code ec;
  if (!fs::is_directory(opts.photo_dir, ec)) {
    return input_error("synthetic camera: photo textures: folder '" + opts.photo_dir +
                       "' not found: " + hint);
  }
  std::vector<std::pair<std::string, std::string>> found;  // (file name, path)
  for (fs::recursive_directory_iterator
           it(opts.photo_dir, fs::directory_options::skip_permission_denied, ec),
       end;
       !ec && it != end; it.increment(ec)) {
    if (!it->is_regular_file(ec)) continue;
    std::string ext = it->path().extension().string();
    std::transform(ext.begin(), ext.end(), ext.begin(),
                   [](unsigned char c) { return static_cast<char>(std::tolower(c)); });
    if (ext != ".jpg" && ext != ".jpeg") continue;
    if (is_resolution_variant(it->path().stem().string())) continue;
    found.emplace_back(it->path().filename().string(), it->path().string());
  }
  std::sort(found.begin(), found.end());
  for (std::size_t i = 0; i < found.size(); ++i) {
    const bool even = i % 2 == 0;
    if (opts.photo_set == "all" || (opts.photo_set == "dev") == even) {
      out.push_back(found[i].second);
    }
  }
  if (out.empty()) {
    return input_error("synthetic camera: photo textures: no *.jpg photos in folder '" +
                       opts.photo_dir + "'" +
                       (found.empty() ? "" : " for photo_set " + opts.photo_set) + ": " + hint);
  }
  return Status::ok();
}

Status SyntheticCamera::load_wall_photos(std::mt19937& rng, std::vector<cv::Mat>& photos) {
  std::vector<std::string> all;
  if (Status s = list_photos(opts_, all); !s.is_ok()) return s;
  // A seeded shuffle, then one photo per wall (distinct while the set has six or more).
  std::vector<std::size_t> order(all.size());
  for (std::size_t i = 0; i < order.size(); ++i) order[i] = i;
  for (std::size_t i = order.size(); i > 1; --i) std::swap(order[i - 1], order[rng() % i]);
  photos.clear();
  photo_files_.clear();
  for (std::size_t k = 0; k < textures_.size(); ++k) {
    const std::string& path = all[order[k % order.size()]];
    cv::Mat img = cv::imread(path, cv::IMREAD_GRAYSCALE);
    if (img.empty() || img.cols < 16 || img.rows < 16) {
      return input_error("synthetic camera: photo textures: cannot read '" + path + "'");
    }
    photos.push_back(img);
    photo_files_.push_back(path);
  }
  return Status::ok();
}

void SyntheticCamera::make_photo_textures(const std::vector<cv::Mat>& photos, std::mt19937& rng) {
  // Each wall: its photo at a density of texture_size texels per room height (so photos keep
  // their aspect), upright on the vertical walls (texture rows run up). Rooms: one random
  // crop of the wall's aspect; the hall: a grid of crops half the hall's height, like
  // facades and signs.
  const bool hall = kind_ == Scenario::kHallDrive || kind_ == Scenario::kHallTurn ||
                    kind_ == Scenario::kHallRepeated;
  const double density = opts_.texture_size / static_cast<double>(room_hi_[2] - room_lo_[2]);
  for (std::size_t k = 0; k < textures_.size(); ++k) {
    const std::size_t a = k / 2;
    const std::size_t pa = a == 0 ? 1 : 0;
    const std::size_t qa = a == 2 ? 1 : 2;
    const int w = std::clamp(static_cast<int>(std::lround((room_hi_[pa] - room_lo_[pa]) * density)),
                             kMinMipSize, 8192);
    const int h = std::clamp(static_cast<int>(std::lround((room_hi_[qa] - room_lo_[qa]) * density)),
                             kMinMipSize, 8192);
    cv::Mat canvas;
    if (!hall) {
      canvas = photo_crop(photos[k], w, h, uniform(rng, 0.55, 1.0), rng);
    } else {
      canvas = cv::Mat(h, w, CV_8UC1, cv::Scalar(128));
      const int tile = std::max(kMinMipSize, opts_.texture_size / 2);
      for (int y0 = 0; y0 < h; y0 += tile) {
        for (int x0 = 0; x0 < w; x0 += tile) {
          const int tw = std::min(tile, w - x0);
          const int th = std::min(tile, h - y0);
          photo_crop(photos[k], tw, th, uniform(rng, 0.3, 0.7), rng)
              .copyTo(canvas(cv::Rect(x0, y0, tw, th)));
        }
      }
    }
    if (a < 2) cv::flip(canvas, canvas, 0);  // vertical walls: row 0 is the floor
    Texture& tex = textures_[k];
    tex.w = w;
    tex.h = h;
    tex.levels = make_mips_rect(std::vector<std::uint8_t>(canvas.datastart, canvas.dataend), w, h);
  }
}

void SyntheticCamera::make_corridor_textures(const std::vector<cv::Mat>& sources,
                                             std::mt19937& rng) {
  // Painted walls: the source image flattened toward white (corridor_contrast), tiled in
  // squares of the wall's smaller side; then the few features of a real corridor: skirting,
  // doors with frames and handles, posters (side walls), floor tiles and ceiling lights.
  const double density = kCorridorTexelsPerM;
  const double contrast = opts_.corridor_contrast;
  for (std::size_t k = 0; k < textures_.size(); ++k) {
    const std::size_t a = k / 2;
    const std::size_t pa = a == 0 ? 1 : 0;
    const std::size_t qa = a == 2 ? 1 : 2;
    const double ext_u = room_hi_[pa] - room_lo_[pa];
    const double ext_v = room_hi_[qa] - room_lo_[qa];
    const int w = std::max(kMinMipSize, static_cast<int>(std::lround(ext_u * density)));
    const int h = std::max(kMinMipSize, static_cast<int>(std::lround(ext_v * density)));
    const bool floor = k == 4;
    const bool ceiling = k == 5;
    const double base = floor ? 140.0 : ceiling ? 212.0 : kCorridorWhite;
    const double gain = floor ? std::min(1.0, 2.5 * contrast) : contrast;
    cv::Mat canvas(h, w, CV_32FC1);
    const int tile = std::min(w, h);
    for (int x0 = 0; x0 < w; x0 += tile) {
      const int tw = std::min(tile, w - x0);
      for (int y0 = 0; y0 < h; y0 += tile) {
        const int th = std::min(tile, h - y0);
        cv::Mat crop;
        photo_crop(sources[k], tw, th, uniform(rng, 0.4, 0.9), rng).convertTo(crop, CV_32F);
        const double mean = cv::mean(crop)[0];
        crop.convertTo(crop, CV_32F, gain, base - gain * mean);
        crop.copyTo(canvas(cv::Rect(x0, y0, tw, th)));
      }
    }
    auto fill = [&](double u0, double v0, double u1, double v1, double value) {
      const int c0 = std::clamp(static_cast<int>(u0 * density), 0, w);
      const int c1 = std::clamp(static_cast<int>(u1 * density), 0, w);
      const int r0 = std::clamp(static_cast<int>(v0 * density), 0, h);
      const int r1 = std::clamp(static_cast<int>(v1 * density), 0, h);
      if (c1 > c0 && r1 > r0) canvas(cv::Rect(c0, r0, c1 - c0, r1 - r0)).setTo(value);
    };
    if (a < 2) {
      // Skirting board and its shadow line (rows run up from the floor).
      fill(0.0, 0.0, ext_u, 0.10, 150.0 + uniform(rng, -10, 10));
      fill(0.0, 0.10, ext_u, 0.115, kCorridorWhite - 30.0);
      // Doors: frame, leaf (a low-contrast patch of the source), handle.
      std::vector<std::pair<double, double>> taken;
      double u = a == 0 ? 0.5 * ext_u - 0.45 : uniform(rng, 1.0, 3.0);
      while (u + 1.0 < ext_u) {
        const double top = std::min(2.05, ext_v - 0.2);
        fill(u - 0.06, 0.0, u + 0.96, top + 0.06, kCorridorWhite - uniform(rng, 25, 45));
        cv::Mat leaf;
        const int lw = std::max(2, static_cast<int>(0.9 * density));
        const int lh = std::max(2, static_cast<int>(top * density));
        photo_crop(sources[(k + 3) % sources.size()], lw, lh, uniform(rng, 0.3, 0.8), rng)
            .convertTo(leaf, CV_32F);
        const double leaf_grey = uniform(rng, 170, 205);
        const double mean = cv::mean(leaf)[0];
        leaf.convertTo(leaf, CV_32F, 0.25, leaf_grey - 0.25 * mean);
        const int c0 = static_cast<int>(u * density);
        if (c0 + lw <= w && lh <= h) leaf.copyTo(canvas(cv::Rect(c0, 0, lw, lh)));
        fill(u + 0.76, 0.98, u + 0.84, 1.02, 90.0);  // handle
        taken.emplace_back(u - 0.2, u + 1.1);
        if (a == 0) break;  // one door in each end wall
        u += uniform(rng, 3.5, 6.5);
      }
      // Posters between the doors (side walls only): a photo crop at moderate contrast.
      if (a == 1) {
        for (double pu = uniform(rng, 0.5, 2.0); pu + 0.7 < ext_u; pu += uniform(rng, 3.0, 7.0)) {
          bool free = true;
          for (const auto& [t0, t1] : taken) free = free && (pu + 0.7 < t0 || pu > t1);
          if (!free) continue;
          const int pw = static_cast<int>(0.6 * density);
          const int ph = static_cast<int>(0.85 * density);
          const int c0 = static_cast<int>(pu * density);
          const int r0 = static_cast<int>(1.15 * density);
          if (c0 + pw > w || r0 + ph > h) continue;
          cv::Mat poster;
          photo_crop(sources[(k + 1) % sources.size()], pw, ph, uniform(rng, 0.3, 0.7), rng)
              .convertTo(poster, CV_32F);
          const double mean = cv::mean(poster)[0];
          poster.convertTo(poster, CV_32F, 0.5, 150.0 - 0.5 * mean);
          poster.copyTo(canvas(cv::Rect(c0, r0, pw, ph)));
        }
      }
    } else if (floor) {
      // Floor tiles: faint seams every 0.6 m.
      for (double u = 0.0; u < ext_u; u += 0.6) fill(u, 0.0, u + 0.01, ext_v, base - 12.0);
      for (double v = 0.0; v < ext_v; v += 0.6) fill(0.0, v, ext_u, v + 0.01, base - 12.0);
    } else {
      // Ceiling lights: bright panels every 2.4 m down the middle.
      for (double u = 1.2; u + 0.6 < ext_u; u += 2.4) {
        fill(u, 0.5 * ext_v - 0.3, u + 1.2, 0.5 * ext_v + 0.3, 250.0);
      }
    }
    cv::Mat grey;
    canvas.convertTo(grey, CV_8U);  // saturating
    Texture& tex = textures_[k];
    tex.w = w;
    tex.h = h;
    std::vector<std::uint8_t> data(static_cast<std::size_t>(w) * static_cast<std::size_t>(h));
    for (int r = 0; r < h; ++r) {
      std::copy(grey.ptr<std::uint8_t>(r), grey.ptr<std::uint8_t>(r) + w,
                data.begin() + static_cast<std::ptrdiff_t>(r) * w);
    }
    tex.levels = make_mips_rect(std::move(data), w, h);
  }
}

}  // namespace mer::hal
