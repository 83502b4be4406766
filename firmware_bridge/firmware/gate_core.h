/* The gate firmware's state machine (docs/protocol.md), portable C99.
 *
 * Hardware is reached only through gate_hw_t callbacks and time is passed in, so the same code
 * runs in the Arduino sketch (firmware.ino) and in the host test harness (host_harness.c) on a
 * pseudo-terminal against the Python host driver. firmware_bridge/mcu_sim.py mirrors it.
 */
#ifndef GATE_CORE_H
#define GATE_CORE_H

#include <stddef.h>
#include <stdint.h>

#include "gate_proto.h"

#ifdef __cplusplus
extern "C" {
#endif

#define GATE_SERVO_RELEASE 0xFF /* servo_to_bin() argument: stop driving (jammed flap) */

typedef struct {
    void (*servo_to_bin)(void *ctx, uint8_t bin);            /* command the flap (or release) */
    int (*flap_at_bin)(void *ctx, uint8_t bin);              /* position sensor confirms bin */
    void (*uart_write)(void *ctx, const uint8_t *data, size_t len);
    void *ctx;
} gate_hw_t;

typedef struct {
    gate_hw_t hw;
    gate_reader_t reader;
    uint8_t n_bins;
    uint16_t boot_id;
    uint32_t boot_ms;
    uint32_t last_rx_ms;
    uint32_t heartbeat_timeout_ms;
    uint32_t move_timeout_ms;
    uint8_t state, fault, bin, event_seq;
    uint32_t sorts_done;
    /* the move in progress */
    uint8_t moving, move_seq, move_type, move_target;
    uint32_t move_started_ms;
    /* duplicate memory: the last request accepted and the reply it got */
    uint8_t have_last, last_seq, last_type, last_len;
    uint8_t last_payload[GATE_MAX_PAYLOAD];
    uint8_t have_reply;
    size_t reply_len;
    uint8_t reply[GATE_MAX_FRAME];
} gate_core_t;

/* Power-on: flap to reject, FAILSAFE/BOOT, empty duplicate memory. boot_id comes from EEPROM. */
void gate_core_boot(gate_core_t *g, const gate_hw_t *hw, uint8_t n_bins, uint16_t boot_id, uint32_t now_ms);
void gate_core_on_byte(gate_core_t *g, uint8_t byte, uint32_t now_ms);
/* Call often (every loop pass): completes moves, detects jams, runs the heartbeat watchdog. */
void gate_core_tick(gate_core_t *g, uint32_t now_ms);

#ifdef __cplusplus
}
#endif

#endif /* GATE_CORE_H */
