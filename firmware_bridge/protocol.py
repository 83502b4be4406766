"""The gate's serial protocol (docs/protocol.md): CRC, frames, the pure parser, message codecs.

No I/O here. ``check_frame`` looks at the front of a byte buffer and says NEED_MORE, DROP k or
FRAME n; it never raises, whatever the bytes. ``FrameReader`` keeps the buffer for a stream.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import NamedTuple

SYNC = 0xA5
MAX_PAYLOAD = 16
HEADER_LEN = 4  # SYNC, LEN, SEQ, TYPE
CRC_LEN = 2
MIN_FRAME = HEADER_LEN + CRC_LEN
MAX_FRAME = MIN_FRAME + MAX_PAYLOAD

# Message types: host -> MCU requests
SORT = 0x01
STATUS = 0x02
HEARTBEAT = 0x03
CLEAR = 0x04
REQUEST_TYPES = (SORT, STATUS, HEARTBEAT, CLEAR)
# MCU -> host
ACK = 0x80
NAK = 0x81
STATUS_REPLY = 0x82
FAULT = 0x83

TYPE_NAMES = {SORT: "SORT", STATUS: "STATUS", HEARTBEAT: "HEARTBEAT", CLEAR: "CLEAR",
              ACK: "ACK", NAK: "NAK", STATUS_REPLY: "STATUS_REPLY", FAULT: "FAULT"}

# Gate states
STATE_READY, STATE_BUSY, STATE_FAULT, STATE_FAILSAFE = 0, 1, 2, 3
STATE_NAMES = {STATE_READY: "ready", STATE_BUSY: "busy", STATE_FAULT: "fault", STATE_FAILSAFE: "failsafe"}

# Fault codes
FAULT_NONE, FAULT_HEARTBEAT_LOST, FAULT_JAM, FAULT_BOOT = 0, 1, 2, 3
FAULT_NAMES = {FAULT_NONE: "", FAULT_HEARTBEAT_LOST: "heartbeat_lost", FAULT_JAM: "jam", FAULT_BOOT: "boot"}

# NAK reasons
NAK_BAD_BIN, NAK_BAD_LENGTH, NAK_UNKNOWN_TYPE, NAK_LATCHED, NAK_JAM, NAK_JAM_PRESENT, NAK_BUSY = range(1, 8)
NAK_NAMES = {NAK_BAD_BIN: "bad_bin", NAK_BAD_LENGTH: "bad_length", NAK_UNKNOWN_TYPE: "unknown_type",
             NAK_LATCHED: "latched", NAK_JAM: "jam", NAK_JAM_PRESENT: "jam_present", NAK_BUSY: "busy"}
# How the host reports each NAK reason (runtime.devices.GateError.kind)
NAK_ERROR_KIND = {NAK_BAD_BIN: "nak", NAK_BAD_LENGTH: "nak", NAK_UNKNOWN_TYPE: "nak", NAK_BUSY: "nak",
                  NAK_LATCHED: "fault_latched", NAK_JAM: "jam", NAK_JAM_PRESENT: "jam"}

# Timing (firmware constants; the simulator and host defaults follow them)
HEARTBEAT_TIMEOUT_MS = 1000
HEARTBEAT_PERIOD_S = 0.25
MOVE_TIMEOUT_MS = 300
DEFAULT_N_BINS = 8
REJECT_BIN = 0
BAUDRATE = 115200

# Parser answers
NEED_MORE = 0
DROP = 1
FRAME = 2


def _make_crc_table() -> tuple[int, ...]:
    table = []
    for byte in range(256):
        crc = byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) if crc & 0x8000 else (crc << 1)
        table.append(crc & 0xFFFF)
    return tuple(table)


_CRC_TABLE = _make_crc_table()


def crc16_ccitt_false(data: bytes | bytearray | memoryview, crc: int = 0xFFFF) -> int:
    """CRC-16/CCITT-FALSE: poly 0x1021, init 0xFFFF, no reflection, xorout 0. check = 0x29B1."""
    for byte in bytes(data):
        crc = ((crc << 8) & 0xFFFF) ^ _CRC_TABLE[((crc >> 8) ^ byte) & 0xFF]
    return crc


class Check(NamedTuple):
    kind: int  # NEED_MORE, DROP or FRAME
    length: int  # bytes to drop, or the frame's length; 0 for NEED_MORE


def _next_sync(buf: bytes | bytearray, start: int) -> int:
    index = buf.find(bytes((SYNC,)), start)
    return len(buf) if index < 0 else index


def check_frame(buf: bytes | bytearray) -> Check:
    """What the front of ``buf`` holds. Pure, total: never raises on any bytes-like input."""
    n = len(buf)
    if n == 0:
        return Check(NEED_MORE, 0)
    if buf[0] != SYNC:
        return Check(DROP, _next_sync(buf, 1))
    if n < 2:
        return Check(NEED_MORE, 0)
    payload_len = buf[1]
    if payload_len > MAX_PAYLOAD:
        return Check(DROP, _next_sync(buf, 1))
    frame_len = MIN_FRAME + payload_len
    if n < frame_len:
        return Check(NEED_MORE, 0)
    body_end = HEADER_LEN + payload_len
    received = (buf[body_end] << 8) | buf[body_end + 1]
    if crc16_ccitt_false(buf[1:body_end]) != received:
        # Drop only up to the next sync: LEN may be the corrupted byte, and a good frame may
        # start inside this bad one.
        return Check(DROP, _next_sync(buf, 1))
    return Check(FRAME, frame_len)


@dataclass(frozen=True)
class Frame:
    seq: int
    type: int
    payload: bytes = b""

    def encode(self) -> bytes:
        return encode_frame(self.seq, self.type, self.payload)

    def describe(self) -> str:
        return f"{TYPE_NAMES.get(self.type, hex(self.type))} seq={self.seq} payload={self.payload.hex()}"


def encode_frame(seq: int, msg_type: int, payload: bytes = b"") -> bytes:
    if not 0 <= seq <= 255 or not 0 <= msg_type <= 255:
        raise ValueError(f"seq {seq} and type {msg_type} must be bytes (0..255)")
    if len(payload) > MAX_PAYLOAD:
        raise ValueError(f"payload of {len(payload)} bytes exceeds the protocol's {MAX_PAYLOAD}")
    body = bytes((len(payload), seq, msg_type)) + bytes(payload)
    return bytes((SYNC,)) + body + struct.pack(">H", crc16_ccitt_false(body))


def decode_frame(frame: bytes) -> Frame:
    """Fields of a frame that check_frame accepted."""
    payload_len = frame[1]
    return Frame(seq=frame[2], type=frame[3], payload=bytes(frame[HEADER_LEN:HEADER_LEN + payload_len]))


class FrameReader:
    """Accumulates stream bytes and yields frames; counts what it had to throw away. No I/O."""

    def __init__(self) -> None:
        self._buf = bytearray()
        self.dropped_bytes = 0
        self.frames = 0

    def feed(self, data: bytes) -> list[Frame]:
        self._buf += data
        found: list[Frame] = []
        while True:
            kind, length = check_frame(self._buf)
            if kind == NEED_MORE:
                break
            if kind == DROP:
                self.dropped_bytes += length
            else:
                found.append(decode_frame(bytes(self._buf[:length])))
                self.frames += 1
            del self._buf[:length]
        return found

    @property
    def pending(self) -> int:
        return len(self._buf)


# --- message payloads -----------------------------------------------------------------------

@dataclass(frozen=True)
class Ack:
    acked_type: int
    state: int
    bin: int
    fault: int
    boot_id: int

    def pack(self) -> bytes:
        return struct.pack(">BBBBH", self.acked_type, self.state, self.bin, self.fault, self.boot_id)


@dataclass(frozen=True)
class Nak:
    acked_type: int
    reason: int
    state: int
    bin: int
    fault: int
    boot_id: int

    def pack(self) -> bytes:
        return struct.pack(">BBBBBH", self.acked_type, self.reason, self.state, self.bin, self.fault, self.boot_id)


@dataclass(frozen=True)
class StatusReply:
    state: int
    bin: int
    fault: int
    n_bins: int
    boot_id: int
    uptime_ms: int
    sorts_done: int

    def pack(self) -> bytes:
        return struct.pack(">BBBBHII", self.state, self.bin, self.fault, self.n_bins, self.boot_id,
                           self.uptime_ms & 0xFFFFFFFF, self.sorts_done & 0xFFFFFFFF)


@dataclass(frozen=True)
class FaultReport:
    fault: int
    state: int
    bin: int
    boot_id: int

    def pack(self) -> bytes:
        return struct.pack(">BBBH", self.fault, self.state, self.bin, self.boot_id)


_PAYLOADS = {ACK: (Ack, ">BBBBH"), NAK: (Nak, ">BBBBBH"), STATUS_REPLY: (StatusReply, ">BBBBHII"),
             FAULT: (FaultReport, ">BBBH")}


class MessageError(ValueError):
    """A frame with a good CRC whose type or payload length is not what the protocol says."""


def parse_reply(frame: Frame) -> Ack | Nak | StatusReply | FaultReport:
    """Payload of an MCU -> host frame; MessageError (never anything else) if it does not fit."""
    entry = _PAYLOADS.get(frame.type)
    if entry is None:
        raise MessageError(f"frame type {frame.type:#04x} is not a reply ({frame.describe()})")
    cls, fmt = entry
    if len(frame.payload) != struct.calcsize(fmt):
        raise MessageError(f"{TYPE_NAMES[frame.type]} payload is {len(frame.payload)} bytes, "
                           f"expected {struct.calcsize(fmt)} ({frame.describe()})")
    return cls(*struct.unpack(fmt, frame.payload))
