#!/usr/bin/env bash
# Make sure the tools the systemd tests use are present: shellcheck (lints systemd/install.sh)
# and systemd-analyze (verifies the unit), and the cross compilers of the firmware build
# (scripts/build_firmware.sh: arm-none-eabi-gcc for a Cortex-M0, avr-gcc and avr-libc for an
# ATmega328P). Installs the Debian/Ubuntu packages when we are root and have apt-get; otherwise
# only says what is missing. Always exits 0: the tests that need a missing tool skip with a
# reason instead of failing.
set -uo pipefail

missing_pkgs=()
command -v shellcheck >/dev/null 2>&1 || missing_pkgs+=(shellcheck)
# pyrealsense2 needs libusb at import time; without it every librealsense test skips.
{ ldconfig -p 2>/dev/null | grep -q "libusb-1.0.so.0"; } || missing_pkgs+=(libusb-1.0-0)
command -v systemd-analyze >/dev/null 2>&1 || missing_pkgs+=(systemd)
# Without recommends: the newlib the ARM compiler recommends is 370 MB and the board core needs
# no C library.
command -v arm-none-eabi-gcc >/dev/null 2>&1 || missing_pkgs+=(gcc-arm-none-eabi)
command -v arm-none-eabi-size >/dev/null 2>&1 || missing_pkgs+=(binutils-arm-none-eabi)
command -v avr-gcc >/dev/null 2>&1 || missing_pkgs+=(gcc-avr)
command -v avr-size >/dev/null 2>&1 || missing_pkgs+=(binutils-avr)
[ -e /usr/lib/avr/include/stdint.h ] || missing_pkgs+=(avr-libc)
# The MQTT broker the VDA 5050 tests start on a loopback port (/usr/sbin is not on every PATH).
{ command -v mosquitto || [ -x /usr/sbin/mosquitto ]; } >/dev/null 2>&1 || missing_pkgs+=(mosquitto)

if [ ${#missing_pkgs[@]} -eq 0 ]; then
    exit 0
fi

if [ "$(id -u)" -ne 0 ] || ! command -v apt-get >/dev/null 2>&1; then
    echo "ensure_ci_tools: missing ${missing_pkgs[*]} (install the Debian/Ubuntu packages of that name);" \
         "the tests that need them will be skipped" >&2
    exit 0
fi

export DEBIAN_FRONTEND=noninteractive
install_pkgs() {
    apt-get install -y -qq --no-install-recommends "${missing_pkgs[@]}" >/dev/null 2>&1
}

# Refresh the package lists only when they are empty or do not know a package yet.
needs_update=0
if [ -z "$(find /var/lib/apt/lists -maxdepth 1 -name '*_Packages*' -print -quit 2>/dev/null)" ]; then
    needs_update=1
else
    for pkg in "${missing_pkgs[@]}"; do
        if ! apt-cache policy "$pkg" 2>/dev/null | grep -q 'Candidate: [0-9]'; then
            needs_update=1
        fi
    done
fi
if [ "$needs_update" -eq 1 ]; then
    apt-get update -qq >/dev/null 2>&1 || echo "ensure_ci_tools: apt-get update failed" >&2
fi

if install_pkgs; then
    echo "ensure_ci_tools: installed ${missing_pkgs[*]}" >&2
else
    echo "ensure_ci_tools: could not install ${missing_pkgs[*]}; the tests that need them will be skipped" >&2
fi
exit 0
