/* Runs the firmware's portable C on the build machine, for tests/test_protocol_c.py.
 *
 *   host_harness crc HEX                 print the CRC-16/CCITT-FALSE of the bytes, 4 hex digits
 *   host_harness encode SEQ TYPE [HEX]   print the encoded frame
 *   host_harness parse                   per stdin line of hex (one stream): the frames found,
 *                                        hex, space separated, then "| dropped N"
 *   host_harness script [--heartbeat-timeout-ms N] [--move-time-ms N]
 *       drive gate_core with explicit time, one stdin command per line, and print the frames
 *       it wrote for that command (hex, space separated): "boot T ID", "rx T HEX", "tick T",
 *       "jam 0|1", "reboot T". For the differential test against mcu_sim.GateFirmware.
 *   host_harness gate [--heartbeat-timeout-ms N] [--move-time-ms N] [--boot-id N]
 *       run gate_core on a new pseudo-terminal; print its slave path; stdin takes
 *       "jam 1", "jam 0", "reboot", "info", "quit". The flap reaches a commanded bin after
 *       move-time-ms unless jammed (the stand-in for the position sensor).
 * POSIX only. It sits in the sketch folder, which the Arduino IDE compiles whole, so it is
 * fenced off from the Arduino build by the ARDUINO macro.
 */
#if !defined(ARDUINO)
#define _XOPEN_SOURCE 600
#define _DEFAULT_SOURCE
#include <errno.h>
#include <fcntl.h>
#include <poll.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <termios.h>
#include <time.h>
#include <unistd.h>

#include "gate_core.h"
#include "gate_proto.h"

static size_t from_hex(const char *hex, uint8_t *out, size_t cap)
{
    size_t n = 0;
    unsigned int byte;
    while (hex[0] && hex[1] && n < cap && sscanf(hex, "%2x", &byte) == 1) {
        out[n++] = (uint8_t)byte;
        hex += 2;
    }
    return n;
}

static void print_hex(const uint8_t *data, size_t len)
{
    size_t i;
    for (i = 0; i < len; i++) {
        printf("%02x", data[i]);
    }
}

static int cmd_parse(void)
{
    static char line[1 << 16];
    static uint8_t stream[1 << 15];
    while (fgets(line, sizeof line, stdin)) {
        gate_reader_t r;
        uint8_t frame[GATE_MAX_FRAME];
        size_t i, n, len;
        int first = 1;
        line[strcspn(line, "\r\n")] = 0;
        n = from_hex(line, stream, sizeof stream);
        gate_reader_init(&r);
        for (i = 0; i < n; i++) {
            gate_reader_push(&r, stream[i]);
            while (gate_reader_next(&r, frame, &len)) {
                if (!first) {
                    putchar(' ');
                }
                print_hex(frame, len);
                first = 0;
            }
        }
        printf("%s| dropped %u\n", first ? "" : " ", (unsigned)r.dropped_bytes);
        fflush(stdout);
    }
    return 0;
}

/* --- the gate on a pty ----------------------------------------------------------------------- */

typedef struct {
    int master_fd;
    uint8_t commanded;
    uint32_t commanded_ms;
    uint32_t move_time_ms;
    int jammed;
    uint32_t now_ms;
} sim_hw_t;

static uint32_t monotonic_ms(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (uint32_t)((uint64_t)ts.tv_sec * 1000u + (uint64_t)ts.tv_nsec / 1000000u);
}

static void hw_servo(void *ctx, uint8_t bin)
{
    sim_hw_t *hw = (sim_hw_t *)ctx;
    hw->commanded = bin;
    hw->commanded_ms = hw->now_ms;
}

static int hw_at_bin(void *ctx, uint8_t bin)
{
    sim_hw_t *hw = (sim_hw_t *)ctx;
    return !hw->jammed && hw->commanded == bin && (uint32_t)(hw->now_ms - hw->commanded_ms) >= hw->move_time_ms;
}

static void hw_write(void *ctx, const uint8_t *data, size_t len)
{
    sim_hw_t *hw = (sim_hw_t *)ctx;
    ssize_t written;
    if (hw->master_fd < 0) { /* script mode: one hex word per frame on stdout */
        printf(" ");
        print_hex(data, len);
        return;
    }
    written = write(hw->master_fd, data, len);
    (void)written; /* nobody reading: a real UART would lose the bytes too */
}

static int cmd_script(int argc, char **argv)
{
    static char line[4096];
    static uint8_t bytes[2048];
    sim_hw_t hw;
    gate_hw_t callbacks;
    gate_core_t core;
    uint32_t heartbeat_timeout_ms = GATE_HEARTBEAT_TIMEOUT_MS;
    int i;
    memset(&hw, 0, sizeof hw);
    memset(&core, 0, sizeof core);
    hw.master_fd = -1;
    hw.move_time_ms = 60;
    for (i = 2; i + 1 < argc; i += 2) {
        if (strcmp(argv[i], "--heartbeat-timeout-ms") == 0) {
            heartbeat_timeout_ms = (uint32_t)atoi(argv[i + 1]);
        } else if (strcmp(argv[i], "--move-time-ms") == 0) {
            hw.move_time_ms = (uint32_t)atoi(argv[i + 1]);
        }
    }
    callbacks.servo_to_bin = hw_servo;
    callbacks.flap_at_bin = hw_at_bin;
    callbacks.uart_write = hw_write;
    callbacks.ctx = &hw;
    while (fgets(line, sizeof line, stdin)) {
        unsigned long t = 0, arg = 0;
        char hex[4096];
        if (sscanf(line, "boot %lu %lu", &t, &arg) == 2) { /* a fresh gate: flap free */
            hw.now_ms = (uint32_t)t;
            hw.jammed = 0;
            gate_core_boot(&core, &callbacks, GATE_DEFAULT_N_BINS, (uint16_t)arg, hw.now_ms);
            core.heartbeat_timeout_ms = heartbeat_timeout_ms;
        } else if (sscanf(line, "reboot %lu", &t) == 1) {
            hw.now_ms = (uint32_t)t;
            gate_core_boot(&core, &callbacks, GATE_DEFAULT_N_BINS, (uint16_t)(core.boot_id + 1), hw.now_ms);
            core.heartbeat_timeout_ms = heartbeat_timeout_ms;
        } else if (sscanf(line, "rx %lu %4095s", &t, hex) == 2) {
            size_t n = from_hex(hex, bytes, sizeof bytes), k;
            hw.now_ms = (uint32_t)t;
            for (k = 0; k < n; k++) {
                gate_core_on_byte(&core, bytes[k], hw.now_ms);
            }
        } else if (sscanf(line, "tick %lu", &t) == 1) {
            hw.now_ms = (uint32_t)t;
            gate_core_tick(&core, hw.now_ms);
        } else if (sscanf(line, "jam %lu", &arg) == 1) {
            hw.jammed = (int)arg;
        }
        printf("\n");
        fflush(stdout);
    }
    return 0;
}

static int cmd_gate(int argc, char **argv)
{
    sim_hw_t hw;
    gate_hw_t callbacks;
    gate_core_t core;
    uint32_t heartbeat_timeout_ms = GATE_HEARTBEAT_TIMEOUT_MS;
    uint16_t boot_id = 1;
    int master, slave, i, running = 1;
    char *slave_name;
    struct termios tio;
    char line[128];
    size_t line_len = 0;

    memset(&hw, 0, sizeof hw);
    hw.move_time_ms = 60;
    for (i = 2; i + 1 < argc; i += 2) {
        if (strcmp(argv[i], "--heartbeat-timeout-ms") == 0) {
            heartbeat_timeout_ms = (uint32_t)atoi(argv[i + 1]);
        } else if (strcmp(argv[i], "--move-time-ms") == 0) {
            hw.move_time_ms = (uint32_t)atoi(argv[i + 1]);
        } else if (strcmp(argv[i], "--boot-id") == 0) {
            boot_id = (uint16_t)atoi(argv[i + 1]);
        } else {
            fprintf(stderr, "unknown option %s\n", argv[i]);
            return 2;
        }
    }
    master = posix_openpt(O_RDWR | O_NOCTTY);
    if (master < 0 || grantpt(master) != 0 || unlockpt(master) != 0 || !(slave_name = ptsname(master))) {
        perror("pty");
        return 1;
    }
    slave = open(slave_name, O_RDWR | O_NOCTTY); /* held open so the master never sees EIO */
    if (slave < 0 || tcgetattr(slave, &tio) != 0) {
        perror("slave");
        return 1;
    }
    cfmakeraw(&tio);
    tcsetattr(slave, TCSANOW, &tio);
    fcntl(master, F_SETFL, fcntl(master, F_GETFL) | O_NONBLOCK);
    hw.master_fd = master;
    hw.now_ms = monotonic_ms();
    callbacks.servo_to_bin = hw_servo;
    callbacks.flap_at_bin = hw_at_bin;
    callbacks.uart_write = hw_write;
    callbacks.ctx = &hw;
    gate_core_boot(&core, &callbacks, GATE_DEFAULT_N_BINS, boot_id, hw.now_ms);
    core.heartbeat_timeout_ms = heartbeat_timeout_ms;
    printf("%s\n", slave_name);
    fflush(stdout);

    while (running) {
        struct pollfd fds[2];
        uint8_t buf[256];
        ssize_t n, k;
        fds[0].fd = master;
        fds[0].events = POLLIN;
        fds[1].fd = STDIN_FILENO;
        fds[1].events = POLLIN;
        poll(fds, 2, 1);
        hw.now_ms = monotonic_ms();
        if (fds[0].revents & POLLIN) {
            n = read(master, buf, sizeof buf);
            for (k = 0; k < n; k++) {
                gate_core_on_byte(&core, buf[k], hw.now_ms);
            }
        }
        if (fds[1].revents & (POLLIN | POLLHUP)) {
            char c;
            n = read(STDIN_FILENO, &c, 1);
            if (n <= 0) {
                break; /* the test went away */
            }
            if (c != '\n' && line_len + 1 < sizeof line) {
                line[line_len++] = c;
            } else if (c == '\n') {
                line[line_len] = 0;
                line_len = 0;
                if (strcmp(line, "jam 1") == 0) {
                    hw.jammed = 1;
                } else if (strcmp(line, "jam 0") == 0) {
                    hw.jammed = 0;
                } else if (strcmp(line, "reboot") == 0) {
                    boot_id++;
                    gate_core_boot(&core, &callbacks, GATE_DEFAULT_N_BINS, boot_id, hw.now_ms);
                    core.heartbeat_timeout_ms = heartbeat_timeout_ms;
                } else if (strcmp(line, "quit") == 0) {
                    running = 0;
                }
                printf("state %u fault %u bin %u sorts %u\n", core.state, core.fault, core.bin,
                       (unsigned)core.sorts_done);
                fflush(stdout);
            }
        }
        gate_core_tick(&core, hw.now_ms);
    }
    close(slave);
    close(master);
    return 0;
}

int main(int argc, char **argv)
{
    uint8_t data[4096], frame[GATE_MAX_FRAME];
    if (argc >= 3 && strcmp(argv[1], "crc") == 0) {
        size_t n = from_hex(argv[2], data, sizeof data);
        printf("%04x\n", gate_crc16(data, n));
        return 0;
    }
    if (argc >= 4 && strcmp(argv[1], "encode") == 0) {
        size_t n = argc >= 5 ? from_hex(argv[4], data, sizeof data) : 0;
        size_t len = gate_encode_frame((uint8_t)atoi(argv[2]), (uint8_t)atoi(argv[3]), data, (uint8_t)n, frame);
        if (n > GATE_MAX_PAYLOAD || len == 0) {
            fprintf(stderr, "payload too long\n");
            return 1;
        }
        print_hex(frame, len);
        printf("\n");
        return 0;
    }
    if (argc >= 2 && strcmp(argv[1], "parse") == 0) {
        return cmd_parse();
    }
    if (argc >= 2 && strcmp(argv[1], "script") == 0) {
        return cmd_script(argc, argv);
    }
    if (argc >= 2 && strcmp(argv[1], "gate") == 0) {
        return cmd_gate(argc, argv);
    }
    fprintf(stderr, "usage: host_harness crc HEX | encode SEQ TYPE [HEX] | parse | script [options] | gate [options]\n");
    return 2;
}

#else
typedef int host_harness_not_built_for_arduino; /* ISO C wants a non-empty file */
#endif /* !ARDUINO */
