/* Gate serial protocol, version 1 (docs/protocol.md): constants, CRC, parser, encoder.
 *
 * Portable C99, no I/O and no allocation: compiled into the Arduino sketch (firmware.ino) and,
 * on the build machine, into the test harness (host_harness.c) that checks it against the
 * Python implementation (firmware_bridge/protocol.py). Keep the two in step; a test compares
 * every constant below with protocol.py.
 */
#ifndef GATE_PROTO_H
#define GATE_PROTO_H

#include <stddef.h>
#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

#define GATE_SYNC 0xA5
#define GATE_MAX_PAYLOAD 16
#define GATE_HEADER_LEN 4 /* SYNC, LEN, SEQ, TYPE */
#define GATE_CRC_LEN 2
#define GATE_MIN_FRAME (GATE_HEADER_LEN + GATE_CRC_LEN)
#define GATE_MAX_FRAME (GATE_MIN_FRAME + GATE_MAX_PAYLOAD)

/* Message types: host -> MCU */
#define GATE_SORT 0x01
#define GATE_STATUS 0x02
#define GATE_HEARTBEAT 0x03
#define GATE_CLEAR 0x04
/* MCU -> host */
#define GATE_ACK 0x80
#define GATE_NAK 0x81
#define GATE_STATUS_REPLY 0x82
#define GATE_FAULT 0x83

/* States */
#define GATE_STATE_READY 0
#define GATE_STATE_BUSY 1
#define GATE_STATE_FAULT 2
#define GATE_STATE_FAILSAFE 3

/* Fault codes */
#define GATE_FAULT_NONE 0
#define GATE_FAULT_HEARTBEAT_LOST 1
#define GATE_FAULT_JAM 2
#define GATE_FAULT_BOOT 3

/* NAK reasons */
#define GATE_NAK_BAD_BIN 1
#define GATE_NAK_BAD_LENGTH 2
#define GATE_NAK_UNKNOWN_TYPE 3
#define GATE_NAK_LATCHED 4
#define GATE_NAK_JAM 5
#define GATE_NAK_JAM_PRESENT 6
#define GATE_NAK_BUSY 7

/* Timing and geometry */
#define GATE_HEARTBEAT_TIMEOUT_MS 1000
#define GATE_MOVE_TIMEOUT_MS 300
#define GATE_DEFAULT_N_BINS 8
#define GATE_REJECT_BIN 0
#define GATE_BAUDRATE 115200

/* check_frame answers */
#define GATE_NEED_MORE 0
#define GATE_DROP 1
#define GATE_FRAME 2

/* CRC-16/CCITT-FALSE: poly 0x1021, init 0xFFFF, no reflection, xorout 0; check 0x29B1. */
uint16_t gate_crc16(const uint8_t *data, size_t len);

/* What the front of buf holds: GATE_NEED_MORE (*length 0), GATE_DROP (*length bytes to
 * discard) or GATE_FRAME (*length bytes form a frame). Total over any input. */
int gate_check_frame(const uint8_t *buf, size_t n, size_t *length);

/* Writes the frame into out (at least GATE_MAX_FRAME bytes); returns its length, 0 if the
 * payload is too long. */
size_t gate_encode_frame(uint8_t seq, uint8_t type, const uint8_t *payload, uint8_t payload_len,
                         uint8_t *out);

/* Byte-at-a-time receiver for a UART loop. After gate_reader_push(), call gate_reader_next()
 * until it returns 0: one byte can complete more than one frame after a resync. */
typedef struct {
    uint8_t buf[GATE_MAX_FRAME];
    size_t n;
    uint32_t dropped_bytes;
} gate_reader_t;

void gate_reader_init(gate_reader_t *r);
void gate_reader_push(gate_reader_t *r, uint8_t byte);
/* Returns 1 and copies a frame into frame (GATE_MAX_FRAME bytes) with its length, else 0. */
int gate_reader_next(gate_reader_t *r, uint8_t *frame, size_t *frame_len);

#ifdef __cplusplus
}
#endif

#endif /* GATE_PROTO_H */
