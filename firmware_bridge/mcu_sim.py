"""A simulated gate MCU that behaves as the firmware does (firmware/gate_core.c), on a real pty.

Two layers:

* ``GateFirmware`` — the firmware's state machine, pure, with time passed in (``now_ms``):
  bins, moves that take time, acks, the duplicate memory, the heartbeat watchdog fail-safe,
  jams, CLEAR and the boot latch. It mirrors gate_core.c function for function.
* ``MCUSimulator`` — runs a ``GateFirmware`` in a thread on the master end of a pseudo-terminal
  pair, so the host driver talks to it through a real tty (``/dev/pts/N``) exactly as to the
  USB-serial adapter. Line faults are injectable: slow acks, dropped and duplicated frames in
  either direction, serial noise, a jammed flap, a reboot.

``start_simulated_gate() -> (device_path, simulator)`` is the one entry point for tests, the
daemon's simulated mode and the demo. ``python -m vs2t_edge.firmware_bridge.mcu_sim`` runs one
in the foreground and prints its device path, for commissioning practice from another shell.
"""

from __future__ import annotations

import errno
import os
import random
import select
import socket
import threading
import time
import tty
from dataclasses import dataclass, field

from vs2t_edge.firmware_bridge import protocol as p


@dataclass
class _Move:
    seq: int
    request_type: int  # SORT or CLEAR
    target_bin: int
    started_ms: int


class GateFirmware:
    """The gate firmware's logic (docs/protocol.md); ``jam_present`` stands for the flap sensor."""

    def __init__(self, *, n_bins: int = p.DEFAULT_N_BINS, boot_id: int = 1, now_ms: int = 0,
                 heartbeat_timeout_ms: int = p.HEARTBEAT_TIMEOUT_MS, move_time_ms: int = 60,
                 move_timeout_ms: int = p.MOVE_TIMEOUT_MS) -> None:
        if not 2 <= n_bins <= 255:
            raise ValueError(f"n_bins must be 2..255, got {n_bins}")
        self.n_bins = n_bins
        self.heartbeat_timeout_ms = heartbeat_timeout_ms
        self.move_time_ms = move_time_ms
        self.move_timeout_ms = move_timeout_ms
        self.jam_present = False  # the flap is mechanically blocked: moves never confirm
        self.boot_id = boot_id - 1
        self.executed: list[int] = []  # bins actually moved to by SORT, in order (for tests)
        self.reboot(now_ms)

    # --- lifecycle ---------------------------------------------------------------------------
    def reboot(self, now_ms: int) -> None:
        """Power-on: new boot id, flap to reject, FAILSAFE/BOOT, duplicate memory empty."""
        self.boot_id = (self.boot_id + 1) & 0xFFFF
        self.boot_ms = now_ms
        self.state = p.STATE_FAILSAFE
        self.fault = p.FAULT_BOOT
        self.bin = p.REJECT_BIN
        self.sorts_done = 0
        self.last_rx_ms = now_ms
        self.move: _Move | None = None
        self.last_request: tuple[int, int, bytes] | None = None
        self.last_reply: bytes | None = None
        self.event_seq = 0

    # --- frames in ---------------------------------------------------------------------------
    def on_frame(self, frame: p.Frame, now_ms: int) -> list[bytes]:
        """One CRC-valid frame from the host; returns the frames to send."""
        self.last_rx_ms = now_ms  # every valid frame feeds the watchdog
        key = (frame.seq, frame.type, frame.payload)
        if key == self.last_request and frame.type in (p.SORT, p.CLEAR):
            # A retransmission: answer from the cache, or stay quiet while the move runs.
            return [] if self.last_reply is None else [self.last_reply]
        self.last_request = key
        self.last_reply = None
        handler = {p.SORT: self._on_sort, p.STATUS: self._on_status,
                   p.HEARTBEAT: self._on_heartbeat, p.CLEAR: self._on_clear}.get(frame.type)
        if handler is None:
            return [self._nak(frame.seq, frame.type, p.NAK_UNKNOWN_TYPE)]
        expected_len = 1 if frame.type == p.SORT else 0
        if len(frame.payload) != expected_len:
            return [self._nak(frame.seq, frame.type, p.NAK_BAD_LENGTH)]
        return handler(frame, now_ms)

    def _on_sort(self, frame: p.Frame, now_ms: int) -> list[bytes]:
        target = frame.payload[0]
        if target >= self.n_bins:
            return [self._nak(frame.seq, p.SORT, p.NAK_BAD_BIN)]
        if self.state in (p.STATE_FAULT, p.STATE_FAILSAFE):
            return [self._nak(frame.seq, p.SORT, p.NAK_LATCHED)]
        if self.state == p.STATE_BUSY:
            return [self._nak(frame.seq, p.SORT, p.NAK_BUSY)]
        self._start_move(frame.seq, p.SORT, target, now_ms)
        return []  # the ACK comes when the flap reaches the bin (tick)

    def _on_status(self, frame: p.Frame, now_ms: int) -> list[bytes]:
        reply = p.StatusReply(self.state, self.bin, self.fault, self.n_bins, self.boot_id,
                              (now_ms - self.boot_ms) & 0xFFFFFFFF, self.sorts_done)
        return [self._remember(p.encode_frame(frame.seq, p.STATUS_REPLY, reply.pack()), frame.seq, p.STATUS)]

    def _on_heartbeat(self, frame: p.Frame, now_ms: int) -> list[bytes]:
        return [self._ack(frame.seq, p.HEARTBEAT)]

    def _on_clear(self, frame: p.Frame, now_ms: int) -> list[bytes]:
        if self.state == p.STATE_BUSY:
            return [self._nak(frame.seq, p.CLEAR, p.NAK_BUSY)]
        if self.state == p.STATE_READY:
            return [self._ack(frame.seq, p.CLEAR)]
        # Latched: drive the flap home to reject; the ACK comes once it is there.
        self._start_move(frame.seq, p.CLEAR, p.REJECT_BIN, now_ms)
        return []

    def _start_move(self, seq: int, request_type: int, target: int, now_ms: int) -> None:
        self.move = _Move(seq, request_type, target, now_ms)
        self.state = p.STATE_BUSY

    # --- time --------------------------------------------------------------------------------
    def tick(self, now_ms: int) -> list[bytes]:
        out: list[bytes] = []
        if self.state in (p.STATE_READY, p.STATE_BUSY) and now_ms - self.last_rx_ms > self.heartbeat_timeout_ms:
            out += self._failsafe(now_ms)
        move = self.move
        if move is None:
            return out
        elapsed = now_ms - move.started_ms
        if not self.jam_present and elapsed >= self.move_time_ms:
            self.move = None
            self.bin = move.target_bin
            self.state, self.fault = p.STATE_READY, p.FAULT_NONE
            if move.request_type == p.SORT:
                self.sorts_done += 1
                self.executed.append(move.target_bin)
            out.append(self._ack(move.seq, move.request_type))
        elif self.jam_present and elapsed >= self.move_timeout_ms:
            # The position sensor never confirmed: stop driving, latch, report.
            self.move = None
            self.state, self.fault = p.STATE_FAULT, p.FAULT_JAM
            reason = p.NAK_JAM if move.request_type == p.SORT else p.NAK_JAM_PRESENT
            out.append(self._nak(move.seq, move.request_type, reason))
            out.append(self._fault_frame())
        return out

    def _failsafe(self, now_ms: int) -> list[bytes]:
        out = []
        move, self.move = self.move, None
        # the duplicate memory is forgotten: a cached ACK says READY at a bin, and after the host's
        # 8-bit SEQ wraps a new SORT could match it and be answered "done" while the flap is at reject
        self.last_request = self.last_reply = None
        self.state, self.fault = p.STATE_FAILSAFE, p.FAULT_HEARTBEAT_LOST
        self.bin = p.REJECT_BIN  # the servo is commanded to reject at once
        if move is not None:
            out.append(self._nak(move.seq, move.request_type, p.NAK_LATCHED))
        out.append(self._fault_frame())
        return out

    # --- frames out --------------------------------------------------------------------------
    def _remember(self, frame: bytes, seq: int, request_type: int) -> bytes:
        """Cache the reply to the request in the duplicate memory, so a retransmission gets it."""
        if self.last_request is not None and self.last_request[:2] == (seq, request_type):
            self.last_reply = frame
        return frame

    def _ack(self, seq: int, acked_type: int) -> bytes:
        ack = p.Ack(acked_type, self.state, self.bin, self.fault, self.boot_id)
        return self._remember(p.encode_frame(seq, p.ACK, ack.pack()), seq, acked_type)

    def _nak(self, seq: int, acked_type: int, reason: int) -> bytes:
        nak = p.Nak(acked_type, reason, self.state, self.bin, self.fault, self.boot_id)
        return self._remember(p.encode_frame(seq, p.NAK, nak.pack()), seq, acked_type)

    def _fault_frame(self) -> bytes:
        self.event_seq = (self.event_seq + 1) & 0xFF
        report = p.FaultReport(self.fault, self.state, self.bin, self.boot_id)
        return p.encode_frame(self.event_seq, p.FAULT, report.pack())


@dataclass
class LineFaults:
    """What the simulated line and MCU do wrong; change fields while the simulator runs."""

    ack_delay_s: float = 0.0  # every reply leaves this late (a slow MCU)
    drop_tx: int = 0  # drop the next N frames the MCU sends
    drop_rx: int = 0  # lose the next N frames the host sends (never reach the firmware)
    duplicate_tx: int = 0  # send the next N MCU frames twice
    noise_bytes: int = 0  # random bytes (sync bytes included) written before every MCU frame
    # A lying MCU (firmware bug, wrong firmware, a corrupted byte the CRC happened to pass): the
    # next ``lie_acks`` ACKs of a SORT or CLEAR go out with their fields replaced by those set
    # here (None keeps the true value), CRC recomputed, SEQ and type right.
    lie_acks: int = 0
    lie_bin: int | None = None
    lie_state: int | None = None
    lie_fault: int | None = None
    seed: int = 0
    rng: random.Random = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self.rng = random.Random(self.seed)


class MCUSimulator:
    """``GateFirmware`` on the master side of a pty, in a background thread."""

    def __init__(self, *, faults: LineFaults | None = None, transport: str = "pty", **firmware_kwargs) -> None:
        if transport not in ("pty", "tcp"):
            raise ValueError(f"transport must be 'pty' or 'tcp', got {transport!r}")
        self.faults = faults or LineFaults()
        self._lock = threading.RLock()
        self._t0 = time.monotonic()
        self.firmware = GateFirmware(now_ms=self.now_ms(), **firmware_kwargs)
        self.master_fd = self.slave_fd = -1
        self._listener: socket.socket | None = None
        self._conn: socket.socket | None = None
        if transport == "pty":
            self.master_fd, self.slave_fd = os.openpty()
            tty.setraw(self.slave_fd)  # no echo, no CR/LF translation: a binary line
            os.set_blocking(self.master_fd, False)
            self.device_path = os.ttyname(self.slave_fd)
        else:
            # pyserial's socket:// URL, as a serial-over-LAN bridge would offer; loopback only.
            self._listener = socket.create_server(("127.0.0.1", 0))
            self._listener.setblocking(False)
            self.device_path = f"socket://127.0.0.1:{self._listener.getsockname()[1]}"
        self.reader = p.FrameReader()
        self.rx_frames: list[p.Frame] = []  # every valid frame that reached the firmware
        self.tx_frames = 0
        self.lies_told = 0  # ACKs sent with replaced fields (LineFaults.lie_acks)
        self._outbox: list[tuple[float, bytes]] = []  # (due time, frame)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="mcu-sim", daemon=True)

    def now_ms(self) -> int:
        return int((time.monotonic() - self._t0) * 1000)

    def start(self) -> "MCUSimulator":
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=2)
        for fd in (self.master_fd, self.slave_fd):
            if fd >= 0:
                try:
                    os.close(fd)
                except OSError:
                    pass
        for sock in (self._conn, self._listener):
            if sock is not None:
                sock.close()

    def __enter__(self) -> "MCUSimulator":
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # --- injections (thread-safe) --------------------------------------------------------------
    def jam(self, present: bool = True) -> None:
        """Block (or free) the flap: moves stop confirming until freed."""
        with self._lock:
            self.firmware.jam_present = present

    def reboot(self) -> None:
        """A brown-out or watchdog reset: the MCU comes back with a new boot id, latched."""
        with self._lock:
            self._outbox.clear()
            self.reader = p.FrameReader()
            self.firmware.reboot(self.now_ms())

    def inject_noise(self, data: bytes) -> None:
        """Write raw bytes to the host as if the line picked them up."""
        with self._lock:
            self._outbox.append((time.monotonic(), bytes(data)))

    def send_raw(self, frame: bytes) -> None:  # alias used by tests for clarity
        self.inject_noise(frame)

    @property
    def state(self) -> int:
        with self._lock:
            return self.firmware.state

    @property
    def executed(self) -> list[int]:
        with self._lock:
            return list(self.firmware.executed)

    # --- the loop ------------------------------------------------------------------------------
    def _receive(self) -> bytes:
        """Bytes from the host within ~2 ms, from the pty or the TCP connection."""
        if self.master_fd >= 0:
            ready, _, _ = select.select([self.master_fd], [], [], 0.002)
            if not ready:
                return b""
            try:
                return os.read(self.master_fd, 4096)
            except OSError as exc:
                if exc.errno in (errno.EAGAIN, errno.EIO):  # EIO: no host has the tty open
                    return b""
                raise
        sockets = [self._listener] + ([self._conn] if self._conn is not None else [])
        ready, _, _ = select.select(sockets, [], [], 0.002)
        if self._listener in ready:
            conn, _ = self._listener.accept()
            if self._conn is not None:
                self._conn.close()  # one host at a time, like a UART
            conn.setblocking(False)
            self._conn = conn
        if self._conn is not None and self._conn in ready:
            try:
                data = self._conn.recv(4096)
            except BlockingIOError:
                return b""
            except OSError:
                data = b""
            if not data:  # the host hung up; the MCU keeps running
                self._conn.close()
                self._conn = None
            return data
        return b""

    def _transmit(self, data: bytes) -> None:
        if self.master_fd >= 0:
            os.write(self.master_fd, data)
        elif self._conn is not None:
            self._conn.send(data)

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                data = self._receive()
            except (OSError, ValueError):
                return
            with self._lock:
                now = self.now_ms()
                out: list[bytes] = []
                for frame in self.reader.feed(data) if data else []:
                    if self.faults.drop_rx > 0:
                        self.faults.drop_rx -= 1
                        continue
                    self.rx_frames.append(frame)
                    out += self.firmware.on_frame(frame, now)
                out += self.firmware.tick(now)
                for frame in out:
                    self._queue(frame)
                self._flush_due()

    def _lie(self, frame: bytes) -> bytes:
        """``frame`` as the lying MCU sends it (LineFaults.lie_acks), or unchanged."""
        faults = self.faults
        if faults.lie_acks <= 0 or frame[3] != p.ACK:
            return frame
        decoded = p.decode_frame(frame)
        ack = p.parse_reply(decoded)
        if ack.acked_type not in (p.SORT, p.CLEAR):
            return frame
        faults.lie_acks -= 1
        lie = p.Ack(ack.acked_type, ack.state if faults.lie_state is None else faults.lie_state,
                    ack.bin if faults.lie_bin is None else faults.lie_bin,
                    ack.fault if faults.lie_fault is None else faults.lie_fault, ack.boot_id)
        self.lies_told += 1
        return p.encode_frame(decoded.seq, p.ACK, lie.pack())

    def _queue(self, frame: bytes) -> None:
        faults = self.faults
        frame = self._lie(frame)
        if faults.drop_tx > 0:
            faults.drop_tx -= 1
            return
        copies = 1
        if faults.duplicate_tx > 0:
            faults.duplicate_tx -= 1
            copies = 2
        due = time.monotonic() + faults.ack_delay_s
        for _ in range(copies):
            noise = bytes(faults.rng.choice((p.SYNC, faults.rng.randrange(256)))
                          for _ in range(faults.noise_bytes))
            self._outbox.append((due, noise + frame))

    def _flush_due(self) -> None:
        now = time.monotonic()
        keep = []
        for due, data in self._outbox:
            if due > now:
                keep.append((due, data))
                continue
            try:
                self._transmit(data)
                self.tx_frames += 1
            except OSError:
                pass  # nobody reading (buffer full or closed): a real UART would lose it too
        self._outbox = keep


def start_simulated_gate(*, faults: LineFaults | None = None, transport: str = "pty",
                         **firmware_kwargs) -> tuple[str, MCUSimulator]:
    """Start a simulated gate MCU on a new pty (or a loopback TCP port: transport="tcp");
    returns (device path or pyserial URL for the host, simulator)."""
    sim = MCUSimulator(faults=faults, transport=transport, **firmware_kwargs).start()
    return sim.device_path, sim


def main(argv: list[str] | None = None) -> int:
    """A simulated gate in its own process, up until SIGINT/SIGTERM: for commissioning practice,
    and for tests where the gate must outlive the service (a killed daemon does not kill the real
    gate). Prints its device path on the first line; on exit, ``executed [bins]`` (JSON) - the
    moves SORT made - so a test can reconcile them with the journal."""
    import argparse
    import json
    import signal

    parser = argparse.ArgumentParser(prog="python -m vs2t_edge.firmware_bridge.mcu_sim")
    parser.add_argument("--transport", choices=("pty", "tcp"), default="pty")
    parser.add_argument("--move-ms", type=int, default=60, help="time a move takes")
    parser.add_argument("--heartbeat-timeout-ms", type=int, default=p.HEARTBEAT_TIMEOUT_MS)
    args = parser.parse_args(argv)

    def stop(_signum, _frame):
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, stop)
    path, sim = start_simulated_gate(transport=args.transport, move_time_ms=args.move_ms,
                                     heartbeat_timeout_ms=args.heartbeat_timeout_ms)
    print(f"simulated gate on {path} (Ctrl-C to stop); try: VS2T_GATE_PORT={path} vs2t-edge sort status",
          flush=True)
    try:
        while True:
            time.sleep(1)
    except KeyboardInterrupt:
        pass
    finally:
        sim.stop()
        print("executed " + json.dumps(sim.executed), flush=True)
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
