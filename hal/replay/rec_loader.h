#pragma once
/// @file rec_loader.h
/// `rec:FILE` — replay of a native recording (recording.h) as a FrameLoader.
///
/// Every intact frame replays; the first damaged chunk (truncated, bad magic, bad length,
/// CRC mismatch) ends the stream: load() returns kEndOfStream there, the damage report is
/// logged once (MER_LOG_WARN) and kept in damage(). Intrinsics, depth and ground truth come
/// from the file.

#include <memory>
#include <optional>
#include <string>

#include "core/status.h"
#include "hal/replay/frame_loader.h"
#include "hal/replay/recording.h"

namespace mer::hal {

/// FrameLoader of a `.merrec` file.
class RecLoader final : public FrameLoader {
 public:
  /// Does not touch the file; open() does.
  explicit RecLoader(std::string path);

  /// Opens the file, validates the header, scans the chunks and collects the ground truth.
  /// Header errors are kInputError naming the file and the byte offset.
  Status open() override;
  /// Frames whose chunk structure is intact (CRC mismatches found later end the stream
  /// earlier).
  std::size_t size() const override { return reader_.frame_count(); }
  const CameraIntrinsics& intrinsics() const override { return reader_.header().intrinsics; }
  bool has_depth() const override { return reader_.header().has_depth; }
  bool has_ground_truth() const override { return reader_.header().has_ground_truth; }
  /// kOk with the frame decoded; kEndOfStream at the clean end or at the first damage
  /// (`status` then holds the damage message, code kInputError).
  LoadStatus load(std::size_t index, Frame& out, Status& status) override;
  /// The nominal frame rate stored in the header.
  double nominal_fps() const override { return reader_.header().nominal_fps; }
  /// "rec:FILE (WxH, N frames[, depth][, ground truth]; camera: DESCRIPTION)".
  std::string describe() const override;
  /// The ground-truth poses of the intact chunks (structure-checked at open()).
  const Trajectory& ground_truth() const override { return ground_truth_; }

  /// The first damage found so far (by open()'s scan or by load()), if any.
  const std::optional<RecordingDamage>& damage() const { return reader_.damage(); }
  /// The damage message (FrameLoader interface). Call after load() reported the end.
  std::string damage_report() const override {
    return reader_.damage() ? reader_.damage()->message : std::string();
  }
  /// The file header (valid after open()).
  const RecordingHeader& header() const { return reader_.header(); }

 private:
  std::string build_description() const;

  std::string path_;
  std::string description_;  // set by open()
  RecordingReader reader_;
  Trajectory ground_truth_;
  bool damage_logged_ = false;
};

/// Creates (does not open) the loader of `rec:PATH`; error for an empty path.
Result<std::unique_ptr<FrameLoader>> make_rec_loader(const std::string& path);

}  // namespace mer::hal
