# shellcheck shell=bash disable=SC2034  # VM_* results are read by the sourcing scripts
# Shared pieces of the real-driver VM tests (tools/hw/*_vm.sh). Sourced, not run.
#
# A test script sets VM_TAG (log prefix), QEMU (emulator) and VM_REQUIRED_PACKAGES (named
# when a tool is missing), then uses, in this order:
#   vm_require_tools TOOL...          fail naming every missing tool (busybox-static included)
#   vm_lock_cache DIR                 create the cache, set CACHE (absolute), take its lock
#   vm_fetch_kernel                   VM_KPKG, VM_KVER, VM_KDIR, VM_KROOT (apt-get download)
#   vm_extract_vmlinux                VM_VMLINUX (uncompressed ELF, booted directly)
#   vm_module_chain MODULE...         module files in load order (modprobe --show-depends)
#   vm_stage_module FILE DIR          copy (decompress) one module into DIR, print its name
#   vm_stage_libs STAGE FILE...       the shared libraries FILEs need (ldd) + the loader
#   vm_cpio STAGE OUT                 newc archive of STAGE (the kernel unpacks concatenations)
#   vm_init_prologue, vm_init_load_modules, vm_init_run_test, vm_init_epilogue
#                                     the pieces of the guest's /init, in that order
#   vm_boot INITRD TIMEOUT SMP        boot qemu (TCG), log to VM_CONSOLE, set VM_QEMU_RC
#   vm_check_result TIMEOUT           fail unless the guest reported rc=0 through qemu
# Everything downloaded or derived is cached under CACHE; several scripts share one cache
# (the kernel is fetched once) and its lock, so they never build or boot concurrently.

# depmod/modprobe live in /sbin, which a non-root PATH may lack.
export PATH="$PATH:/usr/sbin:/sbin"

# Guest settings (no magic numbers below).
readonly VM_GUEST_MEM="512M"
readonly VM_DEBUG_EXIT_PORT=0xf4    # isa-debug-exit I/O port; guest writes its exit code here
readonly VM_DEBUG_EXIT_PORT_DEC=244 # the same port for dd seek= on /dev/port
readonly VM_KERNEL_META_PKG="linux-image-amd64"
readonly VM_KERNEL_APPEND="console=ttyS0 quiet panic=-1 mitigations=off"

VM_TAG="${VM_TAG:-vm}"
QEMU="${QEMU:-qemu-system-x86_64}"
BUSYBOX=""

vm_log() { printf '[%s] %s\n' "$VM_TAG" "$*"; }
vm_fail() {
  printf '[%s] FAIL: %s\n' "$VM_TAG" "$*" >&2
  exit 1
}
# Seconds between two `date +%s.%N` stamps, one decimal.
vm_elapsed() { awk -v a="$1" -v b="$2" 'BEGIN{printf "%.1f", b-a}'; }

# ---- tools -------------------------------------------------------------------------------
vm_require_tools() {
  local missing=() tool b
  for tool in "$QEMU" "$@"; do
    command -v "$tool" >/dev/null 2>&1 || missing+=("$tool")
  done
  for b in /bin/busybox /usr/bin/busybox; do
    # Must be the static build: the guest has no libc of its own for it.
    if [ -x "$b" ] && ! ldd "$b" >/dev/null 2>&1; then BUSYBOX="$b"; break; fi
  done
  [ -n "$BUSYBOX" ] || missing+=("busybox (static)")
  if [ ${#missing[@]} -gt 0 ]; then
    vm_fail "missing tools: ${missing[*]} (Debian packages: $VM_REQUIRED_PACKAGES; 'tools/dev.sh setup' installs them)"
  fi
}

# ---- cache -------------------------------------------------------------------------------
vm_lock_cache() {
  mkdir -p "$1"
  CACHE="$(cd "$1" && pwd)"
  # One VM build at a time per cache (parallel ctest runs share it).
  exec 9>"$CACHE/.lock"
  flock 9
}

# ---- kernel package ----------------------------------------------------------------------
# Resolves the kernel package linux-image-amd64 depends on, apt-get downloads and unpacks
# it (once), drops kernels cached earlier and runs nothing else.
vm_fetch_kernel() {
  local kpkg deb old
  kpkg=$(apt-cache depends "$VM_KERNEL_META_PKG" 2>/dev/null |
    sed -n 's/^ *Depends: \(linux-image-[0-9][^ ]*-amd64\)$/\1/p' | head -n1 || true)
  if [ -z "$kpkg" ]; then
    # Offline re-run: use the kernel cached last time, if any.
    kpkg=$(cat "$CACHE/kernel.pkg" 2>/dev/null || true)
    [ -n "$kpkg" ] || vm_fail "cannot resolve the kernel package of '$VM_KERNEL_META_PKG' with apt-cache (run 'apt-get update')"
    vm_log "apt-cache could not resolve $VM_KERNEL_META_PKG; using cached $kpkg"
  fi
  VM_KPKG="$kpkg"
  VM_KVER="${kpkg#linux-image-}"
  VM_KDIR="$CACHE/kernel/$VM_KVER"
  VM_KROOT="$VM_KDIR/root"
  if [ ! -f "$VM_KDIR/.unpacked" ]; then
    vm_log "fetching $kpkg (apt-get download)"
    rm -rf "$VM_KDIR"
    mkdir -p "$VM_KDIR"
    (cd "$VM_KDIR" && apt-get download -q "$kpkg" >"$VM_KDIR/download.log" 2>&1) ||
      { cat "$VM_KDIR/download.log" >&2; vm_fail "apt-get download $kpkg failed (stale package lists? run 'apt-get update')"; }
    deb=$(find "$VM_KDIR" -maxdepth 1 -name "*.deb" | head -n1)
    [ -n "$deb" ] || vm_fail "apt-get download $kpkg produced no .deb"
    dpkg-deb -x "$deb" "$VM_KROOT"
    rm -f "$deb"
    touch "$VM_KDIR/.unpacked"
    # Drop kernels cached by earlier runs (Debian moved on).
    for old in "$CACHE"/kernel/*; do
      [ "$old" = "$VM_KDIR" ] || rm -rf "$old"
    done
  fi
  echo "$kpkg" >"$CACHE/kernel.pkg"
  [ -d "$VM_KROOT/lib/modules/$VM_KVER" ] || vm_fail "no lib/modules/$VM_KVER in $kpkg"
}

# ---- vmlinux -----------------------------------------------------------------------------
vm_extract_vmlinux() {
  local bz off
  VM_VMLINUX="$VM_KDIR/vmlinux"
  [ -s "$VM_VMLINUX" ] && return 0
  bz="$VM_KROOT/boot/vmlinuz-$VM_KVER"
  [ -f "$bz" ] || vm_fail "no boot/vmlinuz-$VM_KVER in $VM_KPKG"
  # The bzImage carries the kernel as an xz stream; find its magic (FD 37 7A 58 5A 00).
  off=$(LC_ALL=C grep -obUaP '\xFD7zXZ\x00' "$bz" | head -n1 | cut -d: -f1 || true)
  [ -n "$off" ] || vm_fail "$bz: no xz payload found (compression changed?)"
  # Trailing data after the stream is expected; keep what decompressed.
  tail -c +"$((off + 1))" "$bz" | xz -dc --single-stream >"$VM_VMLINUX.tmp" 2>/dev/null || true
  [ "$(head -c 4 "$VM_VMLINUX.tmp" | od -An -tx1 | tr -d ' ')" = "7f454c46" ] ||
    vm_fail "$bz: extracted payload is not an ELF vmlinux"
  mv "$VM_VMLINUX.tmp" "$VM_VMLINUX"
}

# The Debian package version the kernel was built from ("6.1.192-2"), read from the
# vmlinux banner ("... #1 SMP PREEMPT_DYNAMIC Debian 6.1.192-2 (date)"): works offline.
vm_kernel_debian_version() {
  LC_ALL=C grep -aoE 'Linux version [^ ]+ .*Debian [0-9][^ ]*' "$VM_VMLINUX" | head -n1 |
    sed 's/.*Debian //'
}

# ---- modules -----------------------------------------------------------------------------
# Module files of MODULEs and their dependencies in load order (dependencies first, each
# file once).
vm_module_chain() {
  local m
  depmod -b "$VM_KROOT" "$VM_KVER"
  for m in "$@"; do
    modprobe -d "$VM_KROOT" -S "$VM_KVER" --show-depends "$m"
  done | awk '$1 == "insmod" && !seen[$2]++ {print $2}'
}

# Copies module FILE into DIR, decompressing .ko.xz; prints the staged file name.
vm_stage_module() {
  local name
  name=$(basename "$1")
  case "$name" in
    *.ko.xz) xz -dc "$1" >"$2/${name%.xz}"; name="${name%.xz}" ;;
    *.ko.zst) vm_fail "$1: zstd-compressed modules are not supported by this script" ;;
    *) cp "$1" "$2/$name" ;;
  esac
  echo "$name"
}

# ---- initramfs ---------------------------------------------------------------------------
# Copies the shared libraries of each FILE (ldd) and the dynamic loader into STAGE at the
# paths the loader looks for them.
vm_stage_libs() {
  local stage="$1" lib
  shift
  while read -r lib; do
    [ -n "$lib" ] || continue
    mkdir -p "$stage$(dirname "$lib")"
    cp -L "$lib" "$stage$lib"
  done < <(for f in "$@"; do ldd "$f"; done |
    awk '/=> \// {print $3} /^[[:space:]]*\/[^ ]+ \(/ {print $1}' | sort -u)
}

vm_cpio() {
  (cd "$1" && find . -print0 | LC_ALL=C sort -z | cpio -o -0 -H newc --quiet) >"$2.tmp"
  mv "$2.tmp" "$2"
}

# Start of /init: busybox applets, pseudo file systems, boot marker.
vm_init_prologue() {
  cat <<'EOF'
/bin/busybox --install -s /bin
export PATH=/bin
mount -t proc proc /proc
mount -t sysfs sysfs /sys
mount -t devtmpfs devtmpfs /dev
mkdir -p /tmp && mount -t tmpfs tmpfs /tmp
echo "MER_HW_BOOTED $(cut -d' ' -f1 /proc/uptime)s"
EOF
}

# /init: insert the modules listed in /modules/order ("file params" per line) in order.
vm_init_load_modules() {
  cat <<'EOF2'
while read -r mod params; do
  insmod "/modules/$mod" $params || echo "MER_HW_INSMOD_FAILED $mod"
done < /modules/order
echo "MER_HW_MODULES_LOADED $(cut -d' ' -f1 /proc/uptime)s $(ls /dev | grep -c '^video')"
EOF2
}

# /init: run /mer/test with the arguments in /mer/args; its exit status in $rc.
vm_init_run_test() {
  cat <<'EOF2'
rc=127
if [ -x /mer/test ]; then
  /mer/test $(cat /mer/args) </dev/null
  rc=$?
fi
EOF2
}

# End of /init: report $rc, hand it to qemu through isa-debug-exit, power off.
vm_init_epilogue() {
  cat <<EOF
echo "MER_HW_RESULT rc=\$rc uptime=\$(cut -d' ' -f1 /proc/uptime)s"
# isa-debug-exit: qemu exits with (rc << 1) | 1.
printf "\\\\\$(printf %03o \$rc)" | dd of=/dev/port bs=1 seek=$VM_DEBUG_EXIT_PORT_DEC count=1 2>/dev/null
poweroff -f
EOF
}

# ---- boot --------------------------------------------------------------------------------
# Boots VM_VMLINUX with INITRD; console in VM_CONSOLE (next to INITRD), exit status in
# VM_QEMU_RC, wall time in VM_BOOT_S.
vm_boot() {
  local initrd="$1" timeout_s="$2" smp="$3" t0 t1
  VM_CONSOLE="$(dirname "$initrd")/console.log"
  t0=$(date +%s.%N)
  set +e
  timeout --kill-after=5 "$timeout_s" "$QEMU" \
    -accel tcg -cpu max -smp "$smp" -m "$VM_GUEST_MEM" -nographic -no-reboot -nic none \
    -kernel "$VM_VMLINUX" -initrd "$initrd" \
    -append "$VM_KERNEL_APPEND" \
    -device isa-debug-exit,iobase=$VM_DEBUG_EXIT_PORT,iosize=0x04 \
    </dev/null 2>&1 | tr -d '\r' | tee "$VM_CONSOLE"
  VM_QEMU_RC=${PIPESTATUS[0]}
  set -e
  t1=$(date +%s.%N)
  VM_BOOT_S=$(vm_elapsed "$t0" "$t1")
}

# Fails unless the console has the guest's MER_HW_RESULT rc=0 and qemu's exit status
# carries the same code (a guest that crashed or hung cannot pass).
vm_check_result() {
  local timeout_s="$1" result expected
  if [ "$VM_QEMU_RC" -eq 124 ] || [ "$VM_QEMU_RC" -eq 137 ]; then
    tail -n 30 "$VM_CONSOLE" >&2
    vm_fail "VM did not finish within ${timeout_s} s (hang)"
  fi
  result=$(sed -n 's/^MER_HW_RESULT rc=\([0-9]*\).*/\1/p' "$VM_CONSOLE" | tail -n1)
  [ -n "$result" ] || { tail -n 30 "$VM_CONSOLE" >&2; vm_fail "no MER_HW_RESULT marker in the console (guest crashed?)"; }
  if grep -q '^MER_HW_INSMOD_FAILED' "$VM_CONSOLE"; then
    grep '^MER_HW_INSMOD_FAILED' "$VM_CONSOLE" >&2
    vm_fail "module loading failed in the guest"
  fi
  # isa-debug-exit encodes the guest's code as (rc << 1) | 1; qemu's exit status keeps
  # the low 8 bits (a crashed program's rc=134 arrives as 13).
  expected=$((((result << 1) | 1) & 0xff))
  if [ "$VM_QEMU_RC" -ne "$expected" ]; then
    vm_fail "qemu exit status $VM_QEMU_RC does not carry the guest result $result (expected $expected)"
  fi
  [ "$result" -eq 0 ] || vm_fail "test program failed in the VM (rc=$result); see the checks above"
}

# Packs the staged test files, appends them to the base initramfs (the kernel unpacks
# concatenated newc archives in order), boots, reports timings and checks the result.
# Usage: vm_pack_boot_check BASE_CPIO RUN_DIR T_START TIMEOUT_S SMP
vm_pack_boot_check() {
  local base_cpio=$1 run=$2 t_start=$3 timeout_s=$4 smp=$5
  vm_cpio "$run/stage" "$run/test.cpio"
  cat "$base_cpio" "$run/test.cpio" >"$run/initrd.cpio"
  local t_prep t_end
  t_prep=$(date +%s.%N)
  vm_log "prepared in $(vm_elapsed "$t_start" "$t_prep") s" \
    "(kernel $VM_KVER, initrd $(($(stat -c %s "$run/initrd.cpio") / 1024 / 1024)) MiB)"
  vm_boot "$run/initrd.cpio" "$timeout_s" "$smp"
  t_end=$(date +%s.%N)
  vm_log "VM wall time ${VM_BOOT_S} s (total $(vm_elapsed "$t_start" "$t_end") s), qemu exit status $VM_QEMU_RC, console log $VM_CONSOLE"
  vm_check_result "$timeout_s"
  vm_log "PASS"
}
