#pragma once
/// @file slam_config.h
/// The whole configuration of mer_slam: one section per module. Loaded from the built-in
/// defaults, then `--config FILE`, then `--board FILE`, then command-line flags; validated
/// after each step. `mer_slam --print-config` prints it as commented YAML that loads back.

#include "backend/local_ba.h"
#include "backend/map_culling.h"
#include "core/options.h"
#include "depth/depth_options.h"
#include "frontend/tracking_options.h"
#include "hal/camera_factory.h"
#include "loop/loop_closer.h"
#include "loop/relocalizer.h"
#include "map/map.h"
#include "pipeline/pipeline_options.h"

namespace mer::app {

/// Top-level configuration.
struct SlamConfig {
  pipeline::PipelineOptions pipeline;
  hal::CameraOptions camera;
  frontend::TrackingOptions tracking;
  map::MapOptions map;
  depth::DepthOptions depth;
  backend::LocalBaOptions backend;
  backend::CullingOptions culling;
  mer::loop::LoopOptions loop;
  mer::loop::RelocalizerOptions relocalization;
  pipeline::BoardOptions board;
  pipeline::TelemetryOptions telemetry;
  pipeline::OutputOptions output;

  template <class V>
  void visit(V& v) {
    v.section("pipeline", pipeline, "how the pipeline runs");
    v.section("camera", camera, "frame sources");
    v.section("tracking", tracking, "tracking stage (localization front end)");
    v.section("map", map, "map capacities and 3D cells");
    v.section("depth", depth, "keyframe creation and depth inference");
    v.section("backend", backend, "local bundle adjustment of the covisibility window");
    v.section("culling", culling, "removal of redundant keyframes and bad map points");
    v.section("loop", loop, "loop closure (retrieval, Sim(3) check, pose graph)");
    v.section("relocalization", relocalization,
              "relocalization after tracking is lost (retrieval, descriptor PnP-RANSAC, "
              "projection refinement)");
    v.section("board", board, "thread placement and latency budgets");
    v.section("telemetry", telemetry, "latency and allocation accounting");
    v.section("output", output, "output files");
  }
};

}  // namespace mer::app
