#include "frontend/keypoint_grid.h"

#include <algorithm>

namespace mer::frontend {

void KeypointGrid::reserve(int width, int height, int cell_px, int max_keypoints) {
  cell_px_ = cell_px;
  cols_ = (width + cell_px - 1) / cell_px;
  rows_ = (height + cell_px - 1) / cell_px;
  start_.assign(static_cast<std::size_t>(cols_ * rows_ + 1), 0);
  fill_.assign(static_cast<std::size_t>(cols_ * rows_), 0);
  items_.assign(static_cast<std::size_t>(max_keypoints), 0);
}

void KeypointGrid::build(std::span<const features::Keypoint> keypoints,
                         std::span<const features::Descriptor> descriptors) {
  const auto n = std::min({keypoints.size(), descriptors.size(), items_.size()});
  keypoints_ = keypoints.first(n);
  descriptors_ = descriptors.first(n);
  const std::size_t cells = fill_.size();  // cols_ * rows_
  std::fill(start_.begin(), start_.end(), 0);
  auto cell_of = [&](const features::Keypoint& k) {
    const int cx = std::clamp(static_cast<int>(k.x) / cell_px_, 0, cols_ - 1);
    const int cy = std::clamp(static_cast<int>(k.y) / cell_px_, 0, rows_ - 1);
    return cy * cols_ + cx;
  };
  for (std::size_t i = 0; i < n; ++i) ++start_[static_cast<std::size_t>(cell_of(keypoints[i]) + 1)];
  for (std::size_t c = 0; c < cells; ++c) start_[c + 1] += start_[c];
  std::copy_n(start_.begin(), cells, fill_.begin());
  for (std::size_t i = 0; i < n; ++i) {
    const int c = cell_of(keypoints[i]);
    items_[static_cast<std::size_t>(fill_[static_cast<std::size_t>(c)]++)] =
        static_cast<std::int32_t>(i);
  }
}

KeypointGrid::Match KeypointGrid::search(const Eigen::Vector2d& uv, double r, int min_level,
                                         int max_level, const features::Descriptor& desc) const {
  const int x0 = std::max(0, static_cast<int>((uv.x() - r) / cell_px_));
  const int x1 = std::min(cols_ - 1, static_cast<int>((uv.x() + r) / cell_px_));
  const int y0 = std::max(0, static_cast<int>((uv.y() - r) / cell_px_));
  const int y1 = std::min(rows_ - 1, static_cast<int>((uv.y() + r) / cell_px_));
  Match m;
  for (int gy = y0; gy <= y1; ++gy) {
    for (int gx = x0; gx <= x1; ++gx) {
      const auto cell = static_cast<std::size_t>(gy * cols_ + gx);
      for (int it = start_[cell]; it < start_[cell + 1]; ++it) {
        const int k = items_[static_cast<std::size_t>(it)];
        const features::Keypoint& kp = keypoints_[static_cast<std::size_t>(k)];
        if (kp.level < min_level || kp.level > max_level) continue;
        const double dx = kp.x - uv.x();
        const double dy = kp.y - uv.y();
        if (dx * dx + dy * dy > r * r) continue;
        const int d = features::hamming(desc, descriptors_[static_cast<std::size_t>(k)]);
        if (d < m.best) {
          m.second = m.best;
          m.best = d;
          m.index = k;
        } else if (d < m.second) {
          m.second = d;
        }
      }
    }
  }
  return m;
}

}  // namespace mer::frontend
