/* Mecanum motor board serial protocol, v1: codec. See mecanum_proto.h and PROTOCOL.md. */
#include "mecanum_proto.h"

/* CRC-32/ISO-HDLC, reflected poly 0xEDB88320, a nibble at a time: 64 bytes of table, not 1 KB. */
static const uint32_t crc_nibble[16] = {
    0x00000000u, 0x1DB71064u, 0x3B6E20C8u, 0x26D930ACu, 0x76DC4190u, 0x6B6B51F4u, 0x4DB26158u, 0x5005713Cu,
    0xEDB88320u, 0xF00F9344u, 0xD6D6A3E8u, 0xCB61B38Cu, 0x9B64C2B0u, 0x86D3D2D4u, 0xA00AE278u, 0xBDBDF21Cu};

uint32_t mp_crc32_update(uint32_t crc, const uint8_t *data, size_t len)
{
    size_t i;
    crc = ~crc;
    for (i = 0; i < len; i++) {
        crc ^= data[i];
        crc = (crc >> 4) ^ crc_nibble[crc & 0x0Fu];
        crc = (crc >> 4) ^ crc_nibble[crc & 0x0Fu];
    }
    return ~crc;
}

uint32_t mp_crc32(const uint8_t *data, size_t len) { return mp_crc32_update(0u, data, len); }

size_t mp_cobs_encode(const uint8_t *in, size_t len, uint8_t *out)
{
    size_t read = 0, write = 1, code_at = 0;
    uint8_t code = 1;
    while (read < len) {
        if (in[read] == 0) {
            out[code_at] = code;
            code_at = write++;
            code = 1;
        } else {
            out[write++] = in[read];
            code++;
            /* a full block ends without an implied zero; start a new one only if data follows */
            if (code == 0xFF && read + 1 < len) {
                out[code_at] = code;
                code_at = write++;
                code = 1;
            }
        }
        read++;
    }
    out[code_at] = code;
    return write;
}

int mp_cobs_decode(const uint8_t *in, size_t len, uint8_t *out, size_t out_cap)
{
    size_t i = 0, n = 0, k;
    while (i < len) {
        uint8_t code = in[i];
        if (code == 0 || i + code > len) {
            return -1;
        }
        for (k = 1; k < code; k++) {
            if (n >= out_cap) {
                return -1;
            }
            out[n++] = in[i + k];
        }
        i += code;
        if (code != 0xFF && i < len) {
            if (n >= out_cap) {
                return -1;
            }
            out[n++] = 0;
        }
    }
    return (int)n;
}

int mp_payload_len(uint8_t msg_id)
{
    switch (msg_id) {
    case MP_HELLO: return MP_LEN_HELLO;
    case MP_SET_WHEEL_SPEEDS: return MP_LEN_SET_WHEEL_SPEEDS;
    case MP_STOP: return MP_LEN_STOP;
    case MP_HEARTBEAT: return MP_LEN_HEARTBEAT;
    case MP_HELLO_REPLY: return MP_LEN_HELLO_REPLY;
    case MP_ENCODER_REPORT: return MP_LEN_ENCODER_REPORT;
    case MP_STATUS: return MP_LEN_STATUS;
    case MP_ACK: return MP_LEN_ACK;
    case MP_NACK: return MP_LEN_NACK;
    default: return -1;
    }
}

size_t mp_encode_frame(uint8_t msg_id, uint8_t seq, const uint8_t *payload, size_t len, uint8_t *out,
                       size_t out_cap)
{
    uint8_t body[MP_MAX_BODY];
    size_t i, n;
    uint32_t crc;
    if (len > MP_MAX_PAYLOAD || out_cap < len + MP_MIN_BODY + 3u) {
        return 0;
    }
    body[0] = MP_PROTOCOL_VERSION;
    body[1] = msg_id;
    body[2] = seq;
    for (i = 0; i < len; i++) {
        body[MP_HEADER_LEN + i] = payload[i];
    }
    n = MP_HEADER_LEN + len;
    crc = mp_crc32(body, n);
    body[n++] = (uint8_t)crc;
    body[n++] = (uint8_t)(crc >> 8);
    body[n++] = (uint8_t)(crc >> 16);
    body[n++] = (uint8_t)(crc >> 24);
    out[0] = 0;
    n = mp_cobs_encode(body, n, out + 1) + 1;
    out[n++] = 0;
    return n;
}

void mp_decoder_reset(mp_decoder_t *d)
{
    d->len = 0;
    d->skipping = 0;
}

void mp_decoder_init(mp_decoder_t *d)
{
    mp_stats_t zero = {0};
    mp_decoder_reset(d);
    d->stats = zero;
}

static uint32_t rd32(const uint8_t *p)
{
    return (uint32_t)p[0] | ((uint32_t)p[1] << 8) | ((uint32_t)p[2] << 16) | ((uint32_t)p[3] << 24);
}

static uint16_t rd16(const uint8_t *p) { return (uint16_t)(p[0] | (p[1] << 8)); }

static void wr32(uint8_t *p, uint32_t v)
{
    p[0] = (uint8_t)v;
    p[1] = (uint8_t)(v >> 8);
    p[2] = (uint8_t)(v >> 16);
    p[3] = (uint8_t)(v >> 24);
}

static void wr16(uint8_t *p, uint16_t v)
{
    p[0] = (uint8_t)v;
    p[1] = (uint8_t)(v >> 8);
}

/* Check the frame in d->buf; 1 if it went to *out. */
static int decode_frame(mp_decoder_t *d, mp_frame_t *out)
{
    uint8_t body[MP_MAX_BODY];
    int n = mp_cobs_decode(d->buf, d->len, body, sizeof body);
    int expected;
    size_t i, plen;
    if (n < 0) {
        d->stats.cobs_errors++;
        d->stats.bytes_dropped += d->len;
        return 0;
    }
    if ((size_t)n < MP_MIN_BODY) {
        d->stats.too_short++;
        d->stats.bytes_dropped += d->len;
        return 0;
    }
    if (mp_crc32(body, (size_t)n - MP_CRC_LEN) != rd32(body + n - MP_CRC_LEN)) {
        d->stats.crc_errors++;
        d->stats.bytes_dropped += d->len;
        return 0;
    }
    if (body[0] != MP_PROTOCOL_VERSION) {
        d->stats.version_mismatch++;
        d->stats.foreign_version = body[0];
        d->stats.bytes_dropped += d->len;
        return 0;
    }
    plen = (size_t)n - MP_MIN_BODY;
    expected = mp_payload_len(body[1]);
    if (expected >= 0 && plen < (size_t)expected) {
        d->stats.bad_length++;
        d->stats.bytes_dropped += d->len;
        return 0;
    }
    out->version = body[0];
    out->msg_id = body[1];
    out->seq = body[2];
    out->known = (uint8_t)(expected >= 0);
    out->len = (uint8_t)plen;
    for (i = 0; i < plen; i++) {
        out->payload[i] = body[MP_HEADER_LEN + i];
    }
    d->stats.frames++;
    if (expected < 0) {
        d->stats.unknown++;
    }
    return 1;
}

int mp_decoder_feed(mp_decoder_t *d, uint8_t byte, mp_frame_t *out)
{
    int got = 0;
    if (byte == 0) {
        if (!d->skipping && d->len > 0) {
            got = decode_frame(d, out);
        }
        d->len = 0;
        d->skipping = 0;
        return got;
    }
    if (d->skipping) {
        d->stats.bytes_dropped++;
    } else if (d->len >= MP_MAX_ENCODED) {
        /* no delimiter where one must be: drop this frame rather than grow */
        d->stats.oversize++;
        d->stats.bytes_dropped += (uint32_t)d->len + 1u;
        d->len = 0;
        d->skipping = 1;
    } else {
        d->buf[d->len++] = byte;
    }
    return 0;
}

size_t mp_pack_hello(const mp_hello_t *m, uint8_t *p)
{
    p[0] = m->minor;
    wr32(p + 1, m->nonce);
    return MP_LEN_HELLO;
}

size_t mp_pack_set_wheel_speeds(const mp_set_wheel_speeds_t *m, uint8_t *p)
{
    int i;
    for (i = 0; i < 4; i++) {
        wr32(p + 4 * i, (uint32_t)m->speed_mrad_s[i]);
    }
    return MP_LEN_SET_WHEEL_SPEEDS;
}

size_t mp_pack_hello_reply(const mp_hello_reply_t *m, uint8_t *p)
{
    p[0] = m->minor;
    wr32(p + 1, m->nonce);
    p[5] = m->fw_major;
    p[6] = m->fw_minor;
    p[7] = m->fw_patch;
    wr32(p + 8, m->ticks_per_rev);
    wr32(p + 12, m->max_speed_mrad_s);
    wr32(p + 16, m->max_accel_mrad_s2);
    wr16(p + 20, m->watchdog_ms);
    wr16(p + 22, m->report_period_us);
    wr16(p + 24, m->capabilities);
    return MP_LEN_HELLO_REPLY;
}

size_t mp_pack_encoder_report(const mp_encoder_report_t *m, uint8_t *p)
{
    int i;
    wr32(p, m->t_us);
    for (i = 0; i < 4; i++) {
        wr32(p + 4 + 4 * i, (uint32_t)m->ticks[i]);
    }
    return MP_LEN_ENCODER_REPORT;
}

size_t mp_pack_status(const mp_status_t *m, uint8_t *p)
{
    wr32(p, m->t_us);
    wr16(p + 4, m->battery_mv);
    p[6] = m->motor_faults;
    p[7] = m->flags;
    wr16(p + 8, m->rx_errors);
    return MP_LEN_STATUS;
}

size_t mp_pack_ack(const mp_ack_t *m, uint8_t *p)
{
    p[0] = m->ref_id;
    p[1] = m->ref_seq;
    return MP_LEN_ACK;
}

size_t mp_pack_nack(const mp_nack_t *m, uint8_t *p)
{
    p[0] = m->ref_id;
    p[1] = m->ref_seq;
    p[2] = m->reason;
    p[3] = m->detail;
    return MP_LEN_NACK;
}

int mp_unpack_hello(const uint8_t *p, size_t len, mp_hello_t *m)
{
    if (len < MP_LEN_HELLO) {
        return -1;
    }
    m->minor = p[0];
    m->nonce = rd32(p + 1);
    return 0;
}

int mp_unpack_set_wheel_speeds(const uint8_t *p, size_t len, mp_set_wheel_speeds_t *m)
{
    int i;
    if (len < MP_LEN_SET_WHEEL_SPEEDS) {
        return -1;
    }
    for (i = 0; i < 4; i++) {
        m->speed_mrad_s[i] = (int32_t)rd32(p + 4 * i);
    }
    return 0;
}

int mp_unpack_hello_reply(const uint8_t *p, size_t len, mp_hello_reply_t *m)
{
    if (len < MP_LEN_HELLO_REPLY) {
        return -1;
    }
    m->minor = p[0];
    m->nonce = rd32(p + 1);
    m->fw_major = p[5];
    m->fw_minor = p[6];
    m->fw_patch = p[7];
    m->ticks_per_rev = rd32(p + 8);
    m->max_speed_mrad_s = rd32(p + 12);
    m->max_accel_mrad_s2 = rd32(p + 16);
    m->watchdog_ms = rd16(p + 20);
    m->report_period_us = rd16(p + 22);
    m->capabilities = rd16(p + 24);
    return 0;
}

int mp_unpack_encoder_report(const uint8_t *p, size_t len, mp_encoder_report_t *m)
{
    int i;
    if (len < MP_LEN_ENCODER_REPORT) {
        return -1;
    }
    m->t_us = rd32(p);
    for (i = 0; i < 4; i++) {
        m->ticks[i] = (int32_t)rd32(p + 4 + 4 * i);
    }
    return 0;
}

int mp_unpack_status(const uint8_t *p, size_t len, mp_status_t *m)
{
    if (len < MP_LEN_STATUS) {
        return -1;
    }
    m->t_us = rd32(p);
    m->battery_mv = rd16(p + 4);
    m->motor_faults = p[6];
    m->flags = p[7];
    m->rx_errors = rd16(p + 8);
    return 0;
}

int mp_unpack_ack(const uint8_t *p, size_t len, mp_ack_t *m)
{
    if (len < MP_LEN_ACK) {
        return -1;
    }
    m->ref_id = p[0];
    m->ref_seq = p[1];
    return 0;
}

int mp_unpack_nack(const uint8_t *p, size_t len, mp_nack_t *m)
{
    if (len < MP_LEN_NACK) {
        return -1;
    }
    m->ref_id = p[0];
    m->ref_seq = p[1];
    m->reason = p[2];
    m->detail = p[3];
    return 0;
}
