"""Framing, checksums and the firmware state machine without any I/O."""

from __future__ import annotations

import zlib

import pytest

from hardware.led import protocol as p
from hardware.led.firmware import LedFirmware


def test_crc8_check_value() -> None:
    # The CRC-8/SMBUS catalogue check value.
    assert p.crc8(b"123456789") == 0xF4


def test_frame_round_trip_and_corruption() -> None:
    line = p.encode_frame(42, "PROG", ["DATA", 0, "F", 12, 3])
    assert line.endswith(b"\n") and b" *" in line
    frame = p.decode_frame(line)
    assert frame == p.Frame(42, "PROG", ("DATA", "0", "F", "12", "3"))
    damaged = line.replace(b"12", b"13")
    with pytest.raises(p.FrameError, match="checksum"):
        p.decode_frame(damaged)
    with pytest.raises(p.FrameError):
        p.decode_frame(b"42 PING\n")
    with pytest.raises(p.FrameError):
        p.encode_frame(1, "PROG", ["DATA"] + ["F"] * 200)


def test_program_checksum_is_crc32_of_canonical_text() -> None:
    steps = ["F", 3, 17]
    assert p.program_text(steps, 5) == b"5:F 3 17"
    assert p.program_crc32(steps, 5) == f"{zlib.crc32(b'5:F 3 17'):08x}"
    assert p.program_crc32(steps, 5) != p.program_crc32(steps, 4)
    with pytest.raises(ValueError):
        p.program_crc32(["X"], 1)


def test_log_entry_round_trip() -> None:
    entry = p.LogEntry(pulse=7, cycle=1, step=2, light=None, time_us=291667)
    assert p.LogEntry.parse(entry.token()) == entry
    assert entry.to_json()["light"] is None


def _ask(fw: LedFirmware, seq: int, word: str, *args: object) -> p.Frame:
    return p.decode_frame(fw.handle(p.encode_frame(seq, word, args)))


def test_firmware_runs_program_and_logs_pulses() -> None:
    fw = LedFirmware(n_bars=4)
    steps = ["F", 2, 0]
    assert _ask(fw, 1, "PROG", "BEGIN", 3, 2).word == "ACK"
    assert _ask(fw, 2, "PROG", "DATA", 0, *steps).word == "ACK"
    assert fw.pulse() is None  # not running: ignored
    assert _ask(fw, 3, "ARM", p.program_crc32(steps, 2)).args[0] == "ARMED"
    assert _ask(fw, 4, "START").word == "ACK"
    lights = [fw.pulse(time_s=i / 24) for i in range(8)]
    assert lights == ["F", 2, 0, "F", 2, 0, None, None]  # the program ran out after 2 cycles
    assert [e.light for e in fw.log] == lights
    assert fw.log[4] == p.LogEntry(4, 1, 1, 2, round(4 / 24 * 1e6))
    assert fw.ignored_pulses == 1


def test_firmware_refusals_and_replayed_retries() -> None:
    fw = LedFirmware(n_bars=4)
    assert _ask(fw, 1, "FOO").args[0] == p.ERR_UNKNOWN_COMMAND
    assert _ask(fw, 2, "START").args[0] == p.ERR_BAD_STATE
    assert _ask(fw, 3, "PROG", "BEGIN", 2, 1).word == "ACK"
    assert _ask(fw, 4, "ARM", "00000000").args[0] == p.ERR_PROGRAM_INCOMPLETE
    assert _ask(fw, 5, "PROG", "DATA", 0, "F", 9).args[0] == p.ERR_OUT_OF_RANGE  # bar 9 of 4
    assert _ask(fw, 6, "PROG", "DATA", 0, "F", 1).word == "ACK"
    assert _ask(fw, 7, "ARM", "00000000").args[0] == p.ERR_PROGRAM_CHECKSUM
    assert _ask(fw, 8, "INT", "SET", 1, "1.5").args[0] == p.ERR_OUT_OF_RANGE
    # A damaged request is NAKed with its sequence number.
    bad = p.encode_frame(9, "PING").replace(b"PING", b"PONG")
    assert p.decode_frame(fw.handle(bad)) == p.Frame(9, "NAK", ("CRC",))
    # A resent request (same seq, same bytes) is answered again without running twice.
    _ask(fw, 10, "ARM", p.program_crc32(["F", 1], 1))
    _ask(fw, 11, "START")
    first = fw.handle(p.encode_frame(12, "TRIG", [3]))
    again = fw.handle(p.encode_frame(12, "TRIG", [3]))
    assert first == again and fw.pulses == 3
