#!/usr/bin/env bash
# Install the robot controller as a systemd service on a Jetson Nano (JetPack 4.6:
# Ubuntu 18.04, aarch64), or remove it with --uninstall. Safe to run again: each step
# checks what is already there. --dry-run prints every action without doing any.
#
#   sudo systemd/install.sh                      install or update, enable at boot
#   sudo systemd/install.sh --start              ... and (re)start the service now
#   systemd/install.sh --dry-run                 show what would be done (no root needed)
#   sudo systemd/install.sh --uninstall          remove; keep config, state, logs, user
#   sudo systemd/install.sh --uninstall --purge  remove everything, including those
#
# See docs/robot-install.md.
set -euo pipefail

REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
PREFIX=/opt/robot-controller
CONFIG_SRC="$REPO/config/robot.yaml"
ETC_DIR=/etc/robot-controller
STATE_DIR=/var/lib/robot-controller
LOG_DIR=/var/log/robot-controller
UNIT_NAME=robot-controller.service
UNIT_DIR=/etc/systemd/system
UDEV_DIR=/etc/udev/rules.d
MODULES_LOAD=/etc/modules-load.d/robot-controller.conf
SERVICE_USER=robot
SERVICE_GROUPS="dialout plugdev video"
PYTHON=python3.8
# gcc, libc6-dev, python3.8-dev: robotctl kernels build compiles the kernels into a C extension.
APT_PACKAGES="python3.8 python3.8-venv libusb-1.0-0 udev gcc libc6-dev python3.8-dev"
# PyPI's version is 2.55.1.6486: "==2.55.1" matches nothing (PEP 440 pads with zeros).
# It is the last pyrealsense2 with a cp38 manylinux2014 aarch64 wheel.
PYREALSENSE_PIN="pyrealsense2==2.55.1.6486"
NUMPY_PIN="numpy<1.25"   # 1.24 is the last numpy series for Python 3.8
# perf: the plane fit's compiled kernels (numba 0.58.1 / llvmlite 0.41.1 have cp38 aarch64 wheels);
# without them the localizer runs its numpy code at a quarter more CPU.
EXTRAS="realsense,record,perf"
WHEELS=""
MOTOR_USB=""
MOTOR_SERIAL=""
DRY_RUN=0
UNINSTALL=0
PURGE=0
START=0

usage() {
    cat <<EOF
usage: $0 [options]
  --dry-run            print every action, change nothing (root not needed)
  --uninstall          stop, disable and remove the service, udev rules and $PREFIX
  --purge              with --uninstall: also remove $ETC_DIR, $STATE_DIR, $LOG_DIR and user '$SERVICE_USER'
  --prefix DIR         install directory (default $PREFIX)
  --config FILE        robot config to install as $ETC_DIR/robot.yaml if none is there yet
                       (default $CONFIG_SRC)
  --extras LIST        pip extras of the project (default $EXTRAS; add 'live' for the Foxglove view)
  --wheels DIR         install offline from wheels in DIR (pip --no-index --find-links DIR)
  --motor-usb VID:PID  USB ids of the motor board's serial adapter (default 10c4:ea60, a CP2102)
  --motor-serial SER   pin the adapter by its serial number (udevadm info --attribute-walk)
  --start              (re)start the service after installing
  -h, --help           this help
EOF
}

die() { echo "install.sh: error: $*" >&2; exit 1; }
warn() { echo "install.sh: warning: $*" >&2; }
note() { echo "== $*"; }

# Every change to the system goes through run: printed, and executed unless --dry-run.
run() {
    printf '+'
    printf ' %q' "$@"
    printf '\n'
    if [ "$DRY_RUN" -eq 0 ]; then
        "$@"
    fi
}

# Install SRC as DEST (mode MODE) unless DEST already has that content.
install_file() {
    local src="$1" dest="$2" mode="$3"
    if [ -f "$dest" ] && cmp -s "$src" "$dest"; then
        echo "= $dest unchanged"
        return 0
    fi
    run install -D -m "$mode" "$src" "$dest"
}

while [ $# -gt 0 ]; do
    case "$1" in
        --dry-run) DRY_RUN=1 ;;
        --uninstall) UNINSTALL=1 ;;
        --purge) PURGE=1 ;;
        --prefix) [ $# -ge 2 ] || die "--prefix needs a directory"; PREFIX="$2"; shift ;;
        --config) [ $# -ge 2 ] || die "--config needs a file"; CONFIG_SRC="$2"; shift ;;
        --extras) [ $# -ge 2 ] || die "--extras needs a list"; EXTRAS="$2"; shift ;;
        --wheels) [ $# -ge 2 ] || die "--wheels needs a directory"; WHEELS="$2"; shift ;;
        --motor-usb) [ $# -ge 2 ] || die "--motor-usb needs VID:PID"; MOTOR_USB="$2"; shift ;;
        --motor-serial) [ $# -ge 2 ] || die "--motor-serial needs a serial number"; MOTOR_SERIAL="$2"; shift ;;
        --start) START=1 ;;
        -h|--help) usage; exit 0 ;;
        *) usage >&2; die "unknown option: $1" ;;
    esac
    shift
done

case "$PREFIX" in
    /?*) PREFIX="${PREFIX%/}" ;;
    *) die "--prefix must be an absolute path other than /, got '$PREFIX'" ;;
esac
[ "$PURGE" -eq 0 ] || [ "$UNINSTALL" -eq 1 ] || die "--purge only goes with --uninstall"
if [ -n "$MOTOR_USB" ] && ! [[ "$MOTOR_USB" =~ ^[0-9a-fA-F]{4}:[0-9a-fA-F]{4}$ ]]; then
    die "--motor-usb must look like 10c4:ea60, got '$MOTOR_USB'"
fi
if [ -n "$MOTOR_SERIAL" ] && ! [[ "$MOTOR_SERIAL" =~ ^[A-Za-z0-9._-]+$ ]]; then
    die "--motor-serial may contain letters, digits, '.', '_' and '-' only"
fi

VENV="$PREFIX/venv"
if [ "$DRY_RUN" -eq 1 ]; then
    note "dry run: nothing will be changed"
elif [ "$(id -u)" -ne 0 ]; then
    die "must run as root (sudo $0 ...), or use --dry-run to see what it would do"
fi

check_platform() {
    local arch os_id="" os_version=""
    arch="$(uname -m)"
    if [ -r /etc/os-release ]; then
        # shellcheck disable=SC1091
        os_id="$(. /etc/os-release && echo "${ID:-}")"
        # shellcheck disable=SC1091
        os_version="$(. /etc/os-release && echo "${VERSION_ID:-}")"
    fi
    [ "$arch" = aarch64 ] || warn "this is $arch, not aarch64: written for the Jetson Nano; pyrealsense2's pin may have no wheel here"
    if [ "$os_id" != ubuntu ] || [ "$os_version" != 18.04 ]; then
        warn "this is ${os_id:-unknown} ${os_version:-unknown}, not Ubuntu 18.04 (JetPack 4.6): package names may differ"
    fi
    [ -e /etc/nv_tegra_release ] || warn "no /etc/nv_tegra_release: this does not look like a Jetson"
}

# ------------------------------------------------------------------ install steps

install_apt_packages() {
    local missing="" pkg
    for pkg in $APT_PACKAGES; do
        if ! dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q "install ok installed"; then
            missing="$missing $pkg"
        fi
    done
    if [ -z "$missing" ]; then
        echo "= apt packages present: $APT_PACKAGES"
        return 0
    fi
    note "installing$missing (python3.8 is in Ubuntu 18.04's universe component, beside the system's 3.6)"
    run apt-get update
    if [ "$DRY_RUN" -eq 0 ] && ! apt-cache policy "$PYTHON" | grep -q 'Candidate: [0-9]'; then
        die "apt has no $PYTHON package: enable Ubuntu's universe component (sudo add-apt-repository universe)"
    fi
    # shellcheck disable=SC2086  # word splitting of the package list is intended
    run env DEBIAN_FRONTEND=noninteractive apt-get install -y --no-install-recommends $missing
}

ensure_user() {
    local group
    for group in $SERVICE_GROUPS; do
        if ! getent group "$group" >/dev/null; then
            run groupadd --system "$group"
        fi
    done
    if getent passwd "$SERVICE_USER" >/dev/null; then
        echo "= user $SERVICE_USER exists"
    else
        run useradd --system --user-group --home-dir "$STATE_DIR" --no-create-home \
            --shell /usr/sbin/nologin --comment "robot controller service" "$SERVICE_USER"
    fi
}

ensure_venv() {
    local have=""
    if [ -x "$VENV/bin/python" ]; then
        have="$("$VENV/bin/python" -c 'import sys; print("%d.%d" % sys.version_info[:2])' 2>/dev/null || true)"
    fi
    if [ "$have" = 3.8 ]; then
        echo "= venv $VENV (Python 3.8) exists"
    else
        if [ -n "$have" ] || [ -e "$VENV" ]; then
            note "replacing $VENV (Python ${have:-broken}) with a Python 3.8 venv"
            run rm -rf "$VENV"
        fi
        run mkdir -p "$PREFIX"
        run "$PYTHON" -m venv "$VENV"
    fi
}

pip_install() {
    local pip_opts=()
    if [ -n "$WHEELS" ]; then
        pip_opts=(--no-index --find-links "$WHEELS")
    fi
    # Ubuntu's venv starts with pip 9, which predates manylinux2014 wheels.
    # ${a[@]+...}: an empty array is "unbound" to set -u in bash before 4.4.
    run "$VENV/bin/python" -m pip install ${pip_opts[@]+"${pip_opts[@]}"} --upgrade "pip>=20.3" setuptools wheel
    run "$VENV/bin/python" -m pip install ${pip_opts[@]+"${pip_opts[@]}"} --upgrade \
        "$NUMPY_PIN" "$PYREALSENSE_PIN" "${REPO}[${EXTRAS}]"
    # Same version number, new code: make sure the checkout's code is what gets installed.
    run "$VENV/bin/python" -m pip install ${pip_opts[@]+"${pip_opts[@]}"} --no-deps --force-reinstall "$REPO"
    run install -D -m 0644 "$REPO/docs/robot-install.md" "$PREFIX/docs/robot-install.md"
}

build_kernels() {
    # The compiled kernels ahead of time, where the service looks (its NUMBA_CACHE_DIR): it then
    # runs them without numba and LLVM in the process (about 120 MiB less). Built as the service
    # user into its state directory; named by a hash of the kernels' sources, so an update that
    # changes them builds anew. A failed build is no failed install: the service compiles the
    # same kernels with numba's JIT at its first start instead.
    case ",$EXTRAS," in *,perf,*) ;; *) return 0 ;; esac
    run install -d -o "$SERVICE_USER" -g "$SERVICE_USER" -m 0750 "$STATE_DIR" "$STATE_DIR/numba-cache"
    if ! run runuser -u "$SERVICE_USER" -- env NUMBA_CACHE_DIR="$STATE_DIR/numba-cache" \
            "$VENV/bin/robotctl" kernels build; then
        warn "the kernels were not compiled ahead of time: the service compiles them with numba at its first start"
    fi
}

install_config() {
    run install -d -m 0755 "$ETC_DIR"
    if [ -e "$ETC_DIR/robot.yaml" ]; then
        echo "= $ETC_DIR/robot.yaml exists: kept (compare with $CONFIG_SRC after updates)"
    else
        [ -f "$CONFIG_SRC" ] || die "config $CONFIG_SRC not found"
        run install -m 0644 "$CONFIG_SRC" "$ETC_DIR/robot.yaml"
    fi
    local map
    if [ -d "$REPO/config/maps" ]; then
        for map in "$REPO"/config/maps/*.yaml; do
            [ -e "$map" ] || continue
            if [ -e "$ETC_DIR/maps/$(basename "$map")" ]; then
                echo "= $ETC_DIR/maps/$(basename "$map") exists: kept"
            else
                run install -D -m 0644 "$map" "$ETC_DIR/maps/$(basename "$map")"
            fi
        done
    fi
}

motor_rule() {
    # The shipped rule's comments and one rule line for the adapter given on the command line.
    local src="$REPO/systemd/99-robot-motor-board.rules" out="$1" vid="10c4" pid="ea60" match
    if [ -n "$MOTOR_USB" ]; then
        vid="${MOTOR_USB%%:*}"
        pid="${MOTOR_USB##*:}"
    fi
    vid="$(echo "$vid" | tr 'A-F' 'a-f')"
    pid="$(echo "$pid" | tr 'A-F' 'a-f')"
    match="ATTRS{idVendor}==\"$vid\", ATTRS{idProduct}==\"$pid\""
    if [ -n "$MOTOR_SERIAL" ]; then
        match="$match, ATTRS{serial}==\"$MOTOR_SERIAL\""
    fi
    {
        grep '^#' "$src"
        echo "# Written by install.sh --motor-usb ${MOTOR_USB:-10c4:ea60}${MOTOR_SERIAL:+ --motor-serial $MOTOR_SERIAL}"
        echo "SUBSYSTEM==\"tty\", $match, SYMLINK+=\"robot-motor-board\", GROUP=\"dialout\", MODE=\"0660\", ENV{ID_MM_DEVICE_IGNORE}=\"1\""
    } >"$out"
}

install_udev_rules() {
    local tmp
    install_file "$REPO/systemd/99-realsense-libusb.rules" "$UDEV_DIR/99-realsense-libusb.rules" 0644
    if [ -z "$MOTOR_USB" ] && [ -z "$MOTOR_SERIAL" ]; then
        install_file "$REPO/systemd/99-robot-motor-board.rules" "$UDEV_DIR/99-robot-motor-board.rules" 0644
    else
        tmp="$(mktemp)"
        motor_rule "$tmp"
        note "motor-board rule: $(grep -v '^#' "$tmp")"
        install_file "$tmp" "$UDEV_DIR/99-robot-motor-board.rules" 0644
        rm -f "$tmp"
    fi
    run udevadm control --reload-rules
    run udevadm trigger --subsystem-match=usb --subsystem-match=tty
    # The unit's DeviceAllow=char-ttyUSB/char-ttyACM needs these drivers registered before it starts.
    install_file "$REPO/systemd/robot-controller-modules.conf" "$MODULES_LOAD" 0644
    run modprobe -a usbserial cdc_acm || warn "could not load usbserial/cdc_acm now; they load at the next boot"
}

install_unit() {
    local tmp
    if [ "$PREFIX" = /opt/robot-controller ]; then
        install_file "$REPO/systemd/$UNIT_NAME" "$UNIT_DIR/$UNIT_NAME" 0644
    else
        tmp="$(mktemp)"
        sed "s#/opt/robot-controller#$PREFIX#g" "$REPO/systemd/$UNIT_NAME" >"$tmp"
        note "unit with /opt/robot-controller replaced by $PREFIX"
        install_file "$tmp" "$UNIT_DIR/$UNIT_NAME" 0644
        rm -f "$tmp"
    fi
    run systemctl daemon-reload
    run systemctl enable "$UNIT_NAME"
    if [ "$START" -eq 1 ]; then
        run systemctl restart "$UNIT_NAME"
    fi
}

do_install() {
    check_platform
    install_apt_packages
    ensure_user
    ensure_venv
    pip_install
    build_kernels
    install_config
    install_udev_rules
    install_unit
    note "installed. Edit $ETC_DIR/robot.yaml, then: sudo systemctl restart $UNIT_NAME"
    note "status: systemctl status $UNIT_NAME   log: journalctl -u $UNIT_NAME -f"
}

# ------------------------------------------------------------------ uninstall

remove_if_ours() {
    # Another librealsense install may own the same rules file: remove it only if it is ours.
    local ours="$1" dest="$2"
    if [ -e "$dest" ]; then
        if [ -z "$ours" ] || cmp -s "$ours" "$dest"; then
            run rm -f "$dest"
        else
            echo "= $dest differs from ours: kept"
        fi
    fi
}

do_uninstall() {
    if [ -e "$UNIT_DIR/$UNIT_NAME" ]; then
        run systemctl disable --now "$UNIT_NAME" || warn "could not stop/disable $UNIT_NAME"
        run rm -f "$UNIT_DIR/$UNIT_NAME"
        run systemctl daemon-reload || warn "systemctl daemon-reload failed"
        run systemctl reset-failed "$UNIT_NAME" || true
    else
        echo "= no $UNIT_DIR/$UNIT_NAME"
    fi
    remove_if_ours "$REPO/systemd/99-realsense-libusb.rules" "$UDEV_DIR/99-realsense-libusb.rules"
    remove_if_ours "" "$UDEV_DIR/99-robot-motor-board.rules"
    remove_if_ours "$REPO/systemd/robot-controller-modules.conf" "$MODULES_LOAD"
    run udevadm control --reload-rules
    if [ -e "$PREFIX" ]; then
        # Never rm -rf a directory we did not make (a mistyped --prefix /usr, say).
        if [ -e "$VENV/bin/robotctl" ] || [ -z "$(ls -A "$PREFIX")" ]; then
            run rm -rf "$PREFIX"
        else
            warn "$PREFIX has no venv/bin/robotctl: not ours, not removed"
        fi
    else
        echo "= no $PREFIX"
    fi
    if [ "$PURGE" -eq 1 ]; then
        run rm -rf "$ETC_DIR" "$STATE_DIR" "$LOG_DIR"
        if getent passwd "$SERVICE_USER" >/dev/null; then
            run userdel "$SERVICE_USER"
        fi
    else
        note "kept $ETC_DIR, $STATE_DIR, $LOG_DIR and user '$SERVICE_USER' (--purge removes them)"
    fi
    note "apt packages ($APT_PACKAGES) are left installed"
}

if [ "$UNINSTALL" -eq 1 ]; then
    do_uninstall
else
    do_install
fi
