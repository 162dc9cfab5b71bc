// Fuzz target: the PFM decoder of depth maps (hal/replay/pfm.h). Besides not crashing, a
// successful decode must honour the documented contract (a CV_32FC1 image of the header's
// size, within the side limit, whose data filled the input exactly), otherwise the target
// aborts (a finding like a crash).
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <span>
#include <string>

#include "hal/replay/pfm.h"

namespace {

constexpr std::size_t kFloatBytes = 4;

[[noreturn]] void fail(const char* what) {
  std::fprintf(stderr, "pfm_fuzz: %s\n", what);
  std::abort();
}

}  // namespace

// NOLINTNEXTLINE(readability-identifier-naming): the name libFuzzer calls
extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  const auto r = mer::hal::parse_pfm(std::span<const std::uint8_t>(data, size), "fuzz.pfm");
  if (!r.is_ok()) {
    if (r.status().message().find("fuzz.pfm") == std::string::npos) fail("error without the name");
    return 0;
  }
  const cv::Mat& m = r.value();
  if (m.type() != CV_32FC1) fail("not a CV_32FC1 image");
  if (m.cols < 1 || m.rows < 1 || m.cols > mer::hal::kMaxPfmSide ||
      m.rows > mer::hal::kMaxPfmSide) {
    fail("size outside [1, kMaxPfmSide]");
  }
  const std::size_t data_bytes =
      static_cast<std::size_t>(m.cols) * static_cast<std::size_t>(m.rows) * kFloatBytes;
  if (data_bytes >= size) fail("more float data than input");
  // Re-encoding and decoding gives the same bits.
  const std::string again = mer::hal::encode_pfm(m);
  const auto r2 =
      mer::hal::parse_pfm(std::span<const std::uint8_t>(
                              reinterpret_cast<const std::uint8_t*>(again.data()), again.size()),
                          "again.pfm");
  if (!r2.is_ok()) fail("an encoded image does not decode");
  if (std::memcmp(r2.value().data, m.data, data_bytes) != 0) fail("round trip changed the data");
  return 0;
}
