#!/usr/bin/env bash
# Runs a libcamera test program inside a qemu VM booted from a stock Debian kernel, against
# the kernel's `vimc` virtual media pipeline (real media controller, V4L2 subdevices and
# videobuf2), driven by libcamera's own vimc pipeline handler and IPA module.
#
#   tools/hw/libcamera_vimc_vm.sh --binary PROG [--cache DIR] [--timeout S] [--smp N]
#                                 [--log-levels L] [-- ARGS...]
#
# What it does (every step cached under --cache, default build/hw-cache, shared with
# tools/hw/vivid_vm.sh: the same kernel, the same lock):
#   1. fetches the kernel package linux-image-amd64 depends on and extracts its vmlinux
#      (tools/hw/vm_common.sh, as for vivid);
#   2. Debian's kernel has no vimc: builds vimc.ko out of tree. apt-get downloads the
#      kernel's own source version (read from the vmlinux banner) of linux-source-6.1,
#      linux-headers-<kver>, linux-headers-<abi>-common and linux-kbuild-6.1, unpacks them
#      with dpkg-deb into the cache (nothing is installed), takes only
#      drivers/media/test-drivers/vimc from the source and runs
#      make -C <headers> M=<vimc> modules with gcc-12, the kernel's compiler;
#   3. base initramfs: busybox-static, vimc's dependency modules in load order, vimc.ko and
#      an /init that marks every video4linux and media device initialized in the udev
#      database (libcamera enumerates through libudev; the guest has no udevd);
#   4. test cpio: PROG, libcamera's vimc IPA module (+ .sign), its proxy and its
#      configuration at their installed paths (package libcamera-ipa), and the shared
#      libraries of all of them (ldd);
#   5. boots qemu (TCG), runs PROG ARGS with LIBCAMERA_LOG_LEVELS=L (default: warnings),
#      prints "MER_HW_RESULT rc=N" and exits qemu through isa-debug-exit with that code.
# Exit status: 0 when PROG passed in the VM; 1 on any failure (missing tools or packages
# included: this test must not pass silently where it cannot run).
set -euo pipefail

SCRIPT_DIR="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
ROOT="$(cd "$SCRIPT_DIR/../.." && pwd)"

readonly ROOT_MODULE="vimc"
readonly VIMC_SRC_SUBDIR="drivers/media/test-drivers/vimc"
readonly KERNEL_CC="gcc-12"  # Debian builds the 6.1 kernel with gcc-12 (.kernelvariables)
readonly BUILD_JOBS=2
readonly IPA_PACKAGE="libcamera-ipa"
# The vimc IPA pieces inside libcamera-ipa: module, its signature, the isolating proxy and
# the configuration file the IPA opens at init.
readonly IPA_FILES_RE='/(ipa_vimc\.so|ipa_vimc\.so\.sign|vimc_ipa_proxy|vimc/vimc\.conf)$'
readonly VM_REQUIRED_PACKAGES="qemu-system-x86 busybox-static cpio xz-utils kmod gcc-12 make libcamera-ipa"
VM_TAG="libcamera_vm"
# MER_QEMU overrides the emulator (e.g. to check that a missing one fails the test).
QEMU="${MER_QEMU:-qemu-system-x86_64}"
# shellcheck source=tools/hw/vm_common.sh
source "$SCRIPT_DIR/vm_common.sh"

BINARY=""
CACHE="$ROOT/build/hw-cache"
TIMEOUT_S=240
SMP=2
# libcamera's warnings, minus the sensor-database notes vimc's sensor always triggers.
LOG_LEVELS="CameraSensor:ERROR,CameraSensorProperties:ERROR,*:WARN"  # first match wins
PROG_ARGS=()

usage() { sed -n '2,28p' "${BASH_SOURCE[0]}" | sed 's/^# \{0,1\}//'; }

while [ $# -gt 0 ]; do
  case "$1" in
    --binary) BINARY="$2"; shift 2 ;;
    --cache) CACHE="$2"; shift 2 ;;
    --timeout) TIMEOUT_S="$2"; shift 2 ;;
    --smp) SMP="$2"; shift 2 ;;
    --log-levels) LOG_LEVELS="$2"; shift 2 ;;
    --) shift; PROG_ARGS=("$@"); break ;;
    -h | --help) usage; exit 0 ;;
    *) usage >&2; vm_fail "unknown argument '$1'" ;;
  esac
done
[ -n "$BINARY" ] || vm_fail "--binary PROG is required"
[ -x "$BINARY" ] || vm_fail "test program '$BINARY' does not exist or is not executable"

vm_require_tools cpio xz modprobe modinfo depmod apt-get apt-cache dpkg dpkg-deb ldd flock \
  timeout tar make "$KERNEL_CC"
mapfile -t ipa_files < <(dpkg -L "$IPA_PACKAGE" 2>/dev/null | grep -E "$IPA_FILES_RE" || true)
[ ${#ipa_files[@]} -eq 4 ] ||
  vm_fail "libcamera's vimc IPA files not found (package $IPA_PACKAGE installed? found: ${ipa_files[*]-none}; 'tools/dev.sh setup' installs it)"

vm_lock_cache "$CACHE"
t_start=$(date +%s.%N)

# ---- 1. kernel ---------------------------------------------------------------------------
vm_fetch_kernel
vm_extract_vmlinux
kdir="$VM_KDIR"

# ---- 2. vimc.ko, built out of tree -------------------------------------------------------
kdebver=$(vm_kernel_debian_version)
[ -n "$kdebver" ] || vm_fail "$VM_VMLINUX: no 'Debian <version>' in the kernel banner"
series=$(echo "$VM_KVER" | cut -d. -f1,2)  # 6.1
kabi="${VM_KVER%-amd64}"                   # 6.1.0-56
vimc_dir="$CACHE/vimc/$VM_KVER-$kdebver"
vimc_ko="$vimc_dir/vimc.ko"
if [ ! -s "$vimc_ko" ]; then
  t_build=$(date +%s.%N)
  work="$CACHE/vimc/work"
  rm -rf "$work"
  mkdir -p "$work/root"
  pkgs=("linux-source-$series=$kdebver" "linux-headers-$VM_KVER=$kdebver"
    "linux-headers-$kabi-common=$kdebver" "linux-kbuild-$series=$kdebver")
  vm_log "fetching ${pkgs[*]} (apt-get download)"
  (cd "$work" && apt-get download -q "${pkgs[@]}" >"$work/download.log" 2>&1) ||
    { cat "$work/download.log" >&2; vm_fail "apt-get download failed (stale package lists? run 'apt-get update')"; }
  src_deb=$(find "$work" -maxdepth 1 -name "linux-source-${series}_*.deb" | head -n1)
  [ -n "$src_deb" ] || vm_fail "apt-get download produced no linux-source-$series .deb"
  # Only vimc's directory out of the ~1.4 GB tree; the rest is streamed past.
  vm_log "extracting $VIMC_SRC_SUBDIR from $(basename "$src_deb")"
  dpkg-deb --fsys-tarfile "$src_deb" |
    tar -xO "./usr/src/linux-source-$series.tar.xz" | xz -dc -T"$BUILD_JOBS" |
    tar -x -C "$work" "linux-source-$series/$VIMC_SRC_SUBDIR" ||
    vm_fail "cannot extract $VIMC_SRC_SUBDIR from $(basename "$src_deb")"
  rm -f "$src_deb"
  vimc_src="$work/linux-source-$series/$VIMC_SRC_SUBDIR"
  [ -f "$vimc_src/Makefile" ] || vm_fail "no $VIMC_SRC_SUBDIR in linux-source-$series $kdebver"
  for deb in "$work"/*.deb; do dpkg-deb -x "$deb" "$work/root"; done
  rm -f "$work"/*.deb
  headers="$work/root/usr/src/linux-headers-$VM_KVER"
  [ -f "$headers/Makefile" ] || vm_fail "no usr/src/linux-headers-$VM_KVER in linux-headers-$VM_KVER"
  # The arch headers include the common ones by absolute path; point it into the cache.
  # (scripts/ and tools/ are relative symlinks into linux-kbuild, unpacked beside.)
  sed -i "s|^include /usr/src/|include $work/root/usr/src/|" "$headers/Makefile"
  vm_log "building vimc.ko ($KERNEL_CC, -j$BUILD_JOBS)"
  make -C "$headers" M="$vimc_src" CONFIG_VIDEO_VIMC=m CC="$KERNEL_CC" -j"$BUILD_JOBS" \
    modules >"$work/build.log" 2>&1 ||
    { tail -n 40 "$work/build.log" >&2; vm_fail "vimc build failed (log: $work/build.log)"; }
  vermagic=$(modinfo -F vermagic "$vimc_src/vimc.ko")
  [ "${vermagic%% *}" = "$VM_KVER" ] || vm_fail "vimc.ko vermagic '$vermagic' does not match $VM_KVER"
  rm -rf "$vimc_dir"
  mkdir -p "$vimc_dir"
  cp "$vimc_src/vimc.ko" "$vimc_ko.tmp"
  mv "$vimc_ko.tmp" "$vimc_ko"
  rm -rf "$work"
  # Drop modules built for kernels cached earlier.
  for old in "$CACHE"/vimc/*; do
    [ "$old" = "$vimc_dir" ] || rm -rf "$old"
  done
  vm_log "vimc.ko for $VM_KVER ($kdebver) built in $(vm_elapsed "$t_build" "$(date +%s.%N)") s"
fi

# ---- 3. modules + base initramfs ---------------------------------------------------------
base_cpio="$kdir/vimc-base.cpio"
init_src="$kdir/vimc-init"
write_init() {
  echo '#!/bin/busybox sh'
  echo '# Generated by tools/hw/libcamera_vimc_vm.sh: load vimc, run the libcamera test, report, power off.'
  vm_init_prologue
  vm_init_load_modules
  cat <<'EOF'
# libcamera enumerates devices through libudev, which lists only devices udev has
# initialized. No udevd here: write the database entries it would ("I:" = initialized).
mkdir -p /run/udev/data
for d in /sys/class/video4linux/* /sys/bus/media/devices/*; do
  [ -r "$d/dev" ] && echo "I:1" >"/run/udev/data/c$(cat "$d/dev")"
done
echo "MER_HW_UDEV_MARKED $(ls /run/udev/data | wc -l) devices"
[ -r /mer/env ] && . /mer/env
EOF
  vm_init_run_test
  vm_init_epilogue
}
if [ ! -s "$base_cpio" ] || [ "$vimc_ko" -nt "$base_cpio" ] ||
  ! cmp -s <(write_init) "$init_src" 2>/dev/null; then
  vm_log "building base initramfs (busybox + $ROOT_MODULE modules)"
  stage="$kdir/vimc-stage"
  rm -rf "$stage"
  mkdir -p "$stage"/{bin,dev,proc,sys,tmp,run,modules,mer}
  cp "$BUSYBOX" "$stage/bin/busybox"
  write_init >"$init_src"
  cp "$init_src" "$stage/init"
  chmod 755 "$stage/init"
  # vimc's dependencies from the stock kernel, in modprobe's load order, then vimc itself.
  IFS=',' read -r -a deps <<<"$(modinfo -F depends "$vimc_ko")"
  [ ${#deps[@]} -gt 0 ] || vm_fail "$vimc_ko: no module dependencies recorded"
  mapfile -t mods < <(vm_module_chain "${deps[@]}")
  [ ${#mods[@]} -ge ${#deps[@]} ] || vm_fail "cannot resolve vimc's dependencies (${deps[*]}) in $VM_KPKG"
  : >"$stage/modules/order"
  for m in "${mods[@]}"; do
    name=$(vm_stage_module "$m" "$stage/modules")
    echo "$name" >>"$stage/modules/order"
  done
  cp "$vimc_ko" "$stage/modules/vimc.ko"
  echo "vimc.ko" >>"$stage/modules/order"
  vm_log "modules: $(awk '{print $1}' "$stage/modules/order" | tr '\n' ' ')"
  vm_cpio "$stage" "$base_cpio"
  rm -rf "$stage"
fi

# ---- 4. test program + libcamera runtime cpio --------------------------------------------
run="$CACHE/run-libcamera"
rm -rf "$run"
mkdir -p "$run/stage/mer"
cp "$BINARY" "$run/stage/mer/test"
printf '%s ' "${PROG_ARGS[@]+"${PROG_ARGS[@]}"}" >"$run/stage/mer/args"
{
  printf "export LIBCAMERA_LOG_LEVELS='%s'\n" "$LOG_LEVELS"
  echo "export HOME=/tmp"
  # liblttng-ust (linked by libcamera) must not wait for a session daemon.
  echo "export LTTNG_UST_REGISTER_TIMEOUT=0"
} >"$run/stage/mer/env"
ipa_bins=()
for f in "${ipa_files[@]}"; do
  mkdir -p "$run/stage$(dirname "$f")"
  cp -L "$f" "$run/stage$f"
  case "$f" in *.so | *_proxy) ipa_bins+=("$f") ;; esac
done
vm_stage_libs "$run/stage" "$BINARY" "${ipa_bins[@]}"
grep -q 'libcamera' < <(ldd "$BINARY") || vm_fail "$BINARY does not link libcamera"
# ---- 5. pack, boot, check ---------------------------------------------------------------
vm_pack_boot_check "$base_cpio" "$run" "$t_start" "$TIMEOUT_S" "$SMP"
