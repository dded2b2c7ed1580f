#!/usr/bin/env bash
# Run a command (default: the `vcan` pytest tests) inside a small qemu VM whose
# kernel has SocketCAN, with vcan0 up (mtu 72, so CAN FD works).
#
#   bash .ci/vcan_vm.sh [command...]      (from the repo root)
#   bash .ci/vcan_vm.sh --prepare         (host tools, kernel and initramfs only; no boot)
#
# --prepare lets CI fetch and build everything the VM needs in the background while
# the host test suite runs; the later boot finds it cached.
#
# Why a VM: the CI host kernel has no CAN (AF_CAN fails with errno 97, and
# `ip link add type vcan` fails), and /dev/kvm does not boot a stock kernel, so
# this boots Debian's own kernel under qemu's software emulation (TCG).
#
# How: Debian's linux-image package is unpacked (never installed) into a cache
# dir; a busybox initramfs loads the virtio/9p/overlay modules, mounts the host
# root read-only over 9p with a tmpfs overlay on top (the guest sees the host's
# Python and packages, its writes are thrown away), switch_roots into it and
# runs a per-run script that loads vcan, brings up vcan0 and runs the command in
# the repo dir. The script prints VCAN_VM_EXIT=<code> on the serial console and
# powers off; this host side parses that and exits with the code (non-zero if
# the VM failed to boot or timed out: 125 = guest set-up failed, 3 = no exit
# code came back, e.g. a timeout; 2 = host-side set-up failed).
#
# Environment knobs: VCAN_VM_CACHE (default /tmp/socd-vcan-vm), VCAN_VM_TIMEOUT
# (seconds, default 900), VCAN_VM_MEM (MiB, default 2048), VCAN_VM_SMP (default 2),
# VCAN_VM_CPU (qemu -cpu model).
set -euo pipefail

started=$(date +%s.%N)
REPO=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd -P)
CACHE=${VCAN_VM_CACHE:-/tmp/socd-vcan-vm}
TIMEOUT=${VCAN_VM_TIMEOUT:-900}
MEM=${VCAN_VM_MEM:-2048}
SMP=${VCAN_VM_SMP:-2}
# Measured under TCG: importing python-can (numpy, pandas, sympy via asammdf)
# took about half the CPU time on a Haswell model that it took on `-cpu max`;
# numpy >= 2.4 needs x86-64-v2 at least, so no older model than Nehalem. The
# features TCG cannot emulate are switched off to keep qemu from warning.
CPU=${VCAN_VM_CPU:-Haswell-noTSX,-pcid,-x2apic,-tsc-deadline,-invpcid}
# Bump when the initramfs recipe below changes, so a stale cache is rebuilt.
RECIPE=1
# Modules the initramfs needs before the host root is mounted.
INITRD_MODULES=(virtio_pci 9pnet_virtio 9p overlay)

prepare_only=0
if [ "${1:-}" = "--prepare" ]; then
    prepare_only=1
    shift
fi
if [ $# -eq 0 ]; then
    set -- python -m pytest -m vcan -v tests
fi

log() { printf 'vcan-vm: %s\n' "$*" >&2; }
die() { log "error: $*"; exit 2; }
seconds_since() { awk -v a="$1" -v b="$(date +%s.%N)" 'BEGIN { printf "%.1f", b - a }'; }

# ---------------------------------------------------------------- host tools
need_apt_update=1
apt_quiet() {
    if [ "$need_apt_update" = 1 ]; then
        DEBIAN_FRONTEND=noninteractive apt-get update -qq >/dev/null
        need_apt_update=0
    fi
    DEBIAN_FRONTEND=noninteractive "$@"
}

missing=()
command -v qemu-system-x86_64 >/dev/null || missing+=(qemu-system-x86)
dpkg -s busybox-static >/dev/null 2>&1 || missing+=(busybox-static)
command -v modprobe >/dev/null && command -v depmod >/dev/null || missing+=(kmod)
command -v ip >/dev/null || missing+=(iproute2)
command -v candump >/dev/null || missing+=(can-utils)
if [ ${#missing[@]} -gt 0 ]; then
    log "installing ${missing[*]}"
    apt_quiet apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
fi
BUSYBOX=$(command -v busybox) || die "busybox not found after installing busybox-static"

# ------------------------------------------- kernel + initramfs (cached build)
mkdir -p "$CACHE"
exec 9>"$CACHE/.lock"
flock 9  # one builder at a time; later runs reuse the result

build_dir=""
if [ -f "$CACHE/current/ready" ] && [ "$(cat "$CACHE/current/ready")" = "$RECIPE" ]; then
    build_dir=$(readlink -f "$CACHE/current")
else
    rm -rf "$CACHE"/.build.* "$CACHE"/*-r[0-9]*  # interrupted or outdated builds
    apt_quiet true
    # linux-image-amd64 is the metapackage; it depends on linux-image-6.1.0-NN-amd64.
    kpkg=$(apt-cache depends linux-image-amd64 2>/dev/null |
        awk '$1 == "Depends:" && $2 ~ /^linux-image-[0-9]/ { print $2; exit }')
    [ -n "$kpkg" ] || die "cannot resolve the kernel package from 'apt-cache depends linux-image-amd64'"
    kver=${kpkg#linux-image-}
    log "building VM kernel + initramfs from $kpkg into $CACHE"
    build_dir="$CACHE/$kver-r$RECIPE"
    tmp=$(mktemp -d "$CACHE/.build.XXXXXX")
    # (as root, apt warns that _apt cannot write into the 0700 temp dir: harmless)
    if ! out=$(cd "$tmp" && apt-get download -qq "$kpkg" 2>&1); then
        printf '%s\n' "$out" >&2
        die "apt-get download $kpkg failed"
    fi
    dpkg-deb -x "$tmp"/"$kpkg"_*.deb "$tmp/kernel"
    rm -f "$tmp"/*.deb
    depmod -b "$tmp/kernel" "$kver"
    for m in vcan can-raw can-bcm "${INITRD_MODULES[@]}"; do
        modprobe -d "$tmp/kernel" -S "$kver" --show-depends "$m" >/dev/null ||
            die "kernel $kver has no module $m"
    done

    initrd="$tmp/initrd"
    mkdir -p "$initrd/bin" "$initrd/modules" "$initrd/dev" "$initrd/proc" "$initrd/sys" \
        "$initrd/lower" "$initrd/rw" "$initrd/newroot"
    cp "$BUSYBOX" "$initrd/bin/busybox"
    # --show-depends lists `insmod <path>` in load order, dependencies first.
    modprobe -d "$tmp/kernel" -S "$kver" -a --show-depends "${INITRD_MODULES[@]}" |
        awk '$1 == "insmod" && !seen[$2]++ { print $2 }' |
        while read -r ko; do
            cp "$ko" "$initrd/modules/"
            basename "$ko" >>"$initrd/modules/order"
        done
    cat >"$initrd/init" <<'INIT'
#!/bin/busybox sh
/bin/busybox --install -s /bin
export PATH=/bin
mount -t devtmpfs devtmpfs /dev
exec </dev/console >/dev/console 2>&1
mount -t proc proc /proc
mount -t sysfs sysfs /sys
fail() { echo "vcan-vm: init: $*"; echo "VCAN_VM_EXIT=125"; poweroff -f; }
while read -r ko; do insmod "/modules/$ko" || fail "insmod $ko"; done </modules/order
run=""
for arg in $(cat /proc/cmdline); do
    case "$arg" in socd.run=*) run=${arg#socd.run=} ;; esac
done
[ -n "$run" ] || fail "no socd.run= on the kernel command line"
mount -t 9p -o trans=virtio,version=9p2000.L,ro,cache=loose,msize=512000 hostroot /lower ||
    fail "cannot mount the host root over 9p"
mount -t tmpfs -o mode=0755 tmpfs /rw
mkdir /rw/upper /rw/work
mount -t overlay -o lowerdir=/lower,upperdir=/rw/upper,workdir=/rw/work overlay /newroot ||
    fail "cannot mount the overlay root"
[ -f "/newroot$run" ] || fail "$run is not visible in the guest"
[ -x /newroot/bin/bash ] || fail "no /bin/bash on the host root"
mount --move /dev /newroot/dev
mount --move /proc /newroot/proc
mount --move /sys /newroot/sys
exec switch_root /newroot /bin/bash "$run"
INIT
    chmod 755 "$initrd/init"
    (cd "$initrd" && find . | "$BUSYBOX" cpio -o -H newc 2>/dev/null | gzip -1) >"$tmp/initrd.gz"
    rm -rf "$initrd"
    cp "$tmp/kernel/boot/vmlinuz-$kver" "$tmp/vmlinuz"
    echo "$kver" >"$tmp/kver"
    echo "$RECIPE" >"$tmp/ready"
    rm -rf "$build_dir"
    mv "$tmp" "$build_dir"
    ln -sfn "$(basename "$build_dir")" "$CACHE/current"
fi
flock -u 9
kver=$(cat "$build_dir/kver")
modules="$build_dir/kernel/lib/modules/$kver"
prep_s=$(seconds_since "$started")
if [ "$prepare_only" = 1 ]; then
    log "prepared kernel $kver in $CACHE (${prep_s} s)"
    exit 0
fi

# ---------------------------------------------------------- per-run script
# The guest gets the host's environment essentials; PATH starts with the
# directory of the real interpreter (a pyenv shim would just add start-up time).
python_bin=$(command -v python || command -v python3 || true)
if [ -n "$python_bin" ]; then
    real_python=$("$python_bin" -c 'import sys; print(sys.executable)')
    guest_path="$(dirname "$real_python"):$PATH"
else
    guest_path=$PATH
fi
rundir=$(mktemp -d /tmp/socd-vcan-run.XXXXXX)
serial_log="$rundir/console.log"
trap 'rm -rf "$rundir"' EXIT

{
    echo '#!/bin/bash'
    echo 'set -u'
    printf 'export PATH=%q HOME=%q LANG=C.UTF-8 TERM=dumb\n' "$guest_path" "${HOME:-/root}"
    for var in PYTHONPATH VIRTUAL_ENV PYTEST_ADDOPTS CI; do
        if [ -n "${!var:-}" ]; then printf 'export %s=%q\n' "$var" "${!var}"; fi
    done
    printf 'KVER=%q MODULES=%q REPO=%q\n' "$kver" "$modules" "$REPO"
    cat <<'STAGE2'
fail() { echo "vcan-vm: guest: $*"; echo "VCAN_VM_EXIT=125"; /bin/busybox poweroff -f; }
mount -t tmpfs tmpfs /run
mkdir -p /dev/pts /dev/shm
mount -t devpts devpts /dev/pts
mount -t tmpfs tmpfs /dev/shm
# Kernel modules for the guest kernel: bind the unpacked tree, so modprobe (and
# the kernel's on-demand loading, e.g. can-bcm for cyclic sends) works.
mkdir -p "/lib/modules/$KVER" && mount --bind "$MODULES" "/lib/modules/$KVER" ||
    fail "cannot bind the kernel modules"
/bin/busybox hostname vcan-vm
ip link set lo up
modprobe -a can can-raw can-bcm vcan || fail "modprobe vcan failed"
ip link add dev vcan0 type vcan || fail "ip link add vcan0 failed"
ip link set vcan0 mtu 72 || fail "cannot set vcan0 mtu 72 (CAN FD)"
ip link set up vcan0 || fail "cannot bring up vcan0"
cd "$REPO" || fail "no repo dir $REPO"
echo "vcan-vm: guest up ($(uname -r), $(nproc) cpus), vcan0 mtu $(cat /sys/class/net/vcan0/mtu)"
STAGE2
    printf '%q ' "$@"
    echo
    cat <<'STAGE2'
rc=$?
echo "VCAN_VM_EXIT=$rc"
sync
/bin/busybox poweroff -f
STAGE2
} >"$rundir/run.sh"
chmod 755 "$rundir/run.sh"

# ---------------------------------------------------------------------- boot
log "booting $kver under qemu TCG (timeout ${TIMEOUT}s): $*"
boot_started=$(date +%s.%N)
set +e
timeout --kill-after=10 "$TIMEOUT" qemu-system-x86_64 \
    -accel tcg -cpu "$CPU" -smp "$SMP" -m "$MEM" \
    -nodefaults -no-user-config -display none -no-reboot -net none \
    -chardev stdio,id=console,signal=off -serial chardev:console \
    -kernel "$build_dir/vmlinuz" -initrd "$build_dir/initrd.gz" \
    -append "console=ttyS0 quiet loglevel=3 panic=-1 mitigations=off socd.run=$rundir/run.sh" \
    -virtfs local,path=/,mount_tag=hostroot,security_model=none,readonly=on,multidevs=remap \
    </dev/null 2>&1 | sed -u 's/\r//g' | tee "$serial_log"
qemu_rc=${PIPESTATUS[0]}
set -e
boot_s=$(seconds_since "$boot_started")

code=$(sed -n 's/^VCAN_VM_EXIT=\([0-9][0-9]*\)$/\1/p' "$serial_log" | tail -n 1)
if [ -z "$code" ]; then
    if [ "$qemu_rc" = 124 ] || [ "$qemu_rc" = 137 ]; then
        log "error: the VM timed out after ${TIMEOUT}s"
    else
        log "error: the VM stopped (qemu exit $qemu_rc) without reporting an exit code"
    fi
    code=3
fi
log "VM stage took $(seconds_since "$started") s (setup ${prep_s} s, boot + command ${boot_s} s); exit code $code"
exit "$code"
