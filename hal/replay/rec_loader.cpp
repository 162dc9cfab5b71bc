#include "hal/replay/rec_loader.h"

#include <utility>

#include "platform/log_ring.h"

namespace mer::hal {

RecLoader::RecLoader(std::string path) : path_(std::move(path)) {}

Status RecLoader::open() {
  damage_logged_ = false;
  ground_truth_ = Trajectory{{}, path_};
  if (Status s = reader_.open(path_); !s.is_ok()) return s;
  // Trajectory needs strictly increasing times; a recording's camera clock should give
  // that, but never hand out a trajectory that breaks the invariant.
  for (const StampedPose& p : reader_.ground_truth()) {
    if (ground_truth_.poses.empty() || p.t_ns > ground_truth_.poses.back().t_ns) {
      ground_truth_.poses.push_back(p);
    }
  }
  // Built once here: describe() is called from other threads while load() runs on the
  // prefetch thread and may shorten the frame count on damage.
  description_ = build_description();
  return Status::ok();
}

LoadStatus RecLoader::load(std::size_t index, Frame& out, Status& status) {
  switch (reader_.read_frame(index, out)) {
    case ReadStatus::kFrame:
      status = Status::ok();
      return LoadStatus::kOk;
    case ReadStatus::kEnd:
      status = Status(StatusCode::kEndOfStream, "rec:" + path_ + ": end of recording after " +
                                                    std::to_string(index) + " frames");
      return LoadStatus::kEndOfStream;
    case ReadStatus::kDamaged:
      break;
  }
  const RecordingDamage& d = *reader_.damage();
  if (!damage_logged_) {
    damage_logged_ = true;
    MER_LOG_WARN("%s", d.message.c_str());
  }
  status = input_error(d.message);
  return LoadStatus::kEndOfStream;
}

std::string RecLoader::describe() const {
  return description_.empty() ? "rec:" + path_ : description_;
}

std::string RecLoader::build_description() const {
  const RecordingHeader& h = reader_.header();
  std::string s = "rec:" + path_ + " (" + std::to_string(h.intrinsics.width) + "x" +
                  std::to_string(h.intrinsics.height) + ", " +
                  std::to_string(reader_.frame_count()) + " frames";
  if (h.has_depth) s += ", depth";
  if (h.has_ground_truth) s += ", ground truth";
  if (!h.description.empty()) s += "; camera: " + h.description;
  return s + ")";
}

Result<std::unique_ptr<FrameLoader>> make_rec_loader(const std::string& path) {
  if (path.empty()) return invalid_argument("rec: empty recording path (expected rec:FILE)");
  return std::unique_ptr<FrameLoader>(std::make_unique<RecLoader>(path));
}

}  // namespace mer::hal
