#include "app/stop_signal.h"

#include <csignal>

namespace mer::app {
namespace {

std::atomic<bool> g_stop{false};
static_assert(std::atomic<bool>::is_always_lock_free, "signal handler needs a lock-free flag");

extern "C" void on_stop_signal(int /*sig*/) {
  g_stop.store(true, std::memory_order_relaxed);
}

}  // namespace

std::atomic<bool>& stop_flag() {
  return g_stop;
}

void install_stop_signal_handlers() {
  struct sigaction sa {};
  sa.sa_handler = on_stop_signal;
  sigemptyset(&sa.sa_mask);
  sigaction(SIGINT, &sa, nullptr);
  sigaction(SIGTERM, &sa, nullptr);
}

}  // namespace mer::app
