// A folder of depth maps named by timestamp: indexing (seconds and nanosecond names, format
// filter, ignored files), reading 16-bit PNG and PFM maps into metres, and the errors: a
// missing or empty folder, a name that is not a timestamp, duplicates, bad files.
#include "hal/replay/depth_map_folder.h"

#include <string>

#include <gtest/gtest.h>
#include <opencv2/imgcodecs.hpp>

#include "hal/replay/pfm.h"
#include "replay_fixtures.h"

namespace mer::hal {
namespace {

using test::TempDir;
using test::write_file;
using test::write_png;

constexpr double kTumScale = 5000.0;

/// A 16-bit depth PNG of `w` x `h` with value `v` everywhere but pixel (1, 0) = 0 (no depth).
cv::Mat png16(int w, int h, std::uint16_t v) {
  cv::Mat m(h, w, CV_16UC1, cv::Scalar(v));
  m.at<std::uint16_t>(0, 1) = 0;
  return m;
}

DepthMapFolderOptions options(const std::string& dir) {
  DepthMapFolderOptions o;
  o.folder = dir;
  o.depth_scale = kTumScale;
  return o;
}

TEST(DepthMapTime, SecondsNanosecondsAndAuto) {
  std::int64_t t = 0;
  ASSERT_TRUE(parse_depth_map_time("1305031102.175304", "auto", t));
  EXPECT_EQ(t, 1305031102175304000);
  ASSERT_TRUE(parse_depth_map_time("1403636579763555584", "auto", t));
  EXPECT_EQ(t, 1403636579763555584);
  ASSERT_TRUE(parse_depth_map_time("12", "s", t));
  EXPECT_EQ(t, 12'000'000'000);
  ASSERT_TRUE(parse_depth_map_time("12", "ns", t));
  EXPECT_EQ(t, 12);
  ASSERT_TRUE(parse_depth_map_time("0.033333", "s", t));
  EXPECT_EQ(t, 33'333'000);
  for (const char* bad : {"", "frame_0001", "1.5e3", "-3", "+3", "1.2.3", "12a", " 12"}) {
    EXPECT_FALSE(parse_depth_map_time(bad, "auto", t)) << bad;
  }
  EXPECT_FALSE(parse_depth_map_time("1.5", "ns", t));
  EXPECT_FALSE(parse_depth_map_time("99999999999999999999", "ns", t)) << "overflow";
}

TEST(DepthMapFolder, IndexesSortedTimestampsOfBothFormats) {
  TempDir d;
  write_png(d / "1.100000.png", png16(4, 3, 10000));
  write_file(d / "1.000000.pfm", encode_pfm(cv::Mat(3, 4, CV_32FC1, cv::Scalar(1.25F))));
  write_png(d / "0.900000.png", png16(4, 3, 5000));
  write_file(d / "depth.txt", "# an index file: ignored\n");
  write_file(d / ".hidden.png", "not an image");
  std::filesystem::create_directories(d / "2.000000.png");  // a folder: ignored
  auto f = DepthMapFolder::open(options(d.path()));
  ASSERT_TRUE(f.is_ok()) << f.status().message();
  const auto ts = f.value().timestamps();
  ASSERT_EQ(ts.size(), 3U);
  EXPECT_EQ(ts[0], 900'000'000);
  EXPECT_EQ(ts[1], 1'000'000'000);
  EXPECT_EQ(ts[2], 1'100'000'000);
  EXPECT_NE(f.value().file(1).find("1.000000.pfm"), std::string::npos);

  cv::Mat m;
  ASSERT_TRUE(f.value().read(0, m).is_ok());
  ASSERT_EQ(m.type(), CV_32FC1);
  EXPECT_FLOAT_EQ(m.at<float>(2, 3), 1.0F) << "5000 / 5000 per metre";
  EXPECT_FLOAT_EQ(m.at<float>(0, 1), 0.0F) << "0 stays no depth";
  ASSERT_TRUE(f.value().read(1, m).is_ok());
  EXPECT_FLOAT_EQ(m.at<float>(1, 1), 1.25F);
  ASSERT_TRUE(f.value().read(2, m).is_ok());
  EXPECT_FLOAT_EQ(m.at<float>(2, 3), 2.0F);
}

TEST(DepthMapFolder, FormatOptionSelectsTheFiles) {
  TempDir d;
  write_png(d / "1.png", png16(4, 3, 1000));
  write_file(d / "2.pfm", encode_pfm(cv::Mat(3, 4, CV_32FC1, cv::Scalar(1.0F))));
  DepthMapFolderOptions o = options(d.path());
  o.time_unit = "ns";
  o.format = "png16";
  auto png = DepthMapFolder::open(o);
  ASSERT_TRUE(png.is_ok()) << png.status().message();
  ASSERT_EQ(png.value().timestamps().size(), 1U);
  EXPECT_EQ(png.value().timestamps()[0], 1);
  o.format = "float32";
  auto pfm = DepthMapFolder::open(o);
  ASSERT_TRUE(pfm.is_ok()) << pfm.status().message();
  ASSERT_EQ(pfm.value().timestamps().size(), 1U);
  EXPECT_EQ(pfm.value().timestamps()[0], 2);
}

TEST(DepthMapFolder, PfmValuesThatAreNoDepthBecomeZero) {
  TempDir d;
  cv::Mat m(2, 3, CV_32FC1, cv::Scalar(2.0F));
  m.at<float>(0, 0) = std::numeric_limits<float>::quiet_NaN();
  m.at<float>(0, 1) = std::numeric_limits<float>::infinity();
  m.at<float>(0, 2) = -1.0F;
  write_file(d / "5.pfm", encode_pfm(m));
  auto f = DepthMapFolder::open(options(d.path()));
  ASSERT_TRUE(f.is_ok()) << f.status().message();
  cv::Mat r;
  ASSERT_TRUE(f.value().read(0, r).is_ok());
  EXPECT_EQ(r.at<float>(0, 0), 0.0F);
  EXPECT_EQ(r.at<float>(0, 1), 0.0F);
  EXPECT_EQ(r.at<float>(0, 2), 0.0F);
  EXPECT_EQ(r.at<float>(1, 2), 2.0F);
}

TEST(DepthMapFolder, FolderErrorsNameTheFolderOrFile) {
  TempDir d;
  auto missing = DepthMapFolder::open(options(d / "nope"));
  ASSERT_FALSE(missing.is_ok());
  EXPECT_NE(missing.status().message().find("nope' does not exist"), std::string::npos)
      << missing.status().message();

  write_file(d / "file.txt", "x");
  auto not_dir = DepthMapFolder::open(options(d / "file.txt"));
  ASSERT_FALSE(not_dir.is_ok());
  EXPECT_NE(not_dir.status().message().find("not a folder"), std::string::npos);

  auto empty = DepthMapFolder::open(options(d.path()));  // only file.txt
  ASSERT_FALSE(empty.is_ok());
  EXPECT_NE(empty.status().message().find("holds no depth map"), std::string::npos)
      << empty.status().message();

  EXPECT_FALSE(DepthMapFolder::open(options("")).is_ok());

  write_png(d / "frame_0001.png", png16(4, 3, 1000));
  auto bad_name = DepthMapFolder::open(options(d.path()));
  ASSERT_FALSE(bad_name.is_ok());
  EXPECT_NE(bad_name.status().message().find("frame_0001.png"), std::string::npos)
      << bad_name.status().message();
  EXPECT_EQ(bad_name.status().code(), StatusCode::kInvalidArgument);
}

TEST(DepthMapFolder, TwoFilesWithOneTimestampAreRefused) {
  TempDir d;
  write_png(d / "1.5.png", png16(4, 3, 1000));
  write_png(d / "1.500000.png", png16(4, 3, 1000));
  auto f = DepthMapFolder::open(options(d.path()));
  ASSERT_FALSE(f.is_ok());
  EXPECT_NE(f.status().message().find("same timestamp"), std::string::npos) << f.status().message();
}

TEST(DepthMapFolder, BadFilesAreReadErrorsNamingTheFile) {
  TempDir d;
  write_png(d / "1.png", cv::Mat(3, 4, CV_8UC1, cv::Scalar(7)));   // 8-bit
  write_png(d / "2.png", cv::Mat(3, 4, CV_16UC3, cv::Scalar(7)));  // 3 channels
  write_file(d / "3.png", "\x89PNG\r\n garbage");                  // corrupt
  const std::string pfm = encode_pfm(cv::Mat(3, 4, CV_32FC1, cv::Scalar(1.0F)));
  write_file(d / "4.pfm", pfm.substr(0, pfm.size() - 5));  // truncated
  write_file(d / "5.pfm", "PF\n1 1\n-1\n123456789012");    // colour
  write_png(d / "6.png", png16(4, 3, 1000));
  DepthMapFolderOptions o = options(d.path());
  o.time_unit = "ns";
  auto f = DepthMapFolder::open(o);
  ASSERT_TRUE(f.is_ok()) << f.status().message();
  const char* expect[] = {"16-bit single-channel PNG, found 8-bit 1-channel",
                          "16-bit single-channel PNG, found 16-bit 3-channel", "PNG", "truncated",
                          "three-channel"};
  for (std::size_t i = 0; i < 5; ++i) {
    cv::Mat m;
    const Status s = f.value().read(i, m);
    ASSERT_FALSE(s.is_ok()) << i;
    EXPECT_NE(s.message().find(f.value().file(i)), std::string::npos) << s.message();
    EXPECT_NE(s.message().find(expect[i]), std::string::npos) << s.message();
  }
  cv::Mat m;
  EXPECT_TRUE(f.value().read(5, m).is_ok());
  std::filesystem::remove(d / "6.png");
  const Status gone = f.value().read(5, m);
  EXPECT_FALSE(gone.is_ok());
  EXPECT_NE(gone.message().find("6.png"), std::string::npos) << gone.message();
  EXPECT_FALSE(f.value().read(6, m).is_ok()) << "index past the end";
}

}  // namespace
}  // namespace mer::hal
