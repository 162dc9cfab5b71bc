#pragma once
/// @file depth_maps.h
/// The depth maps of `depth.backend: external`: the folder of `depth.external` (read by
/// hal/replay/depth_map_folder.h), behind the core's depth::DepthMapSource. Opened at start,
/// before the pipeline: the folder is indexed once and its first map is read, so a missing
/// or empty folder, a badly named or unreadable map file is a configuration error naming
/// `depth.external.folder`, not a surprise at the first keyframe.

#include <memory>

#include "core/status.h"
#include "depth/depth_map_source.h"
#include "depth/depth_options.h"

namespace mer::app {

/// The depth map source the configured backend needs: null for every backend but
/// `external`; for `external`, the indexed folder or an error naming the key.
Result<std::unique_ptr<depth::DepthMapSource>> open_depth_maps(const depth::DepthOptions& opts);

}  // namespace mer::app
