# Compile options applied to every project target (never to third-party code).
#   mer_target_defaults(<target>)
# -Werror is on for project code; sanitizers are selected with MER_SANITIZER.

set(MER_WARNINGS -Wall -Wextra -Wpedantic -Werror -Wshadow -Wnon-virtual-dtor)
if(CMAKE_CXX_COMPILER_ID STREQUAL "GNU")
  # GCC 12 at -O3 reports -Wrestrict false positives inside libstdc++'s std::string
  # operator+ (GCC bug 105329); keep the rest of -Werror.
  list(APPEND MER_WARNINGS -Wno-restrict)
endif()

if(MER_SANITIZER STREQUAL "asan")
  set(MER_SAN_FLAGS -fsanitize=address,undefined -fno-sanitize-recover=undefined -fno-omit-frame-pointer)
  if(CMAKE_CXX_COMPILER_ID STREQUAL "GNU")
    # The instrumentation defeats GCC's flow analysis: GCC 12 reports a memset bound of
    # 2^64 - 101 inside std::fill_n of a sized vector (tests/fuzz/make_recording_corpus.cpp),
    # which the uninstrumented build does not. The sanitizers check those accesses at run time.
    list(APPEND MER_WARNINGS -Wno-stringop-overflow)
  endif()
elseif(MER_SANITIZER STREQUAL "tsan")
  set(MER_SAN_FLAGS -fsanitize=thread -fno-omit-frame-pointer)
elseif(NOT MER_SANITIZER STREQUAL "")
  message(FATAL_ERROR "MER_SANITIZER must be '', 'asan' or 'tsan', found '${MER_SANITIZER}'")
endif()
if(MER_SAN_FLAGS)
  add_compile_options(${MER_SAN_FLAGS})
  add_link_options(${MER_SAN_FLAGS})
endif()

function(mer_target_defaults target)
  target_compile_options(${target} PRIVATE ${MER_WARNINGS})
  target_include_directories(${target} PUBLIC
    "${PROJECT_SOURCE_DIR}"            # platform/..., hal/...
    "${PROJECT_SOURCE_DIR}/src")       # core/..., pipeline/...
endfunction()
