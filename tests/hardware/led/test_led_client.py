"""The pyserial client against the pty emulator: every command, and bounded failures."""

from __future__ import annotations

import time

import pytest

from hardware.led import (CommandRejected, ControllerTimeout, CorruptReply, DeviceGone, Faults, LedController,
                          LedEmulator, ProgramMismatch, program_crc32)
from hardware.led.firmware import FIRMWARE_NAME
from hardware.led.protocol import LOG_CHUNK_ENTRIES, PROGRAM_CHUNK_STEPS

pytestmark = pytest.mark.timeout(30)

PATTERN = ["F"] + [b for pair in zip(range(0, 32, 2), range(1, 32, 2)) for b in (*pair, "F")][:-1]


@pytest.fixture
def emulator():
    with LedEmulator(n_bars=32) as emu:
        yield emu


def test_every_command_agrees_with_the_firmware(emulator: LedEmulator) -> None:
    fw = emulator.firmware
    with LedController(emulator.port, timeout_s=0.5, retries=1) as ctl:
        assert ctl.ping() < 0.5
        info = ctl.version()
        assert (info.firmware, info.protocol, info.bars) == (FIRMWARE_NAME, 1, 32)
        assert ctl.status().state == "IDLE"

        assert len(PATTERN) > PROGRAM_CHUNK_STEPS  # the upload is chunked
        crc = ctl.upload(PATTERN, repeat=3)
        assert crc == program_crc32(PATTERN, 3)
        assert fw.program.steps == PATTERN and fw.program.repeat == 3
        assert ctl.read_program() == (PATTERN, 3)
        assert ctl.verify_program(PATTERN, 3) == crc
        with pytest.raises(ProgramMismatch):
            ctl.verify_program(PATTERN[::-1], 3)

        ctl.set_intensity("ALL", 0.25)
        assert fw.intensities == [0.25] * 32
        ctl.set_intensities([0.5 + 0.01 * b for b in range(32)])
        assert ctl.intensities(32) == pytest.approx([0.5 + 0.01 * b for b in range(32)])
        assert fw.intensities[31] == pytest.approx(0.81)

        with pytest.raises(CommandRejected) as refused:
            ctl.arm("deadbeef")
        assert refused.value.code == "E04" and "checksum" in str(refused.value)
        ctl.arm(crc)
        status = ctl.status()
        assert (status.state, status.steps, status.repeat, status.crc32) == ("ARMED", len(PATTERN), 3, crc)

        ctl.start()
        assert ctl.status().state == "RUNNING"
        with pytest.raises(CommandRejected):
            ctl.upload(PATTERN, 1)  # not while running
        ctl.trigger(5)
        lights = [emulator.pulse(time_s=i / 24) for i in range(LOG_CHUNK_ENTRIES * 2)]
        assert ctl.status().lit == lights[-1]
        assert ctl.stop() == 5 + len(lights)
        log = ctl.read_log()  # several LOG READ chunks
        assert log == fw.log
        assert [e.light for e in log] == (PATTERN * 2)[:len(log)]
        assert log[5].time_us == 0 and log[6].time_us == round(1e6 / 24)
        ctl.clear_log()
        assert ctl.read_log() == []
        ctl.reset()
        assert ctl.status().state == "IDLE"


def test_corrupted_replies_are_retried(emulator: LedEmulator) -> None:
    faults = Faults(corrupt_replies=frozenset({0, 2, 3}))
    with LedEmulator(faults=faults) as emu, LedController(emu.port, timeout_s=0.3, retries=2) as ctl:
        ctl.ping()  # reply 0 corrupt, reply 1 fine
        ctl.version()  # replies 2 and 3 corrupt, reply 4 fine


def test_retried_trigger_runs_once() -> None:
    with LedEmulator(faults=Faults(corrupt_replies=frozenset({3}))) as emu, \
            LedController(emu.port, timeout_s=0.3, retries=2) as ctl:
        crc = ctl.upload(["F", 1], 0)  # replies 0, 1, 2
        ctl.arm(crc)  # reply 3 corrupt, replayed
        ctl.start()
        ctl.trigger(4)
        assert emu.firmware.pulses == 4


def test_always_corrupt_gives_corrupt_reply_quickly() -> None:
    with LedEmulator(faults=Faults(corrupt_rate=1.0)) as emu, \
            LedController(emu.port, timeout_s=0.5, retries=2) as ctl:
        start = time.monotonic()
        with pytest.raises(CorruptReply, match="PING.*3 attempts"):
            ctl.ping()
        assert time.monotonic() - start < 1.5


def test_silent_controller_gives_timeout_in_bounded_time(emulator: LedEmulator) -> None:
    with LedController(emulator.port, timeout_s=0.2, retries=2) as ctl:
        ctl.ping()
        emulator.set_silent(True)
        start = time.monotonic()
        with pytest.raises(ControllerTimeout, match="no reply within 0.2 s"):
            ctl.status()
        elapsed = time.monotonic() - start
        assert 0.55 < elapsed < 1.5  # three attempts of 0.2 s, no hang
        emulator.set_silent(False)
        ctl.ping()  # recovers


def test_silence_after_some_commands() -> None:
    with LedEmulator(faults=Faults(silent_after=2)) as emu, LedController(emu.port, timeout_s=0.2, retries=1) as ctl:
        ctl.ping()
        ctl.ping()
        with pytest.raises(ControllerTimeout):
            ctl.ping()


def test_unplugged_device_gives_device_gone_quickly(emulator: LedEmulator) -> None:
    with LedController(emulator.port, timeout_s=1.0, retries=3) as ctl:
        ctl.ping()
        emulator.unplug()
        start = time.monotonic()
        with pytest.raises(DeviceGone, match="device gone"):
            ctl.ping()
        assert time.monotonic() - start < 1.0  # no waiting out the timeout and retries
        with pytest.raises(DeviceGone):
            ctl.status()


def test_unplug_during_upload() -> None:
    with LedEmulator(faults=Faults(unplug_after=3)) as emu, LedController(emu.port, timeout_s=0.3, retries=2) as ctl:
        start = time.monotonic()
        with pytest.raises(DeviceGone):
            ctl.upload(PATTERN, 1)
        assert time.monotonic() - start < 1.0


def test_missing_port_gives_device_gone() -> None:
    with pytest.raises(DeviceGone, match="/dev/ttyNO_SUCH_PORT.*cannot open"):
        LedController("/dev/ttyNO_SUCH_PORT")
