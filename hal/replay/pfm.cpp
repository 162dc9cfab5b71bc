#include "hal/replay/pfm.h"

#include <bit>
#include <charconv>
#include <cmath>
#include <cstring>
#include <string_view>

#include "core/assert.h"

namespace mer::hal {
namespace {

constexpr std::size_t kMaxHeaderToken = 32;  // longer width / height / scale: not a PFM
constexpr std::size_t kFloatBytes = 4;
constexpr std::string_view kGrayMagic = "Pf";
constexpr std::string_view kColorMagic = "PF";

bool is_space(std::uint8_t c) {
  return c == ' ' || c == '\t' || c == '\r' || c == '\n';
}

/// The next blank-separated token from `pos` (leading blanks skipped); empty at the end of
/// the input or when longer than kMaxHeaderToken. `pos` ends just past the token.
std::string_view next_token(std::span<const std::uint8_t> b, std::size_t& pos) {
  while (pos < b.size() && is_space(b[pos])) ++pos;
  const std::size_t start = pos;
  while (pos < b.size() && !is_space(b[pos])) {
    if (pos - start >= kMaxHeaderToken) return {};
    ++pos;
  }
  return {reinterpret_cast<const char*>(b.data()) + start, pos - start};
}

bool parse_side(std::string_view tok, int& v) {
  const auto [ptr, ec] = std::from_chars(tok.data(), tok.data() + tok.size(), v);
  return ec == std::errc() && ptr == tok.data() + tok.size() && v > 0 && v <= kMaxPfmSide;
}

std::string printable(std::string_view tok) {
  std::string s;
  for (const char c : tok) {
    s += (c >= ' ' && c <= '~') ? c : '?';
  }
  return s;
}

}  // namespace

Result<cv::Mat> parse_pfm(std::span<const std::uint8_t> bytes, const std::string& name) {
  const std::string where = "PFM '" + name + "': ";
  std::size_t pos = 0;
  const std::string_view magic = next_token(bytes, pos);
  if (magic == kColorMagic) {
    return input_error(where + "three-channel map ('PF'); expected a single-channel 'Pf'");
  }
  if (magic != kGrayMagic) {
    return input_error(where + "expected the magic 'Pf', found '" + printable(magic) + "'");
  }
  int width = 0;
  int height = 0;
  const std::string_view w_tok = next_token(bytes, pos);
  const std::string_view h_tok = next_token(bytes, pos);
  if (!parse_side(w_tok, width) || !parse_side(h_tok, height)) {
    return input_error(where + "expected width and height in [1, " + std::to_string(kMaxPfmSide) +
                       "], found '" + printable(w_tok) + "' '" + printable(h_tok) + "'");
  }
  const std::string_view s_tok = next_token(bytes, pos);
  double scale = 0.0;
  const auto [ptr, ec] = std::from_chars(s_tok.data(), s_tok.data() + s_tok.size(), scale);
  if (s_tok.empty() || ec != std::errc() || ptr != s_tok.data() + s_tok.size() ||
      !std::isfinite(scale) || scale == 0.0) {
    return input_error(where + "expected a non-zero scale (its sign: the byte order), found '" +
                       printable(s_tok) + "'");
  }
  if (pos >= bytes.size() || !is_space(bytes[pos])) {
    return input_error(where + "truncated header (no data after the scale)");
  }
  ++pos;  // the single whitespace byte ending the header
  const auto w = static_cast<std::size_t>(width);
  const auto h = static_cast<std::size_t>(height);
  const std::size_t expected = w * h * kFloatBytes;
  const std::size_t found = bytes.size() - pos;
  if (found < expected) {
    return input_error(where + "truncated: " + std::to_string(width) + "x" +
                       std::to_string(height) + " needs " + std::to_string(expected) +
                       " bytes of float data, found " + std::to_string(found));
  }
  if (found > expected) {
    return input_error(where + std::to_string(found - expected) + " bytes after the " +
                       std::to_string(width) + "x" + std::to_string(height) +
                       " float data (wrong size in the header?)");
  }
  const bool data_little = scale < 0.0;
  const bool swap = data_little != (std::endian::native == std::endian::little);
  cv::Mat image(height, width, CV_32FC1);
  const std::uint8_t* src = bytes.data() + pos;
  for (std::size_t r = 0; r < h; ++r) {
    // PFM rows go bottom-up.
    const std::uint8_t* row = src + (h - 1 - r) * w * kFloatBytes;
    auto* dst = image.ptr<float>(static_cast<int>(r));
    for (std::size_t c = 0; c < w; ++c) {
      std::uint32_t u = 0;
      std::memcpy(&u, row + c * kFloatBytes, kFloatBytes);
      if (swap) u = __builtin_bswap32(u);
      dst[c] = std::bit_cast<float>(u);
    }
  }
  return image;
}

std::string encode_pfm(const cv::Mat& image) {
  MER_ASSERT(image.type() == CV_32FC1, "encode_pfm takes a CV_32FC1 image");
  std::string out = std::string(kGrayMagic) + "\n" + std::to_string(image.cols) + " " +
                    std::to_string(image.rows) + "\n" +
                    (std::endian::native == std::endian::little ? "-1.0\n" : "1.0\n");
  const std::size_t header = out.size();
  const auto w = static_cast<std::size_t>(image.cols);
  out.resize(header + w * static_cast<std::size_t>(image.rows) * kFloatBytes);
  for (int r = 0; r < image.rows; ++r) {
    const auto dst_row = static_cast<std::size_t>(image.rows - 1 - r);
    std::memcpy(out.data() + header + dst_row * w * kFloatBytes, image.ptr<float>(r),
                w * kFloatBytes);
  }
  return out;
}

}  // namespace mer::hal
