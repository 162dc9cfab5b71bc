#include "app/summary.h"

#include <filesystem>

#include <gtest/gtest.h>

#include "support/run_command.h"

namespace mer::app {
namespace {

TEST(Summary, JsonCarriesTheStableKeys) {
  pipeline::PipelineStats st;
  st.frames_in = 10;
  st.frames_processed = 9;
  st.frames_dropped = 1;
  st.latency.push_back({"tracking", 1.0, 2.0, 3.0, 4.0, 1.5, 30.0, 9, 0});
  st.allocs.push_back({"tracking", 0, 9});
  st.cpu.process_s = 2.5;
  st.cpu.source_s = 0.5;
  st.cpu.slam.p50_ms = 7.0;
  st.threads.push_back({"mer_tracking", 1, 80, true, "", 1.25});
  RunInfo info;
  info.input = "synthetic:\"quoted\"";
  const std::string j = summary_json(st, info);
  for (const char* key :
       {"\"frames_in\": 10", "\"frames_processed\": 9", "\"frames_dropped\": 1", "\"frames_lost\"",
        "\"keyframes\"", "\"map_points\"", "\"wall_time_s\"", "\"latency_ms\"",
        "\"tracking\": {\"p50\": 1, \"p90\": 2, \"p99\": 3, \"max\": 4", "\"budget_overruns\"",
        "\"allocs_per_frame\": {\"tracking\": 0}", "synthetic:\\\"quoted\\\"",
        "\"cpu\": {\"process_s\": 2.5, \"source_s\": 0.5", "\"slam\": {\"p50\": 7,",
        "\"cpu_s\": 1.25}"}) {
    EXPECT_NE(j.find(key), std::string::npos) << key << "\n" << j;
  }
}

TEST(Summary, AtomicWriteReplacesTheFile) {
  const auto p = std::filesystem::temp_directory_path() / "mer_summary_atomic.json";
  ASSERT_TRUE(write_file_atomic(p.string(), "one").is_ok());
  ASSERT_TRUE(write_file_atomic(p.string(), "two").is_ok());
  EXPECT_EQ(mer::testing::read_text(p.string()), "two");
  EXPECT_FALSE(std::filesystem::exists(p.string() + ".tmp"));
  std::filesystem::remove(p);
  EXPECT_FALSE(write_file_atomic("/nonexistent/dir/x.json", "x").is_ok());
}

}  // namespace
}  // namespace mer::app
