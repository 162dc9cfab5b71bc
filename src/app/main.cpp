// mer_slam: configuration, start, signals, outputs. The stages are wired in
// pipeline/pipeline.cpp; this file only sets the run up and reports it.

#include <atomic>
#include <csignal>
#include <filesystem>
#include <iostream>
#include <string>
#include <vector>

#include "app/cli.h"
#include "app/depth_maps.h"
#include "app/stop_signal.h"
#include "app/summary.h"
#include "core/config_io.h"
#include "hal/camera_factory.h"
#include "pipeline/pipeline.h"
#include "platform/log_ring.h"
#include "platform/thread_table.h"

namespace {

std::atomic<bool>& g_stop = mer::app::stop_flag();

int fail(const mer::Status& s) {
  std::cerr << "mer_slam: error: " << s.message() << "\n";
  return mer::app::exit_code_for(s);
}

/// Creates --output's directory (an empty path: no output).
mer::Status make_output_dir(const std::string& dir) {
  if (dir.empty()) return mer::Status::ok();
  std::error_code ec;
  std::filesystem::create_directories(dir, ec);
  if (ec || !std::filesystem::is_directory(dir)) {
    return mer::invalid_argument("--output '" + dir + "': cannot create directory" +
                                 (ec ? ": " + ec.message() : std::string()));
  }
  return mer::Status::ok();
}

/// Scores the written trajectories against the ground truth: the run, its keyframes, each
/// segment (its file, and its own frames aligned on their own) and the events.
void evaluate_outputs(const std::string& out, mer::SensorMode mode,
                      const mer::pipeline::Pipeline& pipe, mer::app::RunInfo& info) {
  using namespace mer;
  const pipeline::PipelineStats& stats = pipe.stats();
  info.accuracy = app::evaluate_run(out, mode, stats);
  info.accuracy_keyframes = app::evaluate_run(out, mode, stats, "keyframes_final.txt");
  app::AccuracyReport discarded;
  discarded.note = "discarded (a failed start)";
  for (const pipeline::SegmentStats& g : stats.segments) {
    info.accuracy_segments.push_back(
        g.discarded ? discarded : app::evaluate_run(out, mode, stats, g.trajectory));
  }
  // Each segment's own frames, aligned on their own: the same as its file's unless
  // segments merged (a merged segment's frames are in the file it joined).
  for (const pipeline::SegmentStats& g : stats.segments) {
    info.accuracy_segments_own.push_back(
        g.discarded                 ? discarded
        : stats.segments.size() > 1 ? app::evaluate_run(out, mode, stats, g.trajectory, g.id)
                                    : info.accuracy_segments.back());
  }
  // An event is scored in its segment's own frame, as it was when it happened.
  info.events = app::audit_events(out, stats, info.accuracy_segments_own);
}

/// The final map re-anchors trajectory.txt's frames: the main segment's and those of the
/// segments that joined it, each anchor scaled by its segment's merges. Writes and scores
/// trajectory_final.txt; false on a write error (reported).
bool write_and_score_final_trajectory(const std::string& out, mer::SensorMode mode,
                                      mer::pipeline::Pipeline& pipe, mer::app::RunInfo& info) {
  using namespace mer;
  if (out.empty() || pipe.stats().frames_processed == 0) return true;
  std::uint16_t main_segment = 0;
  for (const pipeline::SegmentStats& g : pipe.stats().segments) {
    if (g.main) main_segment = g.id;
  }
  const std::vector<double> scales = pipe.segment_scales_into_main();
  if (Status w = app::write_final_trajectory(out, pipe.final_keyframe_poses(),
                                             info.final_trajectory, scales, main_segment);
      !w.is_ok()) {
    std::cerr << "mer_slam: error: final trajectory: " << w.message() << "\n";
    return false;
  }
  info.final_trajectory_written = true;
  info.accuracy_final = app::evaluate_run(out, mode, pipe.stats(), "trajectory_final.txt");
  return true;
}

/// --gt-check: the finished map checked against the ground truth. False on an error
/// (reported).
bool check_map_against_truth(const mer::app::CliArgs& args, const mer::app::SlamConfig& config,
                             mer::pipeline::Pipeline& pipe, mer::app::RunInfo& info) {
  using namespace mer;
  info.gt_check_requested = true;
  Status g = Status::ok();
  if (pipe.stats().frames_processed == 0) {
    info.gt_check.note = "no frame processed";
  } else if (info.stopped_by_signal) {
    info.gt_check.note = "stopped by a signal";  // the summary is due now
  } else {
    g = app::run_gt_check(args.output_dir, config.pipeline.mode, config.backend.full_max_iterations,
                          pipe, info.gt_check, info.accuracy_gt_converged,
                          info.accuracy_gt_shuffled, info.accuracy_gt_shuffled_detected);
  }
  if (!g.is_ok()) {
    std::cerr << "mer_slam: error: --gt-check: " << g.message() << "\n";
    return false;
  }
  return true;
}

}  // namespace

int main(int argc, char** argv) {
  using namespace mer;
  mer::app::install_stop_signal_handlers();
  (void)platform::default_log();  // construct before any hot thread logs

  auto parsed = app::parse_cli(argc, argv);
  if (!parsed.is_ok()) {
    std::cerr << app::usage();
    return fail(parsed.status());
  }
  const app::CliArgs& args = parsed.value();
  if (args.help) {
    std::cout << app::usage();
    return 0;
  }
  if (args.version) {
    std::cout << "mer_slam " << MER_VERSION << "\n";
    return 0;
  }
  app::SlamConfig config;
  if (Status s = app::build_config(args, config); !s.is_ok()) return fail(s);
  if (args.print_config) {
    std::cout << "# mer_slam effective configuration (load with --config)\n";
    options::print(config, std::cout);
    return 0;
  }

  // Depth maps of depth.backend: external, indexed once before anything starts.
  auto depth_maps = app::open_depth_maps(config.depth);
  if (!depth_maps.is_ok()) return fail(depth_maps.status());

  platform::LogDrain drain(platform::default_log(), stderr, config.telemetry.log_level);
  const platform::BoardThreads board =
      platform::find_board(config.board.profile).value_or(platform::kBoardGenericX86);
  (void)drain.start(board.log);

  app::RunInfo info;
  info.input = args.input;
  info.sensor_mode = config.pipeline.mode;
  int code = 0;
  {
    auto uri = hal::parse_input_uri(args.input);
    if (!uri.is_ok()) {
      drain.stop();
      return fail(uri.status());
    }
    auto cam = hal::make_camera(uri.value(), config.camera, !config.pipeline.lockstep,
                                config.pipeline.mode == SensorMode::kRgbd);
    if (!cam.is_ok()) {
      drain.stop();
      return fail(cam.status());
    }
    hal::CameraSource& camera = *cam.value();
    if (Status s = camera.open(static_cast<std::size_t>(config.camera.pool_size)); !s.is_ok()) {
      drain.stop();
      return fail(s);
    }
    info.source = camera.describe();
    info.intrinsics = hal::effective_intrinsics(camera.intrinsics(), config.camera.calibration);
    if (Status s = make_output_dir(args.output_dir); !s.is_ok()) {
      drain.stop();
      return fail(s);
    }
    pipeline::PipelineConfig pc{config.pipeline, config.board,    config.telemetry,
                                config.output,   config.tracking, config.map,
                                config.depth,    config.backend,  info.intrinsics,
                                config.culling,  config.loop,     config.relocalization};
    pipeline::Pipeline pipe(pc, camera, g_stop, depth_maps.value().get());
    Status s = pipe.init(args.output_dir);
    if (!s.is_ok()) {
      drain.stop();
      return fail(s);
    }
    s = pipe.run();
    info.stopped_by_signal = g_stop.load();
    if (!s.is_ok()) {
      info.error = s.message();
      code = app::exit_code_for(s);
    }
    drain.stop();  // print pending warnings before the summary
    evaluate_outputs(args.output_dir, config.pipeline.mode, pipe, info);
    const bool final_written =
        write_and_score_final_trajectory(args.output_dir, config.pipeline.mode, pipe, info);
    const bool gt_checked = !args.gt_check || check_map_against_truth(args, config, pipe, info);
    if ((!final_written || !gt_checked) && code == 0) code = 4;
    if (!args.output_dir.empty()) {
      const std::string path = (std::filesystem::path(args.output_dir) / "summary.json").string();
      if (Status w = app::write_file_atomic(path, app::summary_json(pipe.stats(), info));
          !w.is_ok()) {
        std::cerr << "mer_slam: error: " << w.message() << "\n";
        if (code == 0) code = 4;
      }
    }
    if (!args.quiet) app::print_summary(std::cout, pipe.stats(), info);
    if (!s.is_ok()) std::cerr << "mer_slam: error: " << s.message() << "\n";
  }
  return code;
}
