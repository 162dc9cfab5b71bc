#pragma once

#include <optional>
#include <span>
#include <string_view>

#include "platform/rt_thread.h"

namespace mer::platform {

/// Every thread of the application, declared as data (one table per board, after PX4's
/// work-queue table). A plain aggregate: the app copies a board's entry and applies the
/// YAML overrides of core/priority to the copy.
///
/// Priorities: capture is highest (it must never miss a buffer dequeue), then tracking,
/// then the back end (local optimization); depth, loop closure, output and the log writer run
/// with normal scheduling. The depth and back-end threads share the map's writer lock, a
/// priority-inheritance mutex, so the back end never waits behind preempted depth work. Capture and
/// tracking are pinned to separate cores where the board has >= 4 cores, leaving core 0 to the
/// kernel's interrupts and housekeeping.
struct BoardThreads {
  /// Camera dequeue / replay feeder.
  ThreadSpec capture;
  /// Feature extraction, localization, keyframe decision.
  ThreadSpec tracking;
  /// Trajectory / map output writers.
  ThreadSpec output;
  /// LogDrain writer.
  ThreadSpec log;
  /// Keyframe creation: depth inference and insertion into the map (normal scheduling).
  ThreadSpec depth;
  /// Back end: local bundle adjustment and map culling after each keyframe (below tracking).
  ThreadSpec backend;
  /// Loop detection and map fusion (reserved).
  ThreadSpec loop;
};

/// Generic x86-64 host / CI: no pinning (works on 2-core machines), priorities as on the
/// boards (they fall back to normal scheduling, with one warning each, without CAP_SYS_NICE).
inline constexpr BoardThreads kBoardGenericX86{
    .capture = {"mer_capture", -1, 80},
    .tracking = {"mer_tracking", -1, 70},
    .output = {"mer_output", -1, 0},
    .log = {"mer_log", -1, 0},
    .depth = {"mer_depth", -1, 0},
    .backend = {"mer_backend", -1, 60},
    .loop = {"mer_loop", -1, 0},
};

/// Raspberry Pi 4 (4x Cortex-A72): core 0 housekeeping/IRQs, capture on 1, tracking on 2,
/// backend on 3; the normal-priority threads float.
inline constexpr BoardThreads kBoardRpi4{
    .capture = {"mer_capture", 1, 80},
    .tracking = {"mer_tracking", 2, 70},
    .output = {"mer_output", -1, 0},
    .log = {"mer_log", -1, 0},
    .depth = {"mer_depth", -1, 0},
    .backend = {"mer_backend", 3, 60},
    .loop = {"mer_loop", -1, 0},
};

/// Jetson Orin (6 to 12 Cortex-A78AE; the table uses cores 0..5 so it fits the Orin Nano):
/// capture 1, tracking 2, backend 3, depth 4, loop 5; output and log float.
inline constexpr BoardThreads kBoardJetsonOrin{
    .capture = {"mer_capture", 1, 80},
    .tracking = {"mer_tracking", 2, 70},
    .output = {"mer_output", -1, 0},
    .log = {"mer_log", -1, 0},
    .depth = {"mer_depth", 4, 0},
    .backend = {"mer_backend", 3, 60},
    .loop = {"mer_loop", 5, 0},
};

/// The thread table of the board called `name` ("generic_x86", "rpi4", "jetson_orin"),
/// or nullopt for an unknown name.
std::optional<BoardThreads> find_board(std::string_view name) noexcept;

/// Names accepted by find_board(), in a stable order (for error messages and --help).
std::span<const std::string_view> board_names() noexcept;

}  // namespace mer::platform
