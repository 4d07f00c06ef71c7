/*
 * Mecanum motor board serial protocol, v1: the codec for the board's firmware.
 * Specification: firmware_protocol/PROTOCOL.md. Python twin: firmware_protocol/ (same test vectors).
 *
 * C99, no dynamic allocation, no global state, byte order independent of the MCU.
 *
 *   wire  = 0x00 | COBS(body) | 0x00
 *   body  = version u8 | msg_id u8 | seq u8 | payload (0..64) | crc32 u32 little-endian
 *   crc32 = CRC-32/ISO-HDLC over version, msg_id, seq and payload
 *
 * Receive: call mp_decoder_feed() with every byte from the UART; when it returns 1 a checked
 * frame is in *out. Transmit: mp_pack_<message>() into a payload buffer, then mp_encode_frame().
 */
#ifndef MECANUM_PROTO_H
#define MECANUM_PROTO_H

#include <stddef.h>
#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

#define MP_PROTOCOL_VERSION 1u
#define MP_PROTOCOL_MINOR 0u
#define MP_HEADER_LEN 3u
#define MP_CRC_LEN 4u
#define MP_MAX_PAYLOAD 64u
#define MP_MIN_BODY (MP_HEADER_LEN + MP_CRC_LEN)
#define MP_MAX_BODY (MP_HEADER_LEN + MP_MAX_PAYLOAD + MP_CRC_LEN)
#define MP_MAX_ENCODED (MP_MAX_BODY + 1u)    /* one COBS code byte: MP_MAX_BODY < 254 */
#define MP_MAX_WIRE (MP_MAX_ENCODED + 2u)    /* plus the two delimiters */

enum mp_msg_id {
    MP_HELLO = 0x01,
    MP_SET_WHEEL_SPEEDS = 0x02,
    MP_STOP = 0x03,
    MP_HEARTBEAT = 0x04,
    MP_HELLO_REPLY = 0x81,
    MP_ENCODER_REPORT = 0x82,
    MP_STATUS = 0x83,
    MP_ACK = 0x84,
    MP_NACK = 0x85
};

enum mp_nack_reason {
    MP_NACK_UNKNOWN_MESSAGE = 1,
    MP_NACK_CLAMPED = 2,
    MP_NACK_NO_SESSION = 3,
    MP_NACK_ESTOP = 4,
    MP_NACK_MOTOR_FAULT = 5,
    MP_NACK_BAD_VERSION = 6
};

enum mp_status_flag {
    MP_FLAG_WATCHDOG = 0x01,
    MP_FLAG_ESTOP = 0x02,
    MP_FLAG_CLAMPED = 0x04,
    MP_FLAG_HOST_SILENT = 0x08,
    MP_FLAG_NO_SESSION = 0x10
};

/* Payload sizes of the v1 messages; longer payloads (a newer minor version) are accepted. */
#define MP_LEN_HELLO 5u
#define MP_LEN_SET_WHEEL_SPEEDS 16u
#define MP_LEN_STOP 0u
#define MP_LEN_HEARTBEAT 0u
#define MP_LEN_HELLO_REPLY 26u
#define MP_LEN_ENCODER_REPORT 20u
#define MP_LEN_STATUS 10u
#define MP_LEN_ACK 2u
#define MP_LEN_NACK 4u

typedef struct { uint8_t minor; uint32_t nonce; } mp_hello_t;
typedef struct { int32_t speed_mrad_s[4]; } mp_set_wheel_speeds_t;   /* FL, FR, RL, RR */
typedef struct {
    uint8_t minor;
    uint32_t nonce;
    uint8_t fw_major, fw_minor, fw_patch;
    uint32_t ticks_per_rev;
    uint32_t max_speed_mrad_s;
    uint32_t max_accel_mrad_s2;
    uint16_t watchdog_ms;
    uint16_t report_period_us;
    uint16_t capabilities;
} mp_hello_reply_t;
typedef struct { uint32_t t_us; int32_t ticks[4]; } mp_encoder_report_t;
typedef struct {
    uint32_t t_us;
    uint16_t battery_mv;
    uint8_t motor_faults;
    uint8_t flags;
    uint16_t rx_errors;
} mp_status_t;
typedef struct { uint8_t ref_id, ref_seq; } mp_ack_t;
typedef struct { uint8_t ref_id, ref_seq, reason, detail; } mp_nack_t;

/* A checked frame. known = 0: an id this side does not know (answer MP_NACK_UNKNOWN_MESSAGE). */
typedef struct {
    uint8_t version;
    uint8_t msg_id;
    uint8_t seq;
    uint8_t known;
    uint8_t len;
    uint8_t payload[MP_MAX_PAYLOAD];
} mp_frame_t;

/* Same counters, same meaning as the Python DecoderStats. */
typedef struct {
    uint32_t frames;
    uint32_t unknown;
    uint32_t crc_errors;
    uint32_t cobs_errors;
    uint32_t too_short;
    uint32_t bad_length;
    uint32_t version_mismatch;
    uint32_t oversize;
    uint32_t bytes_dropped;
    uint8_t foreign_version;   /* valid when version_mismatch > 0 */
} mp_stats_t;

typedef struct {
    uint8_t buf[MP_MAX_ENCODED];
    uint8_t len;
    uint8_t skipping;   /* overflowed: drop bytes up to the next delimiter */
    mp_stats_t stats;
} mp_decoder_t;

uint32_t mp_crc32_update(uint32_t crc, const uint8_t *data, size_t len);  /* start from 0 */
uint32_t mp_crc32(const uint8_t *data, size_t len);

/* out must hold len + len / 254 + 1 bytes. Returns the encoded length (no delimiter). */
size_t mp_cobs_encode(const uint8_t *in, size_t len, uint8_t *out);
/* Returns the decoded length, or -1 if the encoding is malformed or exceeds out_cap. */
int mp_cobs_decode(const uint8_t *in, size_t len, uint8_t *out, size_t out_cap);

/* Expected payload length of a known id, or -1 for an unknown id. */
int mp_payload_len(uint8_t msg_id);

/* Wire bytes of one frame (both delimiters) into out; returns their count, 0 if it does not fit. */
size_t mp_encode_frame(uint8_t msg_id, uint8_t seq, const uint8_t *payload, size_t len, uint8_t *out,
                       size_t out_cap);

void mp_decoder_init(mp_decoder_t *d);   /* also resets the counters */
void mp_decoder_reset(mp_decoder_t *d);  /* drops a partial frame, keeps the counters */
int mp_decoder_feed(mp_decoder_t *d, uint8_t byte, mp_frame_t *out);

/* pack: writes the payload, returns its length. unpack: 0, or -1 if the payload is too short. */
size_t mp_pack_hello(const mp_hello_t *m, uint8_t *p);
size_t mp_pack_set_wheel_speeds(const mp_set_wheel_speeds_t *m, uint8_t *p);
size_t mp_pack_hello_reply(const mp_hello_reply_t *m, uint8_t *p);
size_t mp_pack_encoder_report(const mp_encoder_report_t *m, uint8_t *p);
size_t mp_pack_status(const mp_status_t *m, uint8_t *p);
size_t mp_pack_ack(const mp_ack_t *m, uint8_t *p);
size_t mp_pack_nack(const mp_nack_t *m, uint8_t *p);
int mp_unpack_hello(const uint8_t *p, size_t len, mp_hello_t *m);
int mp_unpack_set_wheel_speeds(const uint8_t *p, size_t len, mp_set_wheel_speeds_t *m);
int mp_unpack_hello_reply(const uint8_t *p, size_t len, mp_hello_reply_t *m);
int mp_unpack_encoder_report(const uint8_t *p, size_t len, mp_encoder_report_t *m);
int mp_unpack_status(const uint8_t *p, size_t len, mp_status_t *m);
int mp_unpack_ack(const uint8_t *p, size_t len, mp_ack_t *m);
int mp_unpack_nack(const uint8_t *p, size_t len, mp_nack_t *m);

#ifdef __cplusplus
}
#endif

#endif /* MECANUM_PROTO_H */
