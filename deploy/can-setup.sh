#!/usr/bin/env bash
# Bring up a CAN interface for prml2-edge. Idempotent: running it twice changes nothing.
#
#   deploy/can-setup.sh can0 [BITRATE] [RESTART_MS] [TXQUEUELEN]   # real SocketCAN (e.g. Orin mttcan)
#   deploy/can-setup.sh vcan0                                       # virtual bus for bench testing
#
# Needs root (or CAP_NET_ADMIN). Exits non-zero with one line saying what is missing.
set -euo pipefail

iface="${1:-can0}"
bitrate="${2:-500000}"
restart_ms="${3:-100}"
txqueuelen="${4:-1000}"

die() { echo "can-setup: $*" >&2; exit 1; }

command -v ip >/dev/null 2>&1 || die "'ip' not found: install iproute2"
[ "$(id -u)" -eq 0 ] || die "needs root (or CAP_NET_ADMIN) to configure $iface: run with sudo"

load_module() {
    local mod="$1"
    if [ -d "/sys/module/$mod" ]; then return 0; fi
    modprobe "$mod" 2>/dev/null || die "kernel module '$mod' is not available (modprobe $mod failed): install your kernel's CAN modules (linux-modules-extra) or use a kernel with CONFIG_CAN_${mod^^}"
}

case "$iface" in
  vcan*)
    load_module vcan
    if ! ip link show "$iface" >/dev/null 2>&1; then
        ip link add dev "$iface" type vcan
    fi
    ip link set "$iface" txqueuelen "$txqueuelen"
    ip link set up "$iface"
    ;;
  *)
    load_module can
    load_module can_raw
    ip link show "$iface" >/dev/null 2>&1 || die "no interface '$iface': is the CAN controller enabled (Orin: mttcan, see deploy/INSTALL_JETSON.md) or the USB adapter plugged in?"
    current=$(ip -details link show "$iface" | sed -n 's/.*bitrate \([0-9]*\).*/\1/p' | head -n1)
    state=$(ip link show "$iface" | grep -o 'state [A-Z]*' | awk '{print $2}')
    if [ "$current" != "$bitrate" ] || [ "$state" != "UP" ]; then
        ip link set "$iface" down
        ip link set "$iface" type can bitrate "$bitrate" restart-ms "$restart_ms"
    fi
    ip link set "$iface" txqueuelen "$txqueuelen"
    ip link set up "$iface"
    ;;
esac

echo "can-setup: $iface is up ($(ip -details link show "$iface" | grep -o 'state [A-Z-]*' | head -n1))"
