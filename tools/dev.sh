#!/usr/bin/env bash
# mer-slam developer entry point. On a fresh Debian 12 machine:
#   tools/dev.sh demo    install what is missing, build (Release), run mer_slam on the
#                        synthetic camera and print its summary
#   tools/dev.sh test    install what is missing, build, run the whole test suite
# Other commands:
#   tools/dev.sh setup              apt-get install the missing build dependencies
#   tools/dev.sh build [preset]     configure + build (presets: default release asan tsan arm64)
#   tools/dev.sh test [preset] [tier]
#                                   setup + build + ctest. Tiers (CTest labels): unit (the fast
#                                   edit-compile-test loop), replay, concurrency, hw, fuzz,
#                                   lint, bench; default: all. Presets: asan runs the unit and
#                                   fuzz tiers under ASan + UBSan, tsan the concurrency tier
#   tools/dev.sh lint               clang-format + clang-tidy checks (also run by ctest)
#   tools/dev.sh bench              build Release and run the Google Benchmark suite
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
JOBS="${MER_JOBS:-2}"

# Debian packages the build, tests and lint need.
PACKAGES=(
  g++ cmake make ccache pkg-config
  libeigen3-dev
  libceres-dev
  libopencv-core-dev libopencv-imgproc-dev libopencv-features2d-dev libopencv-imgcodecs-dev
  libcamera-dev
  libgtest-dev libbenchmark-dev
  # photo textures of the synthetic camera (camera.synthetic.texture: photo)
  mate-backgrounds
  clang-format clang-tidy
  # tools/results.sh reads the runs' summary.json and the benchmarks' JSON
  jq
  # real-driver tests (label 'hw'): a stock Debian kernel booted in qemu
  qemu-system-x86 busybox-static cpio xz-utils kmod
  libcamera-ipa gcc-12 libelf1 libssl3
)

log() { printf '\033[1m[dev.sh]\033[0m %s\n' "$*"; }

setup() {
  local missing=()
  for p in "${PACKAGES[@]}"; do
    if ! dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q 'install ok installed'; then
      missing+=("$p")
    fi
  done
  if [ ${#missing[@]} -eq 0 ]; then
    log "all build dependencies present"
    return
  fi
  log "installing: ${missing[*]}"
  local sudo=()
  if [ "$(id -u)" -ne 0 ]; then
    command -v sudo >/dev/null || { echo "dev.sh: need root or sudo to install ${missing[*]}" >&2; exit 1; }
    sudo=(sudo)
  fi
  "${sudo[@]}" env DEBIAN_FRONTEND=noninteractive apt-get update -qq
  "${sudo[@]}" env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends "${missing[@]}"
}

build() {
  local preset="${1:-default}"
  shift || true
  log "configure + build preset '$preset' $*"
  cmake --preset "$preset" >/dev/null
  cmake --build --preset "$preset" -j "$JOBS" "$@"
}

PRESETS=(default release asan tsan arm64)
TIERS=(unit replay concurrency hw fuzz lint bench)

run_tests() {
  local preset=default tier="" a
  for a in "$@"; do
    if [[ " ${PRESETS[*]} " == *" $a "* ]]; then
      preset="$a"
    elif [[ " ${TIERS[*]} " == *" $a "* ]]; then
      tier="$a"
    else
      echo "dev.sh: test: '$a' is neither a preset (${PRESETS[*]}) nor a tier (${TIERS[*]})" >&2
      exit 2
    fi
  done
  setup
  build "$preset"
  local filter=()
  [ -z "$tier" ] || filter=(-L "^${tier}\$")
  log "ctest preset '$preset'${tier:+, tier '$tier'}"
  local start=$SECONDS
  ctest --preset "$preset" --output-on-failure -j "$JOBS" "${filter[@]}"
  log "tests took $((SECONDS - start)) s"
}

demo() {
  setup
  build release --target mer_slam
  local out="$ROOT/build/demo-output"
  log "mer_slam on the synthetic camera (threaded, camera rate) -> $out"
  "$ROOT/build/release/src/app/mer_slam" --input synthetic:room_orbit --output "$out"
  log "outputs: $(cd "$out" && ls | tr '\n' ' ')"
}

lint() {
  build default
  ctest --preset default -L lint --output-on-failure -j "$JOBS"
}

bench() {
  setup
  build release
  for b in "$ROOT"/build/release/tests/bench/mer_bench_*; do
    [ -x "$b" ] || continue
    log "$(basename "$b")"
    "$b" --benchmark_repetitions=5 --benchmark_report_aggregates_only=true
  done
}

cmd="${1:-help}"
shift || true
case "$cmd" in
  setup) setup ;;
  build) setup; build "${1:-default}" ;;
  test) run_tests "$@" ;;
  demo) demo ;;
  lint) setup; lint ;;
  bench) bench ;;
  *) sed -n '2,15p' "$0" | sed 's/^# \{0,1\}//'; [ "$cmd" = help ] || exit 2 ;;
esac
