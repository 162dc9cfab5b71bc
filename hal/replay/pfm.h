#pragma once
/// @file pfm.h
/// PFM (Portable Float Map) single-channel images: the float depth-map format of the
/// `external` depth backend (hal/replay/depth_map_folder.h). The format:
///
///   "Pf" <ws> width <ws> height <ws> scale <one whitespace byte> data
///
/// with ASCII decimal width, height > 0 and a non-zero finite scale whose sign gives the byte
/// order of the data (negative: little-endian, positive: big-endian; its magnitude is not
/// applied), then width * height IEEE-754 32-bit floats, rows from the BOTTOM of the image
/// up. "PF" (three channels) is refused. <ws> is one or more blanks, tabs, CR or LF.
///
/// Contract (a libFuzzer harness relies on it): for ANY byte string parse_pfm() returns a
/// CV_32FC1 image or an error naming `name` and what was expected and found, without
/// crashing, hanging, reading out of bounds or allocating more than the input size (the data
/// must be all there before the image is allocated).

#include <cstdint>
#include <span>
#include <string>

#include <opencv2/core/mat.hpp>

#include "core/status.h"

namespace mer::hal {

/// Largest width or height parse_pfm() accepts, px.
inline constexpr int kMaxPfmSide = 1 << 15;

/// Decodes a single-channel PFM held in memory into a CV_32FC1 image (top row first).
Result<cv::Mat> parse_pfm(std::span<const std::uint8_t> bytes, const std::string& name);

/// Encodes a CV_32FC1 image as a little-endian single-channel PFM (scale -1).
std::string encode_pfm(const cv::Mat& image);

}  // namespace mer::hal
