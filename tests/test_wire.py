"""The packet's wire layout and its defensive decoder: the layout as documented (against an
independent struct/zlib writer), bit-exact round trips, and bad bytes (random, truncated,
bit-flipped, foreign, from the receiver's own side, non-finite, implausible (an ``engaged``
flag other than 0 or 1 too), ahead, stale)
rejected and counted by reason without ever raising or touching the packet given to the
decoder."""

from __future__ import annotations

import os
import struct
import subprocess
import sys
import zlib
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from teleop_rt.com import wire
from teleop_rt.com.port import HSI, TO, Packet
from teleop_rt.com.wire import (
    AHEAD,
    CHECKSUM,
    IMPLAUSIBLE,
    JOINTS,
    MAGIC_VERSION,
    NON_FINITE,
    OK,
    SESSION,
    SIDE,
    SIZE,
    STALE,
    Decoder,
    WireBounds,
    WireBuffer,
    encode_into,
    wire_size,
)
from tests.test_no_allocation import net_blocks

SESSION_ID = 0xFEDC_BA98_7654_3210  # above 2**63: the u64 field's top bit set
SENDER = TO  # the packets here are the TO's; a decoder at the HSI expects them


def packet(n: int, tick: int = 5, values: np.ndarray | None = None) -> Packet:
    p = Packet(n)
    p.f[:] = np.arange(1, p.f.size + 1) * 0.25 if values is None else values
    p.tick = p.seq = tick
    p.valid = p.engaged = 1
    return p


def encoded(
    p: Packet, session: int = SESSION_ID, side: int = SENDER, number: int | None = None
) -> bytes:  # fmt: skip
    return bytes(encode_into(WireBuffer(p.n), p, session, 123_456_789, side, number))


def struct_layout(p: Packet, session: int, time_ns: int, side: int, number: int) -> bytes:
    """The layout of the module's docstring, written field by field with struct and zlib."""
    n = p.n
    head = struct.pack("<4sBBHQQqqQ", b"TRWV", 5, side, n, session, p.seq, p.tick, time_ns,
                       number)  # fmt: skip
    vectors = (p.x, p.wave, p.wave_sum, p.x_sum, p.wave_energy, p.e_in, p.e_out)
    body = head + struct.pack(f"<{7 * n}ddQ", *np.concatenate(vectors), p.energy, p.engaged)
    return body + struct.pack("<II", zlib.crc32(body), 0)


def reseal(raw: bytes) -> bytes:
    """The bytes with a CRC that fits them again (to reach the checks after the CRC)."""
    body = raw[:-8]
    return body + struct.pack("<II", zlib.crc32(body), 0)


def untouched(into: Packet) -> bool:
    return bool((into.f == 7.0).all() and (into.i == 7).all())


def sentinel(n: int) -> Packet:
    into = Packet(n)
    into.f[:], into.i[:] = 7.0, 7
    return into


def test_the_layout_is_the_documented_one() -> None:
    for n, side in ((1, HSI), (2, TO), (7, HSI)):
        p = packet(n, tick=2**40 + 3)
        raw = bytes(encode_into(WireBuffer(n), p, SESSION_ID, -5, side, 2**39 + n))
        assert len(raw) == wire_size(n) == 72 + 56 * n
        assert raw == struct_layout(p, SESSION_ID, -5, side, 2**39 + n)
        # a sender that numbers nothing: every tick sent from tick 0, the number its tick
        assert bytes(encode_into(WireBuffer(n), p, SESSION_ID, -5, side)) == struct_layout(
            p, SESSION_ID, -5, side, p.tick
        )  # fmt: skip


finite = st.floats(allow_nan=False, allow_infinity=False, min_value=-1e6, max_value=1e6)
non_negative = st.floats(allow_nan=False, allow_infinity=False, min_value=0.0, max_value=1e12)


@settings(max_examples=300, deadline=None)
@given(
    n=st.integers(1, 7),
    data=st.data(),
    tick=st.integers(0, 2**63 - 1),
    session=st.integers(0, 2**64 - 1),
    time_ns=st.integers(-(2**63), 2**63 - 1),
)
def test_valid_packets_round_trip_bit_for_bit(n, data, tick, session, time_ns) -> None:
    # x, wave, the integrals; then the cumulative energies
    signed = data.draw(st.lists(finite, min_size=4 * n, max_size=4 * n))
    cumulative = data.draw(st.lists(non_negative, min_size=3 * n, max_size=3 * n))
    values = np.array([*signed, *cumulative, data.draw(finite)])
    p = packet(n, tick, values)
    p.engaged = data.draw(st.sampled_from((0, 1)))
    raw = bytes(encode_into(WireBuffer(n), p, session, time_ns, SENDER))
    decoder, into = Decoder(n, SENDER), sentinel(n)
    assert decoder.decode(raw, session, into) == OK
    assert np.array_equal(into.f.view(np.int64), p.f.view(np.int64))  # -0.0 and all
    assert np.array_equal(into.i, p.i)
    assert decoder.sender_time_ns == time_ns and decoder.seen_tick == tick


@settings(max_examples=500, deadline=None)
@given(raw=st.binary(max_size=400))
def test_random_bytes_are_rejected_counted_and_never_written(raw) -> None:
    decoder, into = Decoder(2, SENDER), sentinel(2)
    status = decoder.decode(raw, SESSION_ID, into)
    assert status != OK and untouched(into)
    assert decoder.counts.sum() == 1 and decoder.counts[status] == 1


@settings(max_examples=300, deadline=None)
@given(body=st.binary(min_size=wire_size(2) - 8, max_size=wire_size(2) - 8))
def test_random_bytes_of_the_right_size_with_a_valid_crc_never_raise(body) -> None:
    """Past the CRC: the header and values of random bytes are still checked."""
    decoder, into = Decoder(2, SENDER), sentinel(2)
    raw = b"TRWV\x05\x01\x02\x00" + body[8:]
    status = decoder.decode(reseal(raw + bytes(8)), SESSION_ID, into)
    assert status in (SESSION, NON_FINITE, IMPLAUSIBLE, OK)
    assert status == OK or untouched(into)


@settings(max_examples=200, deadline=None)
@given(cut=st.integers(0, wire_size(3) - 1), extra=st.binary(min_size=1, max_size=16))
def test_truncated_or_extended_packets_are_the_wrong_size(cut, extra) -> None:
    raw = encoded(packet(3))
    decoder, into = Decoder(3, SENDER), sentinel(3)
    assert decoder.decode(raw[:cut], SESSION_ID, into) == SIZE
    assert decoder.decode(raw + extra, SESSION_ID, into) == SIZE
    assert untouched(into) and decoder.counts[SIZE] == 2


@settings(max_examples=500, deadline=None)
@given(data=st.data())
def test_any_one_to_three_bit_flips_are_caught(data) -> None:
    """CRC-32 detects every error of up to three bits in a packet this short."""
    raw = bytearray(encoded(packet(2)))
    bits = data.draw(st.sets(st.integers(0, 8 * len(raw) - 1), min_size=1, max_size=3))
    for b in bits:
        raw[b // 8] ^= 1 << (b % 8)
    decoder, into = Decoder(2, SENDER), sentinel(2)
    status = decoder.decode(bytes(raw), SESSION_ID, into)
    assert status in (MAGIC_VERSION, CHECKSUM) and untouched(into)


def test_each_reason_is_counted_under_its_own_name() -> None:
    n = 2
    decoder = Decoder(n, SENDER, WireBounds(x=[1.0, 2.0], wave=3.0, energy=10.0))
    into = sentinel(n)
    # x, wave, wave integral, x integral, wave energy, E_in, E_out (per joint), energy crossed
    good_values = np.array(
        [0.5, 1.5, 2.0, -2.0, -9.0, 9.0, 8.0, -8.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, -1.0]
    )
    p = packet(n, values=good_values)

    def case(raw: bytes, status: int) -> None:
        assert decoder.decode(raw, SESSION_ID, into) == status, wire.REASONS[status]
        assert untouched(into)

    def with_value(k: int, value: float) -> bytes:
        q = packet(n, values=good_values.copy())
        q.f[k] = value
        return encoded(q)

    good = encoded(p)
    case(good[:-1], SIZE)
    case(b"XRWV" + good[4:], MAGIC_VERSION)
    case(reseal(good[:4] + bytes([4]) + good[5:]), MAGIC_VERSION)  # version 4: no number
    case(reseal(good[:4] + bytes([3]) + good[5:]), MAGIC_VERSION)  # version 3: no engaged
    case(reseal(good[:4] + bytes([2]) + good[5:]), MAGIC_VERSION)  # version 2: no side
    case(reseal(good[:4] + struct.pack("<H", 1) + good[6:]), MAGIC_VERSION)  # version 1
    case(good[:-8] + bytes([good[-8] ^ 1]) + good[-7:], CHECKSUM)
    case(reseal(good[:6] + struct.pack("<H", 3) + good[8:]), JOINTS)
    case(encoded(p, session=SESSION_ID - 1), SESSION)
    case(encoded(p, side=1 - SENDER), SIDE)  # the receiver's own packet, reflected back
    for k, bad in ((0, np.nan), (3, np.inf), (5, np.nan), (7, np.nan), (10, -np.inf),
                   (14, np.nan)):  # fmt: skip
        case(with_value(k, bad), NON_FINITE)
    # x per joint, wave, the integrals, energy crossed: against their bounds
    for k, big in ((0, 1.01), (1, -2.01), (2, 3.5), (4, -10.5), (7, -10.5), (14, 10.5)):
        case(with_value(k, big), IMPLAUSIBLE)
    for k, bad in ((8, -1e-9), (11, 11.0), (13, -1.0)):  # cumulative energies >= 0; bounded
        case(with_value(k, bad), IMPLAUSIBLE)
    for flag in (2, 1 << 32, 2**64 - 1):  # engaged: 0 or 1, nothing else (a damaged flag)
        case(reseal(good[:-16] + struct.pack("<Q", flag) + good[-8:]), IMPLAUSIBLE)
    q = packet(n, values=good_values.copy())
    q.seq = -1  # 2**64 - 1 on the wire
    case(encoded(q), IMPLAUSIBLE)
    # the packet's number: in [0, tick] (at most one packet a tick from tick 0)
    case(encoded(p, number=p.tick + 1), IMPLAUSIBLE)
    case(encoded(p, number=2**64 - 1), IMPLAUSIBLE)  # (-1 as the kernels read it)
    ahead = packet(n, tick=p.tick, values=good_values.copy())
    ahead.seq = p.tick + 1000  # a forged jump of the sequence: beyond what can play
    assert decoder.decode(encoded(ahead), SESSION_ID, into, newest=p.tick + 50) == AHEAD
    ahead = packet(n, tick=p.tick + 51, values=good_values.copy())  # or of the tick
    assert decoder.decode(encoded(ahead), SESSION_ID, into, newest=p.tick + 50) == AHEAD
    assert untouched(into) and decoder.used_seq == -1 and decoder.seen_tick == 0
    decoder.used_seq = p.seq
    case(good, STALE)
    older = packet(n, tick=p.seq - 1, values=good_values.copy())
    case(encoded(older), STALE)
    newer = packet(n, tick=p.seq + 1, values=good_values.copy())
    assert decoder.decode(encoded(newer), SESSION_ID, into) == OK
    assert decoder.counts_by_reason() == {
        "ok": 1, "size": 1, "magic_version": 5, "checksum": 1, "joints": 1, "session": 1,
        "side": 1, "non_finite": 6, "implausible": 15, "ahead": 2, "stale": 2,
    }  # fmt: skip
    assert decoder.rejected == 35


def test_the_bounds_must_be_positive_and_finite() -> None:
    for bounds in (WireBounds(x=0.0), WireBounds(wave=[1.0, np.inf]), WireBounds(energy=-1)):
        with pytest.raises(ValueError, match="wire bound"):
            Decoder(2, SENDER, bounds)


def test_encode_and_decode_allocate_nothing_they_keep() -> None:
    n = 2
    buffer, p = WireBuffer(n), packet(n)
    decoder, into = Decoder(n, SENDER), Packet(n)

    def one() -> None:
        p.seq += 1
        encode_into(buffer, p, SESSION_ID, 1, SENDER)
        decoder.decode(buffer.data, SESSION_ID, into, p.seq)

    for _ in range(100):
        one()
    assert net_blocks(one, 10_000) < 100
    assert decoder.counts[OK] == 10_100


def test_a_decoder_binds_no_encoder() -> None:
    """A decoder's buffer only holds what arrived: a process that only decodes (a packet of the
    independent struct writer, accepted) never loads the encoder, which a bound one did
    (0.2-0.8 s from the on-disk cache on this host); encoding into it is one clear error."""
    if not hasattr(wire._encode, "overloads"):
        pytest.skip("NUMBA_DISABLE_JIT: no kernel to load")
    raw = struct_layout(packet(2), 7, 0, SENDER, 3).hex()
    code = ("import sys; from teleop_rt.com import wire; from teleop_rt.com.port import Packet\n"
            f"d = wire.Decoder(2, {SENDER}); status = d.decode(bytes.fromhex('{raw}'), 7, "
            "Packet(2))\nprint(status, len(wire._encode.overloads))")  # fmt: skip
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                         timeout=600)  # fmt: skip
    assert out.stdout.split() == [str(OK), "0"], out.stderr
    with pytest.raises(ValueError, match="this wire buffer is a decoder's"):
        encode_into(Decoder(2, SENDER)._rx, packet(2), 7, 0, SENDER)
