// PFM decoding: round trip, row order, both byte orders, header variants, and refusals of
// truncated, oversized, colour and garbage inputs with messages naming the file.
#include "hal/replay/pfm.h"

#include <bit>
#include <cstring>
#include <string>

#include <gtest/gtest.h>
#include <opencv2/core.hpp>

namespace mer::hal {
namespace {

std::span<const std::uint8_t> bytes_of(const std::string& s) {
  return {reinterpret_cast<const std::uint8_t*>(s.data()), s.size()};
}

/// A 3x2 image with distinct values, top row first.
cv::Mat sample() {
  cv::Mat m(2, 3, CV_32FC1);
  const float v[] = {1.0F, 2.0F, 3.0F, 4.5F, 5.5F, 6.5F};
  std::memcpy(m.data, v, sizeof(v));
  return m;
}

/// A PFM with the given header text and float data (in file order, `big_endian` or not).
std::string make_pfm(const std::string& header, const std::vector<float>& data, bool big_endian) {
  std::string s = header;
  for (const float f : data) {
    std::uint32_t u = std::bit_cast<std::uint32_t>(f);
    if (big_endian == (std::endian::native == std::endian::little)) u = __builtin_bswap32(u);
    char b[4];
    std::memcpy(b, &u, 4);
    s.append(b, 4);
  }
  return s;
}

TEST(Pfm, RoundTripKeepsValuesAndRowOrder) {
  const cv::Mat m = sample();
  const std::string enc = encode_pfm(m);
  EXPECT_EQ(enc.rfind("Pf\n3 2\n-1.0\n", 0), 0U) << "little-endian header";
  auto r = parse_pfm(bytes_of(enc), "a.pfm");
  ASSERT_TRUE(r.is_ok()) << r.status().message();
  const cv::Mat& d = r.value();
  ASSERT_EQ(d.type(), CV_32FC1);
  ASSERT_EQ(d.cols, 3);
  ASSERT_EQ(d.rows, 2);
  EXPECT_EQ(cv::norm(d, m, cv::NORM_INF), 0.0);
}

TEST(Pfm, RowsAreStoredBottomUp) {
  // File order: bottom row (4.5 5.5 6.5) first.
  const std::string f = make_pfm("Pf\n3 2\n-1\n", {4.5F, 5.5F, 6.5F, 1.0F, 2.0F, 3.0F}, false);
  auto r = parse_pfm(bytes_of(f), "rows.pfm");
  ASSERT_TRUE(r.is_ok()) << r.status().message();
  EXPECT_EQ(cv::norm(r.value(), sample(), cv::NORM_INF), 0.0);
}

TEST(Pfm, BigEndianAndLooseHeaderWhitespace) {
  // Positive scale: big-endian; width and height on their own lines, blanks around them,
  // a scale magnitude other than 1 (not applied).
  const std::string f =
      make_pfm("Pf \n 3\r\n2\t\n2.5\n", {4.5F, 5.5F, 6.5F, 1.0F, 2.0F, 3.0F}, true);
  auto r = parse_pfm(bytes_of(f), "be.pfm");
  ASSERT_TRUE(r.is_ok()) << r.status().message();
  EXPECT_EQ(cv::norm(r.value(), sample(), cv::NORM_INF), 0.0);
}

TEST(Pfm, RefusalsNameTheFileAndWhatIsWrong) {
  const std::string good = encode_pfm(sample());
  const struct {
    std::string input;
    std::string expect;  // part of the message
  } cases[] = {
      {"", "magic"},
      {"P5\n3 2\n255\n", "magic"},
      {make_pfm("PF\n1 1\n-1\n", {1.0F, 2.0F, 3.0F}, false), "three-channel"},
      {"Pf\n3\n", "width and height"},
      {"Pf\n0 2\n-1\n", "width and height"},
      {"Pf\n-3 2\n-1\n", "width and height"},
      {"Pf\n3x 2\n-1\n", "width and height"},
      {"Pf\n99999999999 2\n-1\n", "width and height"},
      {"Pf\n40000 2\n-1\n", "width and height"},
      {"Pf\n3 2\n0\n", "non-zero scale"},
      {"Pf\n3 2\nnan\n", "non-zero scale"},
      {"Pf\n3 2\n-1", "truncated header"},
      {good.substr(0, good.size() - 1), "truncated"},
      {good.substr(0, good.size() - 12), "needs 24 bytes of float data, found 12"},
      {good + "xx", "2 bytes after"},
      {"Pf\n30000 30000\n-1\n", "truncated"},  // must not allocate 3.6 GB
  };
  for (const auto& c : cases) {
    auto r = parse_pfm(bytes_of(c.input), "dir/bad.pfm");
    ASSERT_FALSE(r.is_ok()) << c.expect;
    EXPECT_NE(r.status().message().find("dir/bad.pfm"), std::string::npos) << r.status().message();
    EXPECT_NE(r.status().message().find(c.expect), std::string::npos) << r.status().message();
    EXPECT_EQ(r.status().code(), StatusCode::kInputError);
  }
}

TEST(Pfm, GarbageNeverCrashes) {
  // Every prefix of a valid file and byte flips of its header.
  const std::string good = encode_pfm(sample());
  for (std::size_t n = 0; n < good.size(); ++n) {
    EXPECT_FALSE(parse_pfm(bytes_of(good.substr(0, n)), "p.pfm").is_ok()) << n;
  }
  for (std::size_t i = 0; i < 12; ++i) {
    for (const char c : {'\0', ' ', '9', '-', 'e', '\xff'}) {
      std::string g = good;
      g[i] = c;
      (void)parse_pfm(bytes_of(g), "g.pfm");
    }
  }
}

}  // namespace
}  // namespace mer::hal
