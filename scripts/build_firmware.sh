#!/usr/bin/env bash
# Cross-compile the motor board core and the protocol codec (firmware_protocol/c) for a
# Cortex-M0 and an ATmega328P, the smallest parts a board maker is likely to use, and print what
# they cost. Any compiler warning fails the build (-Werror), as does a missing compiler.
#
#   scripts/build_firmware.sh [--target cortex-m0|atmega328p|all]
#
#   BUILD_DIR     where the objects go (default: a temporary directory, removed afterwards)
#   FIRMWARE_SRC  the C sources (default: firmware_protocol/c of this checkout)
#
# Per target it prints:
#   <target> flash <bytes> ...   text+data of board_core.o and mecanum_proto.o (what the task is
#                                charged for; sections a linker drops are still counted)
#   <target> linked <bytes> ...  text+data of a linked image with a minimal main that calls every
#                                function, --gc-sections, libgcc's helpers included
#   <target> ram <bytes> ...     sizeof(mb_core_t), the only memory the core keeps
#   <target> stack ...           the largest stack frames (-fstack-usage)
#   atmega328p cycles ...        per call, on a simulated 16 MHz part (only if simavr is installed)
set -euo pipefail

here="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
src="${FIRMWARE_SRC:-$here/firmware_protocol/c}"
target="all"
while [ $# -gt 0 ]; do
    case "$1" in
        --target) target="${2:?--target needs a value}"; shift 2 ;;
        -h|--help) sed -n '2,20p' "$0"; exit 0 ;;
        *) echo "build_firmware: unknown argument $1" >&2; exit 2 ;;
    esac
done
case "$target" in
    cortex-m0|atmega328p|all) ;;
    *) echo "build_firmware: unknown target $target (cortex-m0, atmega328p or all)" >&2; exit 2 ;;
esac

if [ -n "${BUILD_DIR:-}" ]; then
    out="$BUILD_DIR"
    mkdir -p "$out"
else
    out="$(mktemp -d)"
    trap 'rm -rf "$out"' EXIT
fi

common=(-std=c99 -Os -ffunction-sections -fdata-sections -Wall -Wextra -Werror -I "$src")

# A main that uses every entry point, so the linked figure is what a firmware really pays.
cat > "$out/probe_main.c" <<'EOF'
#include "board_core.h"
static mb_core_t core;
static uint8_t tx[64];
volatile uint32_t clock_us;
volatile uint8_t uart_in;
volatile int32_t encoder[4];
volatile int32_t pwm[4];
int main(void)
{
    mb_config_t cfg;
    int32_t ticks[4];
    int i;
    mb_config_default(&cfg);
    if (mb_core_init(&core, &cfg, clock_us) != MB_OK) {
        return 1;
    }
    mb_core_set_battery_mv(&core, 12000);
    for (;;) {
        mb_core_rx_byte(&core, uart_in, clock_us);
        for (i = 0; i < 4; i++) {
            ticks[i] = encoder[i];
        }
        mb_core_tick(&core, clock_us, ticks);
        mb_core_set_estop(&core, uart_in == 1u, clock_us);
        mb_core_set_motor_faults(&core, uart_in, clock_us);
        for (i = 0; i < 4; i++) {
            pwm[i] = core.setpoint_urad_s[i];
        }
        if (mb_core_tx_pending(&core) > 0u) {
            uart_in = (uint8_t)mb_core_tx_pop(&core);
            uart_in = (uint8_t)mb_core_tx_take(&core, tx, sizeof tx);
        }
    }
}
EOF
printf '#include "board_core.h"\nmb_core_t mb_ram_probe;\n' > "$out/ram_probe.c"
# GCC may call memcpy and memset even in freestanding code; the C library provides them on a real
# board, byte loops stand in for it where none is installed (built so they do not call themselves).
cat > "$out/libc_min.c" <<'EOF'
#include <stddef.h>
void *memcpy(void *dst, const void *src, size_t n);
void *memset(void *dst, int c, size_t n);
void *memcpy(void *dst, const void *src, size_t n)
{
    unsigned char *d = dst;
    const unsigned char *s = src;
    while (n--) {
        *d++ = *s++;
    }
    return dst;
}
void *memset(void *dst, int c, size_t n)
{
    unsigned char *d = dst;
    while (n--) {
        *d++ = (unsigned char)c;
    }
    return dst;
}
EOF

# text+data of the objects given, from the size tool's Berkeley output
flash_of() {
    local size_tool="$1"; shift
    "$size_tool" "$@" | awk 'NR > 1 { t += $1; d += $2 } END { printf "%d %d %d\n", t + d, t, d }'
}

build() {
    local name="$1" cc="$2" size_tool="$3"; shift 3
    local flags=("$@") dir="$out/$name" objs=() f
    for tool in "$cc" "$size_tool"; do
        if ! command -v "$tool" >/dev/null 2>&1; then
            echo "build_firmware: $tool not found (scripts/ensure_ci_tools.sh installs it)" >&2
            exit 1
        fi
    done
    mkdir -p "$dir"
    for f in board_core mecanum_proto; do
        "$cc" "${flags[@]}" "${common[@]}" -fstack-usage -c "$src/$f.c" -o "$dir/$f.o"
        objs+=("$dir/$f.o")
    done
    "$size_tool" "${objs[@]}" | sed "s|$dir/||" | sed "s/^/$name  /"
    read -r total text data < <(flash_of "$size_tool" "${objs[@]}")
    echo "$name flash $total bytes (text $text + data $data) for board_core.o + mecanum_proto.o"

    "$cc" "${flags[@]}" "${common[@]}" -fno-common -c "$out/ram_probe.c" -o "$dir/ram_probe.o"
    local ram
    ram="$("$size_tool" "$dir/ram_probe.o" | awk 'NR == 2 { print $3 }')"
    echo "$name ram $ram bytes: sizeof(mb_core_t) with MB_TX_CAPACITY 256"

    "$cc" "${flags[@]}" "${common[@]}" -c "$out/probe_main.c" -o "$dir/probe_main.o"
    case "$name" in
        cortex-m0)
            # no C library is packaged for this target: libc_min.c stands in for memcpy and
            # memset, libgcc supplies the 64-bit multiply
            "$cc" "${flags[@]}" "${common[@]}" -ffreestanding -fno-tree-loop-distribute-patterns \
                -c "$out/libc_min.c" -o "$dir/libc_min.o"
            "$cc" "${flags[@]}" -nostdlib -nostartfiles -Wl,--gc-sections -Wl,-e,main \
                "$dir/probe_main.o" "${objs[@]}" "$dir/libc_min.o" -lgcc -o "$dir/probe.elf" ;;
        *)
            "$cc" "${flags[@]}" -Wl,--gc-sections "$dir/probe_main.o" "${objs[@]}" -o "$dir/probe.elf" ;;
    esac
    read -r total text data < <(flash_of "$size_tool" "$dir/probe.elf")
    echo "$name linked $total bytes (text $text + data $data): core, codec, libgcc helpers, startup and a minimal main"

    echo "$name stack $(cat "$dir"/board_core.su "$dir"/mecanum_proto.su | sort -t$'\t' -k2 -n -r | head -4 \
        | awk -F'\t' '{ n = split($1, p, ":"); printf "%s %s B; ", p[n], $2 }')"
}

# Cycle counts on a simulated 16 MHz ATmega328P (simavr), the slowest part the core targets:
# Timer1 at clk/8 brackets each call, so the figures are multiples of 8 cycles.
avr_cycles() {
    local dir="$out/atmega328p"
    if ! command -v simavr >/dev/null 2>&1; then
        echo "atmega328p cycles: skipped (simavr not installed)"
        return 0
    fi
    cat > "$dir/cycles.c" <<'EOF'
#include <avr/interrupt.h>
#include <avr/io.h>
#include <avr/sleep.h>
#include <stdio.h>
#include "board_core.h"

static int uart_putc(char c, FILE *f) { (void)f; while (!(UCSR0A & (1 << UDRE0))) {} UDR0 = (uint8_t)c; return 0; }
static FILE uart = FDEV_SETUP_STREAM(uart_putc, NULL, _FDEV_SETUP_WRITE);
static mb_core_t core;
static uint8_t sink[MB_TX_CAPACITY];
static uint32_t now;
static int32_t ticks[4];
static uint32_t byte_max;

#define START() (TCNT1 = 0)
#define CYCLES() ((uint32_t)TCNT1 * 8u)

/* Feeds one frame; returns the cycles of its closing delimiter, the byte that does the work. */
static uint32_t frame_end(uint8_t id, const uint8_t *payload, size_t len)
{
    uint8_t wire[MP_MAX_WIRE];
    size_t n = mp_encode_frame(id, 0, payload, len, wire, sizeof wire), i;
    uint32_t c = 0;
    for (i = 0; i < n; i++) {
        START();
        mb_core_rx_byte(&core, wire[i], now);
        c = CYCLES();
        if (i + 1 < n && c > byte_max) {
            byte_max = c;
        }
    }
    mb_core_tx_take(&core, sink, sizeof sink);
    return c;
}

static uint32_t set_speeds(int32_t a, int32_t b, int32_t c, int32_t d)
{
    mp_set_wheel_speeds_t m;
    uint8_t p[MP_LEN_SET_WHEEL_SPEEDS];
    m.speed_mrad_s[0] = a; m.speed_mrad_s[1] = b; m.speed_mrad_s[2] = c; m.speed_mrad_s[3] = d;
    return frame_end(MP_SET_WHEEL_SPEEDS, p, mp_pack_set_wheel_speeds(&m, p));
}

/* n ticks of 1 ms; the slowest and the fastest */
static void run_ticks(int n, uint32_t *slow, uint32_t *fast)
{
    int k;
    *slow = 0;
    *fast = 0xFFFFFFFFu;
    for (k = 0; k < n; k++) {
        uint32_t c;
        now += 1000u;
        START();
        mb_core_tick(&core, now, ticks);
        c = CYCLES();
        *slow = c > *slow ? c : *slow;
        *fast = c < *fast ? c : *fast;
        mb_core_tx_take(&core, sink, sizeof sink);
    }
}

int main(void)
{
    mb_config_t cfg;
    mp_hello_t hello;
    uint8_t p[MP_LEN_HELLO];
    uint32_t slow, fast;
    UBRR0 = 0;
    UCSR0B = (1 << TXEN0);
    stdout = &uart;
    TCCR1A = 0;
    TCCR1B = (1 << CS11);
    mb_config_default(&cfg);
    mb_core_init(&core, &cfg, now);
    hello.minor = 0;
    hello.nonce = 0x12345678u;
    printf("cycles rx_hello_frame_end %lu\n", (unsigned long)frame_end(MP_HELLO, p, mp_pack_hello(&hello, p)));
    printf("cycles rx_speeds_frame_end %lu\n", (unsigned long)set_speeds(5000, -5000, 2500, 1234));
    run_ticks(9, &slow, &fast);
    printf("cycles tick_ramping %lu\n", (unsigned long)slow);
    printf("cycles rx_clamped_speeds_frame_end %lu\n", (unsigned long)set_speeds(40000, -25000, 10000, -3));
    printf("cycles rx_byte_inside_a_frame %lu\n", (unsigned long)byte_max);
    set_speeds(3000, 3000, 3000, 3000);
    run_ticks(150, &slow, &fast);  /* ramp done: 150 ms at rest on the target */
    run_ticks(100, &slow, &fast);
    printf("cycles tick_idle %lu\n", (unsigned long)fast);
    printf("cycles tick_with_reports %lu\n", (unsigned long)slow);
    cli();
    sleep_enable();
    sleep_cpu();  /* simavr ends the run here */
    return 0;
}
EOF
    avr-gcc -mmcu=atmega328p "${common[@]}" -Wl,--gc-sections "$dir/cycles.c" "$src/board_core.c" \
        "$src/mecanum_proto.c" -o "$dir/cycles.elf"
    timeout 120 simavr -m atmega328p -f 16000000 "$dir/cycles.elf" 2>&1 | sed 's/\x1b\[[0-9;]*m//g' \
        | awk '$1 == "cycles" { sub(/\.$/, "", $3); printf "atmega328p cycles %s %d (%.0f us at 16 MHz)\n", $2, $3, $3 / 16 }'
}

if [ "$target" = all ] || [ "$target" = cortex-m0 ]; then
    build cortex-m0 arm-none-eabi-gcc arm-none-eabi-size -mcpu=cortex-m0 -mthumb
fi
if [ "$target" = all ] || [ "$target" = atmega328p ]; then
    build atmega328p avr-gcc avr-size -mmcu=atmega328p
    avr_cycles
fi
