/*
 * Mecanum motor board, protocol v1: the board's side as a pure state machine.
 * Specification: firmware_protocol/PROTOCOL.md (sections 3 to 7). Python twin: BoardModel in
 * drivers/chassis/emulator.py; tests/test_board_core.py runs both on the same scenarios and
 * compares every transmitted byte.
 *
 * C99, no I/O, no dynamic allocation, no global state: the caller owns an mb_core_t and feeds it
 *   - every received byte (mb_core_rx_byte),
 *   - one control tick per millisecond with the encoder counts sampled at that instant
 *     (mb_core_tick),
 *   - the e-stop input, the motor driver fault lines and the battery voltage,
 * always with the board's free-running microsecond clock (uint32_t, wrapping at 2^32). It gets
 * back the bytes to transmit (mb_core_tx_take / mb_core_tx_pop) and the ramped wheel setpoints
 * (mb_core_t.setpoint_urad_s) for the motor speed loops. The motor physics stays outside.
 *
 * Not reentrant: call every function of one core from one context (or with interrupts masked).
 * See README.md in this directory for the integration, timing and memory figures.
 */
#ifndef MECANUM_BOARD_CORE_H
#define MECANUM_BOARD_CORE_H

#include <stddef.h>
#include <stdint.h>

#include "mecanum_proto.h"

#ifdef __cplusplus
extern "C" {
#endif

/* Transmit queue size, at least one frame (MP_MAX_WIRE). One received frame queues at most 76
 * bytes, one tick at most 90; 256 leaves room for the UART to lag by a few milliseconds. A frame
 * that does not fit is dropped whole and counted in tx_dropped. */
#ifndef MB_TX_CAPACITY
#define MB_TX_CAPACITY 256u
#endif

/* Config bounds that keep every intermediate value within 32 bits (and 64 for one product). */
#define MB_MAX_SPEED_LIMIT_MRAD_S 1000000u   /* 1000 rad/s: setpoints in urad/s stay in int32 */
#define MB_MAX_ACCEL_LIMIT_MRAD_S2 4000000u  /* 4000 rad/s^2: the per-tick step stays in uint32 */

typedef enum {
    MB_OK = 0,
    MB_ERR_NULL = -1,          /* a NULL pointer */
    MB_ERR_TICKS_PER_REV = -2, /* ticks_per_rev is 0 */
    MB_ERR_MAX_SPEED = -3,     /* max_speed_mrad_s is 0 or above MB_MAX_SPEED_LIMIT_MRAD_S */
    MB_ERR_MAX_ACCEL = -4,     /* max_accel_mrad_s2 is 0 or above MB_MAX_ACCEL_LIMIT_MRAD_S2 */
    MB_ERR_WATCHDOG = -5,      /* watchdog_ms is 0 */
    MB_ERR_REPORT_PERIOD = -6, /* report_period_us is 0 */
    MB_ERR_STATUS_PERIOD = -7  /* status_period_us is 0 or 2^31 us or more */
} mb_result_t;

/* What the board announces in HELLO_REPLY and enforces. */
typedef struct {
    uint32_t ticks_per_rev;      /* encoder counts per wheel revolution, after the gearbox */
    uint32_t max_speed_mrad_s;   /* speed limit (rule 4); commands beyond it are scaled and NACKed */
    uint32_t max_accel_mrad_s2;  /* ramp limit (rule 3) */
    uint16_t watchdog_ms;        /* command watchdog (rule 1) and host-silence period (rule 2) */
    uint16_t report_period_us;   /* ENCODER_REPORT period; 10000 for the required 100 Hz */
    uint32_t status_period_us;   /* periodic STATUS; 100000 for 10 Hz */
    uint8_t fw_major, fw_minor, fw_patch;  /* the board maker's firmware version */
} mb_config_t;

/* The core's state. Caller-owned; treat it as opaque except for the read-only outputs marked. */
typedef struct {
    mb_config_t cfg;
    mp_decoder_t decoder;         /* read-only: receive counters in decoder.stats */
    /* outputs, read-only for the caller */
    int32_t setpoint_urad_s[4];   /* ramped wheel setpoints, FL, FR, RL, RR, in urad/s */
    int32_t target_urad_s[4];     /* where the ramp is heading (the last accepted command) */
    uint8_t flags;                /* MP_FLAG_* as reported in STATUS */
    uint8_t session;              /* 1 after a HELLO since init */
    uint8_t estop;
    uint8_t motor_faults;
    uint16_t battery_mv;
    uint16_t rx_errors;           /* frames dropped since init, saturating (STATUS.rx_errors) */
    uint32_t tx_dropped;          /* frames not queued because the transmit queue was full */
    /* internal */
    uint32_t dropped_seen;        /* decoder drop total already added to rx_errors */
    uint32_t last_cmd_us;         /* last accepted SET_WHEEL_SPEEDS or STOP */
    uint32_t last_rx_us;          /* last valid frame of any kind */
    uint32_t last_tick_us;
    uint32_t next_report_us;
    uint32_t next_status_us;
    /* the ramp walks one straight line in wheel-speed space from ramp_start to the target */
    int32_t ramp_start_urad_s[4];
    int32_t ramp_ratio_q30[4];    /* (target - start) / peak, 2^30 = 1 */
    uint32_t ramp_peak_urad_s;    /* largest |target - start|; 0 = no ramp in progress */
    uint32_t ramp_done_urad_s;    /* progress of the fastest-changing wheel along the line */
    uint8_t tx_seq;
    uint16_t tx_head;
    uint16_t tx_len;
    uint8_t tx_buf[MB_TX_CAPACITY];
} mb_core_t;

/* The defaults of the robot config: 1320 ticks/rev, 20 rad/s, 40 rad/s^2, 200 ms, 100 Hz, 10 Hz. */
void mb_config_default(mb_config_t *cfg);

/* Power-on reset: no session, wheels at rest, counters zero, report grids start at now_us.
 * Returns MB_OK, or an mb_result_t naming the bad config field (the core is then unusable). */
int mb_core_init(mb_core_t *core, const mb_config_t *cfg, uint32_t now_us);

/* One received byte, with the time it was read. Replies are queued for transmission. */
void mb_core_rx_byte(mb_core_t *core, uint8_t byte, uint32_t now_us);
void mb_core_rx(mb_core_t *core, const uint8_t *data, size_t len, uint32_t now_us);

/* The control tick, every 1 ms: watchdog, host silence, the acceleration ramp, the reports that
 * fell due. ticks are the cumulative encoder counts FL, FR, RL, RR sampled at now_us. */
void mb_core_tick(mb_core_t *core, uint32_t now_us, const int32_t ticks[4]);

/* Inputs; each change is reported in STATUS at once. */
void mb_core_set_estop(mb_core_t *core, int active, uint32_t now_us);
void mb_core_set_motor_faults(mb_core_t *core, uint8_t faults, uint32_t now_us);  /* bit i: wheel i */
void mb_core_set_battery_mv(mb_core_t *core, uint16_t battery_mv);

/* Transmit side: whole frames, in order. take copies up to cap bytes out and removes them. */
size_t mb_core_tx_pending(const mb_core_t *core);
size_t mb_core_tx_take(mb_core_t *core, uint8_t *out, size_t cap);
int mb_core_tx_pop(mb_core_t *core);  /* next byte, or -1 if nothing is queued */

#ifdef __cplusplus
}
#endif

#endif /* MECANUM_BOARD_CORE_H */
