#include "app/depth_maps.h"

#include <utility>

#include "hal/replay/depth_map_folder.h"

namespace mer::app {
namespace {

constexpr const char* kFolderKey = "key 'depth.external.folder': ";

/// A hal::DepthMapFolder as a depth::DepthMapSource.
class FolderDepthMaps final : public depth::DepthMapSource {
 public:
  explicit FolderDepthMaps(hal::DepthMapFolder folder) : folder_(std::move(folder)) {}
  std::string describe() const override { return folder_.folder(); }
  std::span<const std::int64_t> timestamps() const override { return folder_.timestamps(); }
  Status load(std::size_t index, cv::Mat& depth) override { return folder_.read(index, depth); }

 private:
  hal::DepthMapFolder folder_;
};

}  // namespace

Result<std::unique_ptr<depth::DepthMapSource>> open_depth_maps(const depth::DepthOptions& opts) {
  if (opts.backend != depth::DepthBackend::kExternal) {
    return std::unique_ptr<depth::DepthMapSource>();
  }
  const depth::ExternalDepthOptions& e = opts.external;
  hal::DepthMapFolderOptions fo;
  fo.folder = e.folder;
  fo.format = e.format;
  fo.time_unit = e.time_unit;
  fo.depth_scale = e.depth_scale;
  Result<hal::DepthMapFolder> folder = hal::DepthMapFolder::open(fo);
  if (!folder.is_ok()) return invalid_argument(kFolderKey + folder.status().message());
  // The first map must read: a wrong format shows now, not at the first keyframe.
  cv::Mat first;
  if (Status s = folder.value().read(0, first); !s.is_ok()) {
    return invalid_argument(kFolderKey + s.message());
  }
  return std::unique_ptr<depth::DepthMapSource>(
      std::make_unique<FolderDepthMaps>(std::move(folder).value()));
}

}  // namespace mer::app
