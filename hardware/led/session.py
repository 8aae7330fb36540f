"""One emulated capture session: emulator up, program uploaded through the real client,
armed, started, triggered once per camera exposure, stopped, log read back."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

from hardware.led import protocol as p
from hardware.led.client import ControllerInfo, LedController
from hardware.led.emulator import Faults, LedEmulator


@dataclass(frozen=True)
class EmulatedSession:
    """What a session leaves behind.

    Attributes:
        log: the controller's log as read back over the serial link (one entry per
            trigger pulse it acted on; missed pulses have none).
        lit_per_pulse: what the bars actually showed at each trigger pulse, in trigger
            order (None when the controller missed the pulse or the program had ended).
            This is the virtual studio's ground truth, not something a real rig knows.
        program_crc32: checksum of the armed program.
        controller: firmware identification.
    """

    log: list[p.LogEntry]
    lit_per_pulse: list[p.Light]
    program_crc32: str
    controller: ControllerInfo


def run_emulated_session(pattern: Sequence[p.Light], n_frames: int,
                         intensities: Sequence[float] | None = None, faults: Faults | None = None,
                         n_bars: int | None = None, trigger_times_s: Sequence[float] | None = None,
                         timeout_s: float = 0.5, retries: int = 3) -> EmulatedSession:
    """Run a capture's light sequence on the emulated controller.

    Args:
        pattern: one cycle of lights (``"F"`` or bar ids), e.g. ``sequence.json["pattern"]``.
        n_frames: trigger pulses to fire (camera exposures).
        intensities: per-bar intensity 0..1 (bar id order), or None to leave them at 1.
        faults: faults to inject (link faults are absorbed by the client's retries; an
            unplug raises ``DeviceGone``).
        n_bars: bars on the board; defaults to ``len(intensities)`` or the largest bar id + 1.
        trigger_times_s: time stamp of each pulse (logged in microseconds), default none.
        timeout_s, retries: the client's reply timeout and resends.

    Returns:
        The controller's log and the lights shown at each pulse.
    """
    if n_frames < 0:
        raise ValueError(f"n_frames must be >= 0, got {n_frames}")
    if trigger_times_s is not None and len(trigger_times_s) != n_frames:
        raise ValueError(f"{len(trigger_times_s)} trigger times for {n_frames} frames")
    bar_ids = [s for s in pattern if s != p.FULL_ON]
    if n_bars is None:
        n_bars = len(intensities) if intensities is not None else (max(bar_ids) + 1 if bar_ids else 1)
    repeat = max(1, math.ceil(n_frames / max(1, len(pattern))))
    with LedEmulator(n_bars=n_bars, faults=faults) as emulator, \
            LedController(emulator.port, timeout_s=timeout_s, retries=retries) as controller:
        info = controller.version()
        controller.reset()
        if intensities is not None:
            controller.set_intensities(intensities)
        crc = controller.upload(pattern, repeat)
        controller.arm(crc)
        controller.clear_log()
        controller.start()
        for i in range(n_frames):
            emulator.pulse(None if trigger_times_s is None else float(trigger_times_s[i]))
        controller.stop()
        log = controller.read_log()
        return EmulatedSession(log, list(emulator.trigger_lights), crc, info)
