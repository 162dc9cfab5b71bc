#include "platform/thread_table.h"

#include <array>

namespace mer::platform {

namespace {

struct BoardEntry {
  std::string_view name;
  const BoardThreads* threads;
};

constexpr std::array<BoardEntry, 3> kBoards{{
    {"generic_x86", &kBoardGenericX86},
    {"rpi4", &kBoardRpi4},
    {"jetson_orin", &kBoardJetsonOrin},
}};

constexpr std::array<std::string_view, kBoards.size()> kBoardNames{kBoards[0].name, kBoards[1].name,
                                                                   kBoards[2].name};

}  // namespace

std::optional<BoardThreads> find_board(std::string_view name) noexcept {
  for (const BoardEntry& e : kBoards) {
    if (e.name == name) {
      return *e.threads;
    }
  }
  return std::nullopt;
}

std::span<const std::string_view> board_names() noexcept {
  return kBoardNames;
}

}  // namespace mer::platform
