/* Gate serial protocol: CRC, parser, encoder (see gate_proto.h and docs/protocol.md). */
#include "gate_proto.h"

#include <string.h>

uint16_t gate_crc16(const uint8_t *data, size_t len)
{
    /* Bitwise, no table: 512 bytes of flash matter more than speed at 115200 baud. */
    uint16_t crc = 0xFFFF;
    size_t i;
    int bit;
    for (i = 0; i < len; i++) {
        crc ^= (uint16_t)((uint16_t)data[i] << 8);
        for (bit = 0; bit < 8; bit++) {
            crc = (crc & 0x8000) ? (uint16_t)((crc << 1) ^ 0x1021) : (uint16_t)(crc << 1);
        }
    }
    return crc;
}

static size_t next_sync(const uint8_t *buf, size_t n, size_t start)
{
    size_t i;
    for (i = start; i < n; i++) {
        if (buf[i] == GATE_SYNC) {
            return i;
        }
    }
    return n;
}

int gate_check_frame(const uint8_t *buf, size_t n, size_t *length)
{
    size_t payload_len, frame_len;
    uint16_t received;
    *length = 0;
    if (n == 0) {
        return GATE_NEED_MORE;
    }
    if (buf[0] != GATE_SYNC) {
        *length = next_sync(buf, n, 1);
        return GATE_DROP;
    }
    if (n < 2) {
        return GATE_NEED_MORE;
    }
    payload_len = buf[1];
    if (payload_len > GATE_MAX_PAYLOAD) {
        *length = next_sync(buf, n, 1);
        return GATE_DROP;
    }
    frame_len = GATE_MIN_FRAME + payload_len;
    if (n < frame_len) {
        return GATE_NEED_MORE;
    }
    received = (uint16_t)(((uint16_t)buf[GATE_HEADER_LEN + payload_len] << 8) | buf[GATE_HEADER_LEN + payload_len + 1]);
    if (gate_crc16(buf + 1, GATE_HEADER_LEN - 1 + payload_len) != received) {
        /* Only up to the next sync: LEN may be the corrupted byte and a good frame may start inside. */
        *length = next_sync(buf, n, 1);
        return GATE_DROP;
    }
    *length = frame_len;
    return GATE_FRAME;
}

size_t gate_encode_frame(uint8_t seq, uint8_t type, const uint8_t *payload, uint8_t payload_len,
                         uint8_t *out)
{
    uint16_t crc;
    if (payload_len > GATE_MAX_PAYLOAD) {
        return 0;
    }
    out[0] = GATE_SYNC;
    out[1] = payload_len;
    out[2] = seq;
    out[3] = type;
    if (payload_len) {
        memcpy(out + GATE_HEADER_LEN, payload, payload_len);
    }
    crc = gate_crc16(out + 1, (size_t)(GATE_HEADER_LEN - 1 + payload_len));
    out[GATE_HEADER_LEN + payload_len] = (uint8_t)(crc >> 8);
    out[GATE_HEADER_LEN + payload_len + 1] = (uint8_t)(crc & 0xFF);
    return (size_t)(GATE_MIN_FRAME + payload_len);
}

void gate_reader_init(gate_reader_t *r)
{
    r->n = 0;
    r->dropped_bytes = 0;
}

void gate_reader_push(gate_reader_t *r, uint8_t byte)
{
    /* The buffer never holds a whole frame's worth without a decision (check_frame answers
     * NEED_MORE only below GATE_MAX_FRAME bytes), so this cannot overflow; guard anyway. */
    if (r->n >= sizeof r->buf) {
        memmove(r->buf, r->buf + 1, r->n - 1);
        r->n--;
        r->dropped_bytes++;
    }
    r->buf[r->n++] = byte;
}

int gate_reader_next(gate_reader_t *r, uint8_t *frame, size_t *frame_len)
{
    size_t length;
    for (;;) {
        int kind = gate_check_frame(r->buf, r->n, &length);
        if (kind == GATE_NEED_MORE) {
            return 0;
        }
        if (kind == GATE_FRAME) {
            memcpy(frame, r->buf, length);
            *frame_len = length;
        } else {
            r->dropped_bytes += (uint32_t)length;
        }
        memmove(r->buf, r->buf + length, r->n - length);
        r->n -= length;
        if (kind == GATE_FRAME) {
            return 1;
        }
    }
}
