#pragma once
/// @file stop_signal.h
/// SIGINT/SIGTERM handling shared by the command-line programs: the handler only sets a
/// lock-free flag that the run loops poll, so every output is still written.

#include <atomic>

namespace mer::app {

/// The process-wide stop flag (set by SIGINT/SIGTERM once installed).
std::atomic<bool>& stop_flag();

/// Installs the SIGINT and SIGTERM handlers that set stop_flag().
void install_stop_signal_handlers();

}  // namespace mer::app
