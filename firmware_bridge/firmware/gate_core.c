/* The gate firmware's state machine; see gate_core.h and docs/protocol.md. */
#include "gate_core.h"

#include <string.h>

static void send_frame(gate_core_t *g, const uint8_t *frame, size_t len)
{
    g->hw.uart_write(g->hw.ctx, frame, len);
}

/* Encode, remember as the reply to the last request when it answers it, and send. */
static void reply(gate_core_t *g, uint8_t seq, uint8_t request_type, uint8_t type,
                  const uint8_t *payload, uint8_t payload_len)
{
    uint8_t frame[GATE_MAX_FRAME];
    size_t len = gate_encode_frame(seq, type, payload, payload_len, frame);
    if (g->have_last && g->last_seq == seq && g->last_type == request_type) {
        memcpy(g->reply, frame, len);
        g->reply_len = len;
        g->have_reply = 1;
    }
    send_frame(g, frame, len);
}

static void send_ack(gate_core_t *g, uint8_t seq, uint8_t acked_type)
{
    uint8_t p[6];
    p[0] = acked_type;
    p[1] = g->state;
    p[2] = g->bin;
    p[3] = g->fault;
    p[4] = (uint8_t)(g->boot_id >> 8);
    p[5] = (uint8_t)(g->boot_id & 0xFF);
    reply(g, seq, acked_type, GATE_ACK, p, sizeof p);
}

static void send_nak(gate_core_t *g, uint8_t seq, uint8_t acked_type, uint8_t reason)
{
    uint8_t p[7];
    p[0] = acked_type;
    p[1] = reason;
    p[2] = g->state;
    p[3] = g->bin;
    p[4] = g->fault;
    p[5] = (uint8_t)(g->boot_id >> 8);
    p[6] = (uint8_t)(g->boot_id & 0xFF);
    reply(g, seq, acked_type, GATE_NAK, p, sizeof p);
}

static void put_u32(uint8_t *p, uint32_t v)
{
    p[0] = (uint8_t)(v >> 24);
    p[1] = (uint8_t)(v >> 16);
    p[2] = (uint8_t)(v >> 8);
    p[3] = (uint8_t)v;
}

static void send_status(gate_core_t *g, uint8_t seq, uint32_t now_ms)
{
    uint8_t p[14];
    p[0] = g->state;
    p[1] = g->bin;
    p[2] = g->fault;
    p[3] = g->n_bins;
    p[4] = (uint8_t)(g->boot_id >> 8);
    p[5] = (uint8_t)(g->boot_id & 0xFF);
    put_u32(p + 6, now_ms - g->boot_ms);
    put_u32(p + 10, g->sorts_done);
    reply(g, seq, GATE_STATUS, GATE_STATUS_REPLY, p, sizeof p);
}

static void send_fault_report(gate_core_t *g)
{
    uint8_t p[5], frame[GATE_MAX_FRAME];
    size_t len;
    p[0] = g->fault;
    p[1] = g->state;
    p[2] = g->bin;
    p[3] = (uint8_t)(g->boot_id >> 8);
    p[4] = (uint8_t)(g->boot_id & 0xFF);
    g->event_seq++;
    len = gate_encode_frame(g->event_seq, GATE_FAULT, p, sizeof p, frame);
    send_frame(g, frame, len);
}

static void start_move(gate_core_t *g, uint8_t seq, uint8_t request_type, uint8_t target, uint32_t now_ms)
{
    g->moving = 1;
    g->move_seq = seq;
    g->move_type = request_type;
    g->move_target = target;
    g->move_started_ms = now_ms;
    g->state = GATE_STATE_BUSY;
    g->hw.servo_to_bin(g->hw.ctx, target);
}

void gate_core_boot(gate_core_t *g, const gate_hw_t *hw, uint8_t n_bins, uint16_t boot_id, uint32_t now_ms)
{
    memset(g, 0, sizeof *g);
    g->hw = *hw;
    gate_reader_init(&g->reader);
    g->n_bins = n_bins;
    g->boot_id = boot_id;
    g->boot_ms = now_ms;
    g->last_rx_ms = now_ms;
    g->heartbeat_timeout_ms = GATE_HEARTBEAT_TIMEOUT_MS;
    g->move_timeout_ms = GATE_MOVE_TIMEOUT_MS;
    g->state = GATE_STATE_FAILSAFE; /* never route on our own after a reset */
    g->fault = GATE_FAULT_BOOT;
    g->bin = GATE_REJECT_BIN;
    g->hw.servo_to_bin(g->hw.ctx, GATE_REJECT_BIN);
}

static void on_frame(gate_core_t *g, const uint8_t *frame, uint32_t now_ms)
{
    uint8_t len = frame[1], seq = frame[2], type = frame[3];
    const uint8_t *payload = frame + GATE_HEADER_LEN;
    uint8_t expected_len;

    g->last_rx_ms = now_ms; /* every valid frame feeds the watchdog */
    if ((type == GATE_SORT || type == GATE_CLEAR) && g->have_last && g->last_seq == seq &&
        g->last_type == type && g->last_len == len && memcmp(g->last_payload, payload, len) == 0) {
        /* A retransmission: answer from the cache, or stay quiet while the move runs. */
        if (g->have_reply) {
            send_frame(g, g->reply, g->reply_len);
        }
        return;
    }
    g->have_last = 1;
    g->last_seq = seq;
    g->last_type = type;
    g->last_len = len;
    memcpy(g->last_payload, payload, len);
    g->have_reply = 0;

    if (type != GATE_SORT && type != GATE_STATUS && type != GATE_HEARTBEAT && type != GATE_CLEAR) {
        send_nak(g, seq, type, GATE_NAK_UNKNOWN_TYPE);
        return;
    }
    expected_len = (type == GATE_SORT) ? 1 : 0;
    if (len != expected_len) {
        send_nak(g, seq, type, GATE_NAK_BAD_LENGTH);
        return;
    }
    switch (type) {
    case GATE_SORT:
        if (payload[0] >= g->n_bins) {
            send_nak(g, seq, type, GATE_NAK_BAD_BIN);
        } else if (g->state == GATE_STATE_FAULT || g->state == GATE_STATE_FAILSAFE) {
            send_nak(g, seq, type, GATE_NAK_LATCHED);
        } else if (g->state == GATE_STATE_BUSY) {
            send_nak(g, seq, type, GATE_NAK_BUSY);
        } else {
            start_move(g, seq, type, payload[0], now_ms); /* the ACK comes when the flap is there */
        }
        break;
    case GATE_STATUS:
        send_status(g, seq, now_ms);
        break;
    case GATE_HEARTBEAT:
        send_ack(g, seq, type);
        break;
    case GATE_CLEAR:
        if (g->state == GATE_STATE_BUSY) {
            send_nak(g, seq, type, GATE_NAK_BUSY);
        } else if (g->state == GATE_STATE_READY) {
            send_ack(g, seq, type);
        } else {
            start_move(g, seq, type, GATE_REJECT_BIN, now_ms); /* home to reject, then ACK */
        }
        break;
    default:
        break;
    }
}

void gate_core_on_byte(gate_core_t *g, uint8_t byte, uint32_t now_ms)
{
    uint8_t frame[GATE_MAX_FRAME];
    size_t len;
    gate_reader_push(&g->reader, byte);
    while (gate_reader_next(&g->reader, frame, &len)) {
        on_frame(g, frame, now_ms);
    }
}

void gate_core_tick(gate_core_t *g, uint32_t now_ms)
{
    uint32_t elapsed;
    /* Unsigned subtraction: correct across the 49-day wrap of millis(). */
    if ((g->state == GATE_STATE_READY || g->state == GATE_STATE_BUSY) &&
        (uint32_t)(now_ms - g->last_rx_ms) > g->heartbeat_timeout_ms) {
        uint8_t was_moving = g->moving;
        /* Forget the duplicate memory: a cached ACK says READY at a bin, and after the host's 8-bit
           SEQ wraps a new SORT could match it and be answered "done" while the flap is at reject. */
        g->have_last = 0;
        g->have_reply = 0;
        g->moving = 0;
        g->state = GATE_STATE_FAILSAFE;
        g->fault = GATE_FAULT_HEARTBEAT_LOST;
        g->bin = GATE_REJECT_BIN;
        g->hw.servo_to_bin(g->hw.ctx, GATE_REJECT_BIN);
        if (was_moving) {
            send_nak(g, g->move_seq, g->move_type, GATE_NAK_LATCHED);
        }
        send_fault_report(g);
    }
    if (!g->moving) {
        return;
    }
    elapsed = (uint32_t)(now_ms - g->move_started_ms);
    if (g->hw.flap_at_bin(g->hw.ctx, g->move_target)) {
        g->moving = 0;
        g->bin = g->move_target;
        g->state = GATE_STATE_READY;
        g->fault = GATE_FAULT_NONE;
        if (g->move_type == GATE_SORT) {
            g->sorts_done++;
        }
        send_ack(g, g->move_seq, g->move_type);
    } else if (elapsed >= g->move_timeout_ms) {
        /* The position sensor never confirmed: stop driving, latch, report. */
        g->moving = 0;
        g->state = GATE_STATE_FAULT;
        g->fault = GATE_FAULT_JAM;
        g->hw.servo_to_bin(g->hw.ctx, GATE_SERVO_RELEASE);
        send_nak(g, g->move_seq, g->move_type, g->move_type == GATE_SORT ? GATE_NAK_JAM : GATE_NAK_JAM_PRESENT);
        send_fault_report(g);
    }
}
