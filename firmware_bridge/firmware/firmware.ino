// Sorting-gate firmware (protocol: docs/protocol.md). Arduino C++ around a portable C core.
//
// Board: any Arduino with a UART and a servo; written for an ATmega328P (Nano/Uno) and also
// builds for an RP2040 with the arduino-pico core. The sketch file is named after its folder,
// as the Arduino IDE and arduino-cli require: `arduino-cli compile -b arduino:avr:nano firmware`.
//
// Hardware:
//   - flap servo on SERVO_PIN, one angle per bin (bin 0 = reject = fail-safe position);
//   - position feedback: the servo's potentiometer wiper on FEEDBACK_PIN (a "feedback servo"),
//     one calibrated ADC reading per bin; the flap "is at" a bin within FEEDBACK_TOLERANCE_ADC;
//   - USB serial at 115200 8N1 to the cell's host.
// Everything protocol- and state-related is in gate_core.c / gate_proto.c, which the tests
// compile with gcc and run against the Python host driver on a pseudo-terminal.

#include <EEPROM.h>
#include <Servo.h>
#if defined(__AVR__)
#include <avr/wdt.h>
#endif

#include "gate_core.h"

static const uint8_t SERVO_PIN = 9;
static const uint8_t FEEDBACK_PIN = A0;
static const uint8_t N_BINS = GATE_DEFAULT_N_BINS;
// Calibrate per gate at commissioning (vs2t-edge sort BIN, then read the ADC).
static const uint8_t BIN_ANGLE_DEG[N_BINS] = {10, 30, 50, 70, 90, 110, 130, 150};
static const int BIN_FEEDBACK_ADC[N_BINS] = {80, 190, 300, 410, 520, 630, 740, 850};
static const int FEEDBACK_TOLERANCE_ADC = 20;
static const int BOOT_ID_EEPROM_ADDR = 0;

static Servo flap;
static gate_core_t core;

static void servo_to_bin(void *ctx, uint8_t bin)
{
    (void)ctx;
    if (bin == GATE_SERVO_RELEASE || bin >= N_BINS) {
        flap.detach();  // jammed: stop pushing against the obstruction
        return;
    }
    if (!flap.attached()) {
        flap.attach(SERVO_PIN);
    }
    flap.write(BIN_ANGLE_DEG[bin]);
}

static int flap_at_bin(void *ctx, uint8_t bin)
{
    (void)ctx;
    if (bin >= N_BINS) {
        return 0;
    }
    int reading = analogRead(FEEDBACK_PIN);
    return abs(reading - BIN_FEEDBACK_ADC[bin]) <= FEEDBACK_TOLERANCE_ADC;
}

static void uart_write(void *ctx, const uint8_t *data, size_t len)
{
    (void)ctx;
    Serial.write(data, len);  // frames are <= 22 bytes, below the 64-byte TX buffer
}

static uint16_t next_boot_id()
{
    // One EEPROM write per boot: ~100k cycles is decades of power cycles.
    uint16_t boot_id = 0;
    EEPROM.get(BOOT_ID_EEPROM_ADDR, boot_id);
    boot_id++;
    EEPROM.put(BOOT_ID_EEPROM_ADDR, boot_id);
    return boot_id;
}

void setup()
{
#if defined(__AVR__)
    wdt_disable();  // a watchdog reset leaves it armed; disarm before the slow setup
#endif
    Serial.begin(GATE_BAUDRATE);
    gate_hw_t hw;
    hw.servo_to_bin = servo_to_bin;
    hw.flap_at_bin = flap_at_bin;
    hw.uart_write = uart_write;
    hw.ctx = NULL;
    // Boots latched in FAILSAFE/BOOT with the flap at reject: a reset never routes by itself.
    gate_core_boot(&core, &hw, N_BINS, next_boot_id(), millis());
#if defined(__AVR__)
    // A hung loop resets the MCU within 250 ms, and the reset lands in the same safe state.
    wdt_enable(WDTO_250MS);
#endif
}

void loop()
{
#if defined(__AVR__)
    wdt_reset();
#endif
    uint32_t now_ms = millis();
    while (Serial.available() > 0) {
        gate_core_on_byte(&core, (uint8_t)Serial.read(), now_ms);
    }
    gate_core_tick(&core, now_ms);
}
