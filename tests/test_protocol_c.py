"""The firmware's C speaks the same protocol as the Python host: compiled here with gcc.

gate_proto.c (CRC, parser, encoder) is checked byte for byte against protocol.py; gate_core.c
(the firmware's state machine) runs on a pseudo-terminal through host_harness.c and the real
Python host driver talks to it. Skips when no C compiler is installed.
"""

from __future__ import annotations

import json
import random
import re
import shutil
import subprocess
import time
from pathlib import Path

import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from vs2t_edge.firmware_bridge import protocol as p
from vs2t_edge.firmware_bridge.gate_client import GateClient, GateClientError

FIRMWARE = Path(__file__).resolve().parents[1] / "firmware_bridge" / "firmware"
SEEDS = sorted((Path(__file__).parent / "fuzz_seeds" / "gate").glob("*.json"))
CC = shutil.which("gcc") or shutil.which("cc")
pytestmark = pytest.mark.skipif(CC is None, reason="no C compiler (gcc/cc) on this machine")


@pytest.fixture(scope="module")
def harness(tmp_path_factory) -> Path:
    exe = tmp_path_factory.mktemp("fw") / "host_harness"
    cmd = [CC, "-std=c99", "-pedantic", "-Wall", "-Wextra", "-Werror", "-O2", "-o", str(exe),
           *(str(FIRMWARE / f) for f in ("host_harness.c", "gate_core.c", "gate_proto.c"))]
    built = subprocess.run(cmd, capture_output=True, text=True)
    assert built.returncode == 0, f"firmware C does not compile cleanly:\n{built.stderr}"
    return exe


@pytest.fixture(scope="module")
def c_parser(harness):
    """A long-running `host_harness parse`: one hex line in, one line of frames out."""
    proc = subprocess.Popen([str(harness), "parse"], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
                            bufsize=1)

    def parse(stream: bytes) -> tuple[list[bytes], int]:
        proc.stdin.write(stream.hex() + "\n")
        proc.stdin.flush()
        frames, dropped = proc.stdout.readline().rsplit("| dropped ", 1)
        return [bytes.fromhex(f) for f in frames.split()], int(dropped)

    yield parse
    proc.stdin.close()
    proc.wait(timeout=5)


def python_parse(stream: bytes) -> tuple[list[bytes], int]:
    reader = p.FrameReader()
    found = [f.encode() for f in reader.feed(stream)]
    return found, reader.dropped_bytes


def run(harness, *args) -> str:
    return subprocess.run([str(harness), *args], capture_output=True, text=True, check=True).stdout.strip()


def test_c_crc_check_value_and_agreement(harness):
    assert run(harness, "crc", b"123456789".hex()) == "29b1"
    rng = random.Random(6)
    for _ in range(15):
        data = bytes(rng.randrange(256) for _ in range(rng.randrange(0, 40)))
        assert int(run(harness, "crc", data.hex() or "x"), 16) == p.crc16_ccitt_false(data)


def test_c_constants_match_python():
    header = (FIRMWARE / "gate_proto.h").read_text()
    defines = {name: int(value, 0) for name, value in re.findall(r"#define GATE_(\w+) (0x[0-9A-Fa-f]+|\d+)\b", header)}
    python_names = {
        "SYNC": p.SYNC, "MAX_PAYLOAD": p.MAX_PAYLOAD, "HEADER_LEN": p.HEADER_LEN, "CRC_LEN": p.CRC_LEN,
        "SORT": p.SORT, "STATUS": p.STATUS, "HEARTBEAT": p.HEARTBEAT, "CLEAR": p.CLEAR, "ACK": p.ACK,
        "NAK": p.NAK, "STATUS_REPLY": p.STATUS_REPLY, "FAULT": p.FAULT,
        "STATE_READY": p.STATE_READY, "STATE_BUSY": p.STATE_BUSY, "STATE_FAULT": p.STATE_FAULT,
        "STATE_FAILSAFE": p.STATE_FAILSAFE, "FAULT_NONE": p.FAULT_NONE,
        "FAULT_HEARTBEAT_LOST": p.FAULT_HEARTBEAT_LOST, "FAULT_JAM": p.FAULT_JAM, "FAULT_BOOT": p.FAULT_BOOT,
        "NAK_BAD_BIN": p.NAK_BAD_BIN, "NAK_BAD_LENGTH": p.NAK_BAD_LENGTH, "NAK_UNKNOWN_TYPE": p.NAK_UNKNOWN_TYPE,
        "NAK_LATCHED": p.NAK_LATCHED, "NAK_JAM": p.NAK_JAM, "NAK_JAM_PRESENT": p.NAK_JAM_PRESENT,
        "NAK_BUSY": p.NAK_BUSY, "HEARTBEAT_TIMEOUT_MS": p.HEARTBEAT_TIMEOUT_MS,
        "MOVE_TIMEOUT_MS": p.MOVE_TIMEOUT_MS, "DEFAULT_N_BINS": p.DEFAULT_N_BINS, "REJECT_BIN": p.REJECT_BIN,
        "BAUDRATE": p.BAUDRATE, "NEED_MORE": p.NEED_MORE, "DROP": p.DROP, "FRAME": p.FRAME,
    }
    for name, value in python_names.items():
        assert defines.get(name) == value, f"GATE_{name} in gate_proto.h is {defines.get(name)}, protocol.py {value}"


def test_c_encoder_matches_python(harness):
    for seq, typ, payload in [(0, p.SORT, b"\x03"), (255, p.HEARTBEAT, b""), (7, p.STATUS_REPLY, bytes(range(14))),
                              (0xA5, 0xA5, b"\xa5" * 16)]:
        assert run(harness, "encode", str(seq), str(typ), payload.hex()) == p.encode_frame(seq, typ, payload).hex()


@pytest.mark.parametrize("seed", SEEDS, ids=[s.stem for s in SEEDS])
def test_c_parser_on_the_seed_corpus(c_parser, seed):
    case = json.loads(seed.read_text())
    stream = bytes.fromhex(case["stream"])
    frames, _ = c_parser(stream)
    assert frames == [bytes.fromhex(f) for f in case["frames"]]


frame_st = st.builds(lambda s, t, pl: p.encode_frame(s, t, pl), st.integers(0, 255), st.integers(0, 255),
                     st.binary(max_size=16))
stream_st = st.lists(st.one_of(frame_st, st.binary(max_size=30), st.just(bytes([p.SYNC])),
                               frame_st.flatmap(lambda f: st.integers(0, len(f) * 8 - 1).map(
                                   lambda bit: bytes(b ^ (1 << (bit % 8)) if i == bit // 8 else b
                                                     for i, b in enumerate(f))))),
                     max_size=12).map(b"".join)


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow,
                                                                  HealthCheck.function_scoped_fixture])
@given(stream_st)
def test_c_parser_accepts_and_drops_exactly_what_python_does(c_parser, stream):
    # Frames, garbage, lone sync bytes and bit-flipped frames, mixed: same frames, same drops.
    assert c_parser(stream) == python_parse(stream)


# --- the firmware's state machine on a pty against the real host driver ---------------------------

class CGate:
    def __init__(self, harness: Path, heartbeat_timeout_ms: int) -> None:
        self.proc = subprocess.Popen([str(harness), "gate", "--heartbeat-timeout-ms", str(heartbeat_timeout_ms)],
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, bufsize=1)
        self.path = self.proc.stdout.readline().strip()

    def command(self, line: str) -> dict[str, int]:
        self.proc.stdin.write(line + "\n")
        self.proc.stdin.flush()
        words = self.proc.stdout.readline().split()
        return {k: int(v) for k, v in zip(words[::2], words[1::2])}

    def close(self) -> None:
        try:
            self.command("quit")
        except (BrokenPipeError, ValueError):
            pass
        self.proc.wait(timeout=5)


@pytest.fixture
def c_gate(harness):
    gate = CGate(harness, heartbeat_timeout_ms=600)
    yield gate
    gate.close()


def test_c_firmware_routes_naks_and_dedups_with_the_python_driver(c_gate):
    with GateClient(c_gate.path, timeout_s=0.3, heartbeat_period_s=0.1) as client:
        assert client.armed_from == "boot"
        client.sort(3)
        assert client.status().bin == 3
        with pytest.raises(GateClientError) as bad:
            client.sort(8)
        assert bad.value.reason == "bad_bin"
        # A retransmitted SORT (same SEQ) is acked from the cache, not executed again.
        with client._lock:
            frame = p.encode_frame(client._next_seq(), p.SORT, b"\x05")
            client._write(frame)
            first = client._wait_reply(frame[2], p.SORT, time.monotonic() + 1)
            client._write(frame)
            again = client._wait_reply(frame[2], p.SORT, time.monotonic() + 1)
        assert isinstance(first, p.Ack) and again == first
        assert c_gate.command("info")["sorts"] == 2


def test_c_firmware_jam_reboot_and_failsafe_with_the_python_driver(c_gate):
    with GateClient(c_gate.path, timeout_s=0.4, heartbeat_period_s=0.1) as client:
        c_gate.command("jam 1")
        with pytest.raises(GateClientError) as jam:
            client.sort(2)
        assert jam.value.kind == "jam"
        with pytest.raises(GateClientError) as still:
            client.clear()
        assert still.value.reason == "jam_present"
        c_gate.command("jam 0")
        client.clear()
        client.sort(2)
        assert [r.fault for r in client.fault_reports] == [p.FAULT_JAM, p.FAULT_JAM]

        c_gate.command("reboot")
        with pytest.raises(GateClientError, match=r"rebooted \(boot id 1 -> 2\)"):
            client.sort(4)
        client.clear()
        client.sort(4)

        client.stop_heartbeat()
        time.sleep(0.8)  # past the 600 ms watchdog
        state = c_gate.command("info")
        assert (state["state"], state["fault"], state["bin"]) == (p.STATE_FAILSAFE, p.FAULT_HEARTBEAT_LOST, 0)
        with pytest.raises(GateClientError) as latched:
            client.sort(1)
        assert latched.value.kind == "fault_latched"
        client.clear()
        client.sort(1)
        assert c_gate.command("info")["sorts"] == 2  # after the reboot: 4, then 1


# --- differential: the Python MCU simulator's firmware model against the C firmware -------------

@pytest.fixture(scope="module")
def c_script(harness):
    """A long-running `host_harness script`: one command in, the frames the C core wrote out."""
    proc = subprocess.Popen([str(harness), "script", "--heartbeat-timeout-ms", "500", "--move-time-ms", "60"],
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, bufsize=1)

    def step(command: str) -> list[str]:
        proc.stdin.write(command + "\n")
        proc.stdin.flush()
        return proc.stdout.readline().split()

    yield step
    proc.stdin.close()
    proc.wait(timeout=5)


request_st = st.one_of(
    st.tuples(st.integers(0, 255), st.just(p.SORT), st.integers(0, 9).map(lambda b: bytes([b]))),
    st.tuples(st.integers(0, 255), st.sampled_from([p.STATUS, p.HEARTBEAT, p.CLEAR]), st.just(b"")),
    st.tuples(st.integers(0, 255), st.sampled_from([p.SORT, p.CLEAR, 0x42, p.ACK]), st.binary(max_size=3)),
)
event_st = st.one_of(
    st.tuples(st.just("send"), request_st),
    st.tuples(st.just("repeat"), st.none()),  # the host retransmits its last frame
    # Clock steps, with the boundaries of move time (60), move timeout (300) and watchdog (500).
    st.tuples(st.just("advance"), st.one_of(st.integers(0, 700), st.sampled_from([59, 60, 61, 299, 300, 301,
                                                                                   499, 500, 501]))),
    st.tuples(st.just("jam"), st.booleans()),
    st.tuples(st.just("reboot"), st.none()),
    st.tuples(st.just("noise"), st.binary(min_size=1, max_size=8)),
)


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow,
                                                                  HealthCheck.function_scoped_fixture])
@given(st.lists(event_st, min_size=1, max_size=40))
# The timing boundaries, spelled out: move done at exactly 60 ms, watchdog at exactly 500 ms
# of silence, jam at exactly 300 ms.
@example([("send", (1, p.CLEAR, b"")), ("advance", 59), ("advance", 1), ("send", (2, p.HEARTBEAT, b"")),
          ("advance", 500), ("advance", 1)])
@example([("send", (1, p.CLEAR, b"")), ("advance", 60), ("jam", True), ("send", (2, p.SORT, b"\x03")),
          ("advance", 299), ("advance", 1), ("repeat", None), ("send", (3, p.CLEAR, b"")), ("advance", 300)])
# A fail-safe forgets the duplicate memory: the same SORT frame again (a wrapped SEQ) is refused, not
# answered with the ACK cached before the latch.
@example([("send", (1, p.CLEAR, b"")), ("advance", 60), ("send", (5, p.SORT, b"\x03")), ("advance", 60),
          ("advance", 501), ("repeat", None)])
def test_python_simulator_behaves_as_the_c_firmware(c_script, events):
    """Same bytes and clock into mcu_sim.GateFirmware and gate_core.c: same frames out, byte for byte."""
    from vs2t_edge.firmware_bridge.mcu_sim import GateFirmware

    now_ms, last = 0, b""
    model = GateFirmware(now_ms=now_ms, boot_id=1, heartbeat_timeout_ms=500, move_time_ms=60)
    reader = p.FrameReader()
    assert c_script("boot 0 1") == []
    transcript = []
    for kind, arg in events:
        if kind in ("send", "repeat", "noise"):
            data = p.encode_frame(*arg) if kind == "send" else (last if kind == "repeat" else arg)
            last = data if kind == "send" else last
            if not data:
                continue
            command = f"rx {now_ms} {data.hex()}"
            out = [f for frame in reader.feed(data) for f in model.on_frame(frame, now_ms)]
        elif kind == "advance":
            now_ms += arg
            command, out = f"tick {now_ms}", model.tick(now_ms)
        elif kind == "jam":
            command, out = f"jam {int(arg)}", []
            model.jam_present = arg
        else:
            command, out = f"reboot {now_ms}", []
            model.reboot(now_ms)
            reader = p.FrameReader()  # gate_core_boot() empties the C reader too
        transcript.append(command)
        assert c_script(command) == [f.hex() for f in out], "\n".join(transcript)
        # Both tick after every step, as the firmware's loop does.
        assert c_script(f"tick {now_ms}") == [f.hex() for f in model.tick(now_ms)], "\n".join(transcript)
