/* Mecanum motor board, protocol v1: the board's state machine. See board_core.h and PROTOCOL.md. */
#include "board_core.h"

#define Q30_ONE 0x40000000u

/* The queue indices are 16 bits and a frame must always fit an empty queue. */
typedef char mb_tx_capacity_is_valid[(MB_TX_CAPACITY >= MP_MAX_WIRE && MB_TX_CAPACITY <= 0xFFFFu) ? 1 : -1];

static uint32_t magnitude(int32_t v) { return v < 0 ? 0u - (uint32_t)v : (uint32_t)v; }

/* True once now has reached deadline on the wrapping clock (within half the clock period). */
static int due(uint32_t now_us, uint32_t deadline_us) { return (uint32_t)(now_us - deadline_us) < 0x80000000u; }

/* floor(num / den * 2^30) for num <= den, den > 0, by shift-and-subtract in 32 bits: it keeps
 * libgcc's 64-bit division (about 940 cycles each on an AVR) out of the image. */
static uint32_t ratio_q30(uint32_t num, uint32_t den)
{
    uint32_t q = 0, rem = num;
    int i;
    if (num >= den) {
        return Q30_ONE;
    }
    for (i = 0; i < 30; i++) {
        uint32_t carry = rem & 0x80000000u;
        rem <<= 1;
        q <<= 1;
        if (carry || rem >= den) {
            rem -= den;
            q |= 1u;
        }
    }
    return q;
}

/* round(ratio * u) for |ratio| <= 2^30 (Q30) and u < 2^31. */
static int32_t scale_q30(int32_t ratio_q30, uint32_t u)
{
    uint64_t p = (uint64_t)magnitude(ratio_q30) * u;
    uint32_t m = (uint32_t)((p + (Q30_ONE >> 1)) >> 30);
    return ratio_q30 < 0 ? -(int32_t)m : (int32_t)m;
}

/* Speed change the acceleration limit allows in h_us, in urad/s, saturating. */
static uint32_t accel_step(uint32_t accel_mrad_s2, uint32_t h_us)
{
    uint32_t ms, frac;
    if (h_us == 1000u) {
        return accel_mrad_s2;  /* the 1 ms tick: no divisions (they cost an AVR 0.08 ms) */
    }
    ms = h_us / 1000u;
    frac = accel_mrad_s2 * (h_us % 1000u) / 1000u;
    if (ms != 0u && accel_mrad_s2 > (0xFFFFFFFFu - frac) / ms) {
        return 0xFFFFFFFFu;
    }
    return accel_mrad_s2 * ms + frac;
}

/* Transmit side  ------------------------------------------------------------------------------- */

static void queue_bytes(mb_core_t *c, const uint8_t *data, size_t n)
{
    size_t i, at;
    if (n > (size_t)(MB_TX_CAPACITY - c->tx_len)) {
        c->tx_dropped++;  /* whole frame or nothing: the host sees the seq gap as one lost frame */
        return;
    }
    at = (size_t)c->tx_head + c->tx_len;
    if (at >= MB_TX_CAPACITY) {
        at -= MB_TX_CAPACITY;
    }
    for (i = 0; i < n; i++) {
        c->tx_buf[at] = data[i];
        if (++at == MB_TX_CAPACITY) {
            at = 0;
        }
    }
    c->tx_len = (uint16_t)(c->tx_len + n);
}

static void send(mb_core_t *c, uint8_t msg_id, const uint8_t *payload, size_t len)
{
    uint8_t wire[MP_MAX_WIRE];
    size_t n = mp_encode_frame(msg_id, c->tx_seq, payload, len, wire, sizeof wire);
    c->tx_seq = (uint8_t)(c->tx_seq + 1u);  /* every frame sent, or lost for want of room, uses a seq */
    queue_bytes(c, wire, n);
}

static void send_ack(mb_core_t *c, uint8_t ref_id, uint8_t ref_seq)
{
    uint8_t p[MP_LEN_ACK];
    mp_ack_t m;
    m.ref_id = ref_id;
    m.ref_seq = ref_seq;
    send(c, MP_ACK, p, mp_pack_ack(&m, p));
}

static void send_nack(mb_core_t *c, uint8_t ref_id, uint8_t ref_seq, uint8_t reason, uint8_t detail)
{
    uint8_t p[MP_LEN_NACK];
    mp_nack_t m;
    m.ref_id = ref_id;
    m.ref_seq = ref_seq;
    m.reason = reason;
    m.detail = detail;
    send(c, MP_NACK, p, mp_pack_nack(&m, p));
}

static void send_status(mb_core_t *c, uint32_t now_us)
{
    uint8_t p[MP_LEN_STATUS];
    mp_status_t m;
    m.t_us = now_us;
    m.battery_mv = c->battery_mv;
    m.motor_faults = c->motor_faults;
    m.flags = c->flags;
    m.rx_errors = c->rx_errors;
    send(c, MP_STATUS, p, mp_pack_status(&m, p));
}

static void send_hello_reply(mb_core_t *c, uint32_t nonce)
{
    uint8_t p[MP_LEN_HELLO_REPLY];
    mp_hello_reply_t m;
    m.minor = MP_PROTOCOL_MINOR;
    m.nonce = nonce;
    m.fw_major = c->cfg.fw_major;
    m.fw_minor = c->cfg.fw_minor;
    m.fw_patch = c->cfg.fw_patch;
    m.ticks_per_rev = c->cfg.ticks_per_rev;
    m.max_speed_mrad_s = c->cfg.max_speed_mrad_s;
    m.max_accel_mrad_s2 = c->cfg.max_accel_mrad_s2;
    m.watchdog_ms = c->cfg.watchdog_ms;
    m.report_period_us = c->cfg.report_period_us;
    m.capabilities = 0;
    send(c, MP_HELLO_REPLY, p, mp_pack_hello_reply(&m, p));
}

static void send_encoder_report(mb_core_t *c, uint32_t now_us, const int32_t ticks[4])
{
    uint8_t p[MP_LEN_ENCODER_REPORT];
    mp_encoder_report_t m;
    int i;
    m.t_us = now_us;
    for (i = 0; i < 4; i++) {
        m.ticks[i] = ticks[i];
    }
    send(c, MP_ENCODER_REPORT, p, mp_pack_encoder_report(&m, p));
}

/* Every flag change is reported at once (PROTOCOL.md section 5). */
static void set_flag(mb_core_t *c, uint8_t flag, int on, uint32_t now_us)
{
    uint8_t next = on ? (uint8_t)(c->flags | flag) : (uint8_t)(c->flags & (uint8_t)~flag);
    if (next != c->flags) {
        c->flags = next;
        send_status(c, now_us);
    }
}

/* Targets and the ramp  ------------------------------------------------------------------------ */

/* A new target starts a new straight line from where the setpoints are now; an unchanged one
 * (the host repeating its command) keeps the line it is on. */
static void set_target(mb_core_t *c, const int32_t target_urad_s[4])
{
    uint32_t mag[4], peak = 0;
    int i, same = 1;
    for (i = 0; i < 4; i++) {
        same = same && c->target_urad_s[i] == target_urad_s[i];
    }
    if (same) {
        return;
    }
    for (i = 0; i < 4; i++) {
        int32_t d = target_urad_s[i] - c->setpoint_urad_s[i];  /* |d| <= 2e9: the config bounds */
        c->target_urad_s[i] = target_urad_s[i];
        c->ramp_start_urad_s[i] = c->setpoint_urad_s[i];
        mag[i] = magnitude(d);
        peak = mag[i] > peak ? mag[i] : peak;
        c->ramp_ratio_q30[i] = d < 0 ? -1 : 1;  /* the sign, until the magnitude is known */
    }
    for (i = 0; i < 4 && peak != 0u; i++) {
        c->ramp_ratio_q30[i] *= (int32_t)ratio_q30(mag[i], peak);
    }
    c->ramp_peak_urad_s = peak;
    c->ramp_done_urad_s = 0;
}

static void zero_target(mb_core_t *c)
{
    int32_t zero[4] = {0, 0, 0, 0};  /* on the stack: a static const would take AVR RAM */
    set_target(c, zero);
}

static void hold_at_zero(mb_core_t *c)
{
    int i;
    for (i = 0; i < 4; i++) {
        c->target_urad_s[i] = 0;
        c->setpoint_urad_s[i] = 0;
    }
    c->ramp_peak_urad_s = 0;
}

/* Rule 3: all four setpoints move along one line, the fastest-changing wheel at max_accel. */
static void ramp(mb_core_t *c, uint32_t h_us)
{
    uint32_t step, done;
    int i;
    if (c->ramp_peak_urad_s == 0u) {
        return;
    }
    step = accel_step(c->cfg.max_accel_mrad_s2, h_us);
    done = c->ramp_done_urad_s;
    done = step > 0xFFFFFFFFu - done ? 0xFFFFFFFFu : done + step;
    if (done >= c->ramp_peak_urad_s) {
        for (i = 0; i < 4; i++) {
            c->setpoint_urad_s[i] = c->target_urad_s[i];
        }
        c->ramp_peak_urad_s = 0;
        return;
    }
    c->ramp_done_urad_s = done;
    for (i = 0; i < 4; i++) {
        c->setpoint_urad_s[i] = c->ramp_start_urad_s[i] + scale_q30(c->ramp_ratio_q30[i], done);
    }
}

/* Received frames  ----------------------------------------------------------------------------- */

static void on_speeds(mb_core_t *c, const mp_frame_t *f, uint32_t now_us)
{
    mp_set_wheel_speeds_t m;
    int32_t target[4];
    uint32_t mag[4], peak = 0, limit = c->cfg.max_speed_mrad_s;
    uint8_t over = 0;
    int i;
    if (c->estop) {
        send_nack(c, MP_SET_WHEEL_SPEEDS, f->seq, MP_NACK_ESTOP, 0);
        return;
    }
    if (c->motor_faults) {
        send_nack(c, MP_SET_WHEEL_SPEEDS, f->seq, MP_NACK_MOTOR_FAULT, c->motor_faults);
        return;
    }
    if (!c->session) {
        send_nack(c, MP_SET_WHEEL_SPEEDS, f->seq, MP_NACK_NO_SESSION, 0);
        return;
    }
    (void)mp_unpack_set_wheel_speeds(f->payload, f->len, &m);  /* the decoder checked the length */
    for (i = 0; i < 4; i++) {
        mag[i] = magnitude(m.speed_mrad_s[i]);
        peak = mag[i] > peak ? mag[i] : peak;
        if (mag[i] > limit) {
            over = (uint8_t)(over | (1u << i));
        }
    }
    for (i = 0; i < 4; i++) {
        if (over) {
            /* one factor for all four keeps the direction of travel; per wheel would bend the path */
            int32_t ratio = (int32_t)ratio_q30(mag[i], peak);
            target[i] = scale_q30(m.speed_mrad_s[i] < 0 ? -ratio : ratio, limit * 1000u);
        } else {
            target[i] = m.speed_mrad_s[i] * 1000;  /* |speed| <= limit: fits */
        }
    }
    if (over) {
        send_nack(c, MP_SET_WHEEL_SPEEDS, f->seq, MP_NACK_CLAMPED, over);
    } else {
        send_ack(c, MP_SET_WHEEL_SPEEDS, f->seq);
    }
    set_target(c, target);
    c->last_cmd_us = now_us;
    set_flag(c, MP_FLAG_CLAMPED, over != 0u, now_us);
    set_flag(c, MP_FLAG_WATCHDOG, 0, now_us);
}

static void on_frame(mb_core_t *c, const mp_frame_t *f, uint32_t now_us)
{
    c->last_rx_us = now_us;
    set_flag(c, MP_FLAG_HOST_SILENT, 0, now_us);
    if (!f->known) {
        send_nack(c, f->msg_id, f->seq, MP_NACK_UNKNOWN_MESSAGE, 0);
        return;
    }
    switch (f->msg_id) {
    case MP_HELLO: {
        mp_hello_t m;
        (void)mp_unpack_hello(f->payload, f->len, &m);
        c->session = 1;
        zero_target(c);  /* a new session starts from standstill */
        send_hello_reply(c, m.nonce);
        set_flag(c, MP_FLAG_NO_SESSION, 0, now_us);
        break;
    }
    case MP_SET_WHEEL_SPEEDS:
        on_speeds(c, f, now_us);
        break;
    case MP_STOP:
        zero_target(c);
        c->last_cmd_us = now_us;
        send_ack(c, MP_STOP, f->seq);
        break;
    case MP_HEARTBEAT:
        break;  /* host presence only: it must never keep the wheels turning */
    default:
        /* a board -> host id sent to the board */
        send_nack(c, f->msg_id, f->seq, MP_NACK_UNKNOWN_MESSAGE, 0);
        break;
    }
}

static uint32_t dropped_total(const mp_stats_t *s)
{
    return s->crc_errors + s->cobs_errors + s->too_short + s->bad_length + s->version_mismatch + s->oversize;
}

/* Public interface  ---------------------------------------------------------------------------- */

void mb_config_default(mb_config_t *cfg)
{
    if (cfg == NULL) {
        return;
    }
    cfg->ticks_per_rev = 1320u;
    cfg->max_speed_mrad_s = 20000u;
    cfg->max_accel_mrad_s2 = 40000u;
    cfg->watchdog_ms = 200u;
    cfg->report_period_us = 10000u;
    cfg->status_period_us = 100000u;
    cfg->fw_major = 1u;
    cfg->fw_minor = 0u;
    cfg->fw_patch = 0u;
}

int mb_core_init(mb_core_t *core, const mb_config_t *cfg, uint32_t now_us)
{
    int i;
    if (core == NULL || cfg == NULL) {
        return MB_ERR_NULL;
    }
    if (cfg->ticks_per_rev == 0u) {
        return MB_ERR_TICKS_PER_REV;
    }
    if (cfg->max_speed_mrad_s == 0u || cfg->max_speed_mrad_s > MB_MAX_SPEED_LIMIT_MRAD_S) {
        return MB_ERR_MAX_SPEED;
    }
    if (cfg->max_accel_mrad_s2 == 0u || cfg->max_accel_mrad_s2 > MB_MAX_ACCEL_LIMIT_MRAD_S2) {
        return MB_ERR_MAX_ACCEL;
    }
    if (cfg->watchdog_ms == 0u) {
        return MB_ERR_WATCHDOG;
    }
    if (cfg->report_period_us == 0u) {
        return MB_ERR_REPORT_PERIOD;
    }
    if (cfg->status_period_us == 0u || cfg->status_period_us >= 0x80000000u) {
        return MB_ERR_STATUS_PERIOD;
    }
    core->cfg = *cfg;
    mp_decoder_init(&core->decoder);
    for (i = 0; i < 4; i++) {
        core->setpoint_urad_s[i] = 0;
        core->target_urad_s[i] = 0;
        core->ramp_start_urad_s[i] = 0;
        core->ramp_ratio_q30[i] = 0;
    }
    core->ramp_peak_urad_s = 0;
    core->ramp_done_urad_s = 0;
    core->flags = MP_FLAG_NO_SESSION;
    core->session = 0;
    core->estop = 0;
    core->motor_faults = 0;
    core->battery_mv = 0;
    core->rx_errors = 0;
    core->tx_dropped = 0;
    core->dropped_seen = 0;
    core->last_cmd_us = now_us;
    core->last_rx_us = now_us;
    core->last_tick_us = now_us;
    /* reports on a fixed grid from reset: the n-th is due at now_us + n * period */
    core->next_report_us = now_us + cfg->report_period_us;
    core->next_status_us = now_us + cfg->status_period_us;
    core->tx_seq = 0;
    core->tx_head = 0;
    core->tx_len = 0;
    return MB_OK;
}

void mb_core_rx_byte(mb_core_t *core, uint8_t byte, uint32_t now_us)
{
    mp_frame_t frame;
    uint32_t mismatches = core->decoder.stats.version_mismatch, total, fresh;
    int got = mp_decoder_feed(&core->decoder, byte, &frame);
    total = dropped_total(&core->decoder.stats);
    fresh = total - core->dropped_seen;
    core->dropped_seen = total;
    core->rx_errors = fresh > (uint32_t)(0xFFFFu - core->rx_errors) ? 0xFFFFu : (uint16_t)(core->rx_errors + fresh);
    if (core->decoder.stats.version_mismatch != mismatches) {
        /* an intact frame of another major version: say which one we saw (its id and seq are not ours
         * to read, so the reference is 0, 0) */
        send_nack(core, 0, 0, MP_NACK_BAD_VERSION, core->decoder.stats.foreign_version);
    }
    if (got) {
        on_frame(core, &frame, now_us);
    }
}

void mb_core_rx(mb_core_t *core, const uint8_t *data, size_t len, uint32_t now_us)
{
    size_t i;
    for (i = 0; i < len; i++) {
        mb_core_rx_byte(core, data[i], now_us);
    }
}

void mb_core_tick(mb_core_t *core, uint32_t now_us, const int32_t ticks[4])
{
    uint32_t h_us = now_us - core->last_tick_us, watchdog_us = (uint32_t)core->cfg.watchdog_ms * 1000u;
    int moving = 0, i;
    core->last_tick_us = now_us;
    for (i = 0; i < 4; i++) {
        moving = moving || core->target_urad_s[i] != 0;
    }
    /* rule 1: only fresh speed commands (or STOP) keep the wheels turning, never heartbeats */
    if (moving && (uint32_t)(now_us - core->last_cmd_us) >= watchdog_us) {
        zero_target(core);
        set_flag(core, MP_FLAG_WATCHDOG, 1, now_us);
    }
    if ((uint32_t)(now_us - core->last_rx_us) >= watchdog_us && !(core->flags & MP_FLAG_HOST_SILENT)) {
        set_flag(core, MP_FLAG_HOST_SILENT, 1, now_us);
    }
    if (core->estop) {
        hold_at_zero(core);
    } else {
        ramp(core, h_us);
    }
    if (due(now_us, core->next_report_us)) {
        send_encoder_report(core, now_us, ticks);
        core->next_report_us += core->cfg.report_period_us;
        if (due(now_us, core->next_report_us)) {
            /* ticks came late (a stall): restart the grid rather than send a burst of stale reports */
            core->next_report_us = now_us + core->cfg.report_period_us;
        }
    }
    if (due(now_us, core->next_status_us)) {
        send_status(core, now_us);
        core->next_status_us += core->cfg.status_period_us;
        if (due(now_us, core->next_status_us)) {
            core->next_status_us = now_us + core->cfg.status_period_us;
        }
    }
}

void mb_core_set_estop(mb_core_t *core, int active, uint32_t now_us)
{
    core->estop = (uint8_t)(active != 0);
    if (core->estop) {
        hold_at_zero(core);  /* rule 5: motor power is cut in hardware; the setpoints follow at once */
    }
    set_flag(core, MP_FLAG_ESTOP, core->estop, now_us);
}

void mb_core_set_motor_faults(mb_core_t *core, uint8_t faults, uint32_t now_us)
{
    faults &= 0x0Fu;
    if (faults == core->motor_faults) {
        return;
    }
    core->motor_faults = faults;
    if (faults) {
        zero_target(core);  /* rule 6: a Mecanum robot with a dead wheel drives unpredictably */
    }
    send_status(core, now_us);
}

void mb_core_set_battery_mv(mb_core_t *core, uint16_t battery_mv) { core->battery_mv = battery_mv; }

size_t mb_core_tx_pending(const mb_core_t *core) { return core->tx_len; }

int mb_core_tx_pop(mb_core_t *core)
{
    uint8_t b;
    if (core->tx_len == 0u) {
        return -1;
    }
    b = core->tx_buf[core->tx_head];
    core->tx_head = (uint16_t)(core->tx_head + 1u == MB_TX_CAPACITY ? 0u : core->tx_head + 1u);
    core->tx_len--;
    return b;
}

size_t mb_core_tx_take(mb_core_t *core, uint8_t *out, size_t cap)
{
    size_t n = 0;
    while (n < cap && core->tx_len > 0u) {
        out[n++] = (uint8_t)mb_core_tx_pop(core);
    }
    return n;
}
