"""The gate protocol's CRC and pure parser (docs/protocol.md), hammered with property tests."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from vs2t_edge.firmware_bridge import protocol as p

SEEDS = sorted((Path(__file__).parent / "fuzz_seeds" / "gate").glob("*.json"))
# Enough non-sync bytes after the last frame that any false start before it is disproved.
TAIL = b"\x00" * p.MAX_FRAME

frames_st = st.builds(
    lambda seq, typ, payload: p.encode_frame(seq, typ, payload),
    st.integers(0, 255), st.integers(0, 255), st.binary(max_size=p.MAX_PAYLOAD),
)
# Noise that is rich in sync bytes and small LEN values, the hard case for resync.
noise_st = st.lists(st.one_of(st.just(p.SYNC), st.integers(0, 20), st.integers(0, 255)), max_size=40).map(bytes)

fast = settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def decode_all(stream: bytes, cuts: list[int] | None = None) -> tuple[list[bytes], p.FrameReader]:
    """Feed the stream in pieces (cut positions) and return the raw frames found."""
    reader = p.FrameReader()
    found: list[p.Frame] = []
    start = 0
    for cut in sorted(set(c for c in (cuts or []) if 0 < c < len(stream))) + [len(stream)]:
        found += reader.feed(stream[start:cut])
        start = cut
    return [f.encode() for f in found], reader


def is_subsequence(needles: list[bytes], haystack: list[bytes]) -> bool:
    it = iter(haystack)
    return all(any(h == n for h in it) for n in needles)


def test_crc_check_value():
    assert p.crc16_ccitt_false(b"123456789") == 0x29B1


def test_crc_matches_bitwise_reference():
    def bitwise(data: bytes) -> int:  # the textbook definition, independent of the table
        crc = 0xFFFF
        for byte in data:
            crc ^= byte << 8
            for _ in range(8):
                crc = ((crc << 1) ^ 0x1021) & 0xFFFF if crc & 0x8000 else (crc << 1) & 0xFFFF
        return crc

    for data in (b"", b"\x00", b"\xff" * 7, bytes(range(256)), b"vs2t-edge gate"):
        assert p.crc16_ccitt_false(data) == bitwise(data)


def test_frame_layout_heartbeat_example():
    frame = p.encode_frame(7, p.HEARTBEAT)
    assert frame[:4] == bytes([0xA5, 0x00, 0x07, 0x03])
    assert int.from_bytes(frame[4:6], "big") == p.crc16_ccitt_false(b"\x00\x07\x03")
    assert p.check_frame(frame) == (p.FRAME, 6)
    assert p.check_frame(frame[:5]) == (p.NEED_MORE, 0)
    assert p.check_frame(b"\x01\x02" + frame) == (p.DROP, 2)


def test_encode_refuses_oversized_payload():
    with pytest.raises(ValueError, match="payload of 17 bytes"):
        p.encode_frame(0, p.SORT, b"x" * 17)


def test_reply_payloads_round_trip_and_bad_lengths_raise_message_error():
    replies = [p.Ack(p.SORT, 0, 3, 0, 513), p.Nak(p.SORT, p.NAK_BAD_BIN, 0, 0, 0, 65535),
               p.StatusReply(3, 0, 1, 8, 7, 2**32 - 1, 12), p.FaultReport(p.FAULT_JAM, 2, 4, 9)]
    types = [p.ACK, p.NAK, p.STATUS_REPLY, p.FAULT]
    for typ, reply in zip(types, replies):
        frame = p.decode_frame(p.encode_frame(1, typ, reply.pack()))
        assert p.parse_reply(frame) == reply
        with pytest.raises(p.MessageError, match="payload is"):
            p.parse_reply(p.Frame(1, typ, reply.pack()[:-1]))
    with pytest.raises(p.MessageError, match="not a reply"):
        p.parse_reply(p.Frame(1, p.SORT, b"\x01"))


@pytest.mark.parametrize("seed", SEEDS, ids=[s.stem for s in SEEDS])
def test_committed_seed_corpus(seed):
    case = json.loads(seed.read_text())
    stream = bytes.fromhex(case["stream"])
    expect = [bytes.fromhex(f) for f in case["frames"]]
    assert decode_all(stream)[0] == expect, seed.name
    # Byte-at-a-time feeding finds the same frames.
    assert decode_all(stream, list(range(len(stream))))[0] == expect, seed.name


@fast
@given(st.binary(max_size=200), st.lists(st.integers(0, 200), max_size=10))
def test_parser_never_raises_and_accounts_for_every_byte(garbage, cuts):
    kind, length = p.check_frame(garbage)
    assert kind in (p.NEED_MORE, p.DROP, p.FRAME)
    if kind == p.NEED_MORE:
        assert length == 0
    else:
        assert 1 <= length <= len(garbage)
    found, reader = decode_all(garbage, cuts)
    assert reader.dropped_bytes + sum(map(len, found)) + reader.pending == len(garbage)
    assert reader.pending < p.MAX_FRAME  # never hoards more than one frame's worth
    for frame in found:  # anything accepted really is a CRC-valid frame
        assert p.check_frame(frame) == (p.FRAME, len(frame))


@fast
@given(st.lists(st.tuples(noise_st, frames_st), min_size=1, max_size=6), noise_st,
       st.lists(st.integers(0, 400), max_size=12))
def test_every_frame_embedded_in_noise_is_found(pieces, trailing_noise, cuts):
    stream = b"".join(noise + frame for noise, frame in pieces) + trailing_noise + TAIL
    expected = [frame for _, frame in pieces]
    found, _ = decode_all(stream, cuts)
    # Noise may (very rarely) hold a CRC-valid frame of its own, so ours must be a subsequence.
    assert is_subsequence(expected, found), (stream.hex(), found)


@fast
@given(st.lists(frames_st, min_size=1, max_size=8), st.lists(st.integers(0, 200), max_size=12))
def test_concatenated_frames_found_in_order_whatever_the_chunking(frames, cuts):
    found, reader = decode_all(b"".join(frames), cuts)
    assert found == frames
    assert reader.dropped_bytes == 0 and reader.pending == 0


@fast
@given(frames_st, st.integers(1, 5))
def test_replayed_frames_are_all_delivered(frame, times):
    # The parser does not deduplicate; duplicates are the MCU's job (tests/test_gate.py).
    assert decode_all(frame * times)[0] == [frame] * times


@fast
@given(frames_st, st.data())
def test_single_bit_flip_is_dropped(frame, data):
    bit = data.draw(st.integers(0, len(frame) * 8 - 1))
    corrupted = bytearray(frame)
    corrupted[bit // 8] ^= 1 << (bit % 8)
    found, _ = decode_all(bytes(corrupted) + TAIL)
    assert found == [], f"bit {bit} flipped in {frame.hex()} still accepted"


@fast
@given(frames_st, st.data())
def test_burst_error_up_to_16_bits_after_len_is_dropped(frame, data):
    # CRC-16 detects every burst of <= 16 bits inside the checked bytes (SEQ..CRC here).
    first_bit = 16  # after SYNC and LEN
    total_bits = len(frame) * 8
    start = data.draw(st.integers(first_bit, total_bits - 1))
    width = data.draw(st.integers(1, min(16, total_bits - start)))
    pattern = data.draw(st.integers(0, (1 << width) - 1)) | 1 | (1 << (width - 1))  # ends are flipped
    value = int.from_bytes(frame, "big") ^ (pattern << (total_bits - start - width))
    corrupted = value.to_bytes(len(frame), "big")
    assert decode_all(corrupted + TAIL)[0] == []


@fast
@given(frames_st, frames_st, st.data())
def test_truncated_frame_followed_by_a_good_one(first, second, data):
    cut = data.draw(st.integers(1, len(first) - 1))
    found, _ = decode_all(first[:cut] + second + TAIL)
    if first[cut:] == second[:len(first) - cut]:  # the bytes cut off are the next frame's first ones:
        assert found[-1:] == [first]  # the stream holds the first frame whole (next test)
    else:
        assert found[-1:] == [second]


def test_a_cut_frame_whose_lost_tail_is_the_next_frames_head_is_read_whole():
    """A frame whose CRC ends in the SYNC byte, cut one byte short, then a frame: the bytes on the
    wire are the first frame complete (its last byte is the next frame's SYNC), so the reader
    returns it, and the next frame, its SYNC taken, is lost - as any unstuffed framing must; the
    host's retry resends it. Found by a clean clone's hypothesis draw."""
    first, second = p.encode_frame(7, 134, b"\x16*"), p.encode_frame(0, 0, b"")
    assert first[-1:] == second[:1] == bytes([p.SYNC])
    found, _ = decode_all(first[:-1] + second + TAIL)
    assert found == [first]


def test_doc_examples_decode():
    """Every worked example in docs/protocol.md is a valid frame and says what the text says."""
    doc = (Path(__file__).resolve().parents[1] / "docs" / "protocol.md").read_text()
    lines = [line for line in doc.splitlines() if line.startswith("A5 ")]
    assert len(lines) == 6, "the worked examples block in docs/protocol.md changed"
    decoded = []
    for line in lines:
        hex_part, words = line[:42].strip(), line[42:].strip()
        frame = bytes.fromhex(hex_part)
        assert p.check_frame(frame) == (p.FRAME, len(frame)), line
        decoded.append((p.decode_frame(frame), words))
    (sort, _), (ack, _), (bad, _), (nak, _), (beat, _), (fault, _) = decoded
    assert (sort.type, sort.seq, sort.payload) == (p.SORT, 0x10, b"\x03")
    assert p.parse_reply(ack) == p.Ack(p.SORT, p.STATE_READY, 3, p.FAULT_NONE, 2) and ack.seq == 0x10
    assert (bad.type, bad.payload) == (p.SORT, b"\x09")
    assert p.parse_reply(nak).reason == p.NAK_BAD_BIN and nak.seq == 0x11
    assert (beat.type, beat.seq, beat.payload) == (p.HEARTBEAT, 0x12, b"")
    assert p.parse_reply(fault) == p.FaultReport(p.FAULT_HEARTBEAT_LOST, p.STATE_FAILSAFE, 0, 2)
