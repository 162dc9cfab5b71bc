// Built instead of libcamera_camera.cpp when libcamera-dev is not installed.
#include "hal/libcamera/libcamera_camera.h"

namespace mer::hal {

bool libcamera_backend_built() {
  return false;
}

Result<std::unique_ptr<CameraSource>> make_libcamera_camera(const std::string& id,
                                                            const LibcameraOptions& /*opts*/) {
  return Status(StatusCode::kUnavailable,
                "--input 'libcamera:" + id +
                    "': this build has no libcamera backend (install libcamera-dev and rebuild)");
}

}  // namespace mer::hal
