# Cross toolchain for 64-bit ARM boards (Raspberry Pi 4/5, Jetson, i.MX8 ...).
#
# Uses aarch64-linux-gnu-g++ (Debian: g++-aarch64-linux-gnu) when installed; otherwise
# falls back to clang with --target, so the preset always configures. Libraries are
# searched in MER_SYSROOT (default: Debian multiarch, i.e. packages installed as
# 'libopencv-core-dev:arm64'). Without them only platform/ is configured (see the warning).
set(CMAKE_SYSTEM_NAME Linux)
set(CMAKE_SYSTEM_PROCESSOR aarch64)

set(MER_CROSS_TRIPLE aarch64-linux-gnu)
find_program(MER_CROSS_GXX ${MER_CROSS_TRIPLE}-g++)
if(MER_CROSS_GXX)
  set(CMAKE_CXX_COMPILER "${MER_CROSS_GXX}")
else()
  find_program(MER_CLANGXX NAMES clang++ clang++-14 REQUIRED)
  set(CMAKE_CXX_COMPILER "${MER_CLANGXX}")
  set(CMAKE_CXX_COMPILER_TARGET ${MER_CROSS_TRIPLE})
  # No aarch64 libc to link against: check the compiler by compiling only.
  set(CMAKE_TRY_COMPILE_TARGET_TYPE STATIC_LIBRARY)
endif()

set(MER_SYSROOT "" CACHE PATH "Sysroot holding aarch64 libraries (empty: Debian multiarch)")
if(MER_SYSROOT)
  set(CMAKE_SYSROOT "${MER_SYSROOT}")
  set(CMAKE_FIND_ROOT_PATH "${MER_SYSROOT}")
else()
  set(CMAKE_LIBRARY_ARCHITECTURE ${MER_CROSS_TRIPLE})
endif()
set(CMAKE_FIND_ROOT_PATH_MODE_PROGRAM NEVER)
set(CMAKE_FIND_ROOT_PATH_MODE_LIBRARY ONLY)
set(CMAKE_FIND_ROOT_PATH_MODE_PACKAGE ONLY)
