"""LED-bar controller: a client over pyserial, its line protocol, and an emulator on a pty.

The protocol is documented in ``hardware/led/PROTOCOL.md``. Pieces:

- ``LedController(port, timeout_s, retries)``: the client (``client.py``). ``port`` is a
  device path (``/dev/ttyUSB0``) or a pyserial URL. Errors are typed (``errors.py``):
  ``ControllerTimeout``, ``CorruptReply``, ``DeviceGone``, ``CommandRejected``,
  ``ProgramMismatch``, all subclasses of ``ControllerError``; no call blocks longer than
  about ``(retries + 1) * timeout_s``.
- ``LedEmulator(n_bars, faults)``: the firmware (``firmware.py``) served on a pty; its
  ``port`` is the slave path the client opens; ``pulse(time_s)`` is the camera trigger.
- ``run_emulated_session``: a whole capture's light sequence in one call.

Usage from the capture stage (virtual studio)::

    from hardware.led import Faults, run_emulated_session

    session = run_emulated_session(
        pattern=sequence["pattern"],          # one cycle, e.g. ["F", 12, 3, "F", 30, 7, ...]
        n_frames=n_frames,                    # camera exposures = trigger pulses
        intensities=bar_intensities,          # per bar id, 0..1 (optional)
        faults=Faults(drop_pulses=frozenset({17})),   # optional: controller misses pulse 17
        trigger_times_s=[i / fps for i in range(n_frames)],
    )
    session.lit_per_pulse   # [n_frames] what lit each exposure ("F", bar id, None = dark): render with it
    session.log             # the controller's log (LogEntry: pulse, cycle, step, light, time_us);
                            # write [e.to_json() for e in session.log] to controller_log.json
    # then label the received frames with stages.capture.labelling.label_frames(
    #     [e.light for e in session.log], brightness_per_camera, ...), where
    #     brightness_per_camera[c] is [R_c, 4]: the linear means of the 2x2 image quadrants of
    #     every frame camera c delivered (image means [R_c] work too, less robustly)

To drive the studio's trigger yourself (e.g. render as each pulse fires), use the pieces::

    with LedEmulator(n_bars=32) as emulator, LedController(emulator.port) as controller:
        crc = controller.upload(pattern, repeat=cycles)
        controller.arm(crc)
        controller.start()
        light = emulator.pulse(time_s)   # per exposure
        controller.stop()
        log = controller.read_log()
"""

from hardware.led.client import ControllerInfo, ControllerStatus, LedController
from hardware.led.emulator import Faults, LedEmulator
from hardware.led.errors import (CommandRejected, ControllerError, ControllerTimeout, CorruptReply,
                                 DeviceGone, ProgramMismatch)
from hardware.led.protocol import FULL_ON, Light, LogEntry, program_crc32
from hardware.led.session import EmulatedSession, run_emulated_session

__all__ = [
    "CommandRejected", "ControllerError", "ControllerInfo", "ControllerStatus", "ControllerTimeout",
    "CorruptReply", "DeviceGone", "EmulatedSession", "FULL_ON", "Faults", "LedController",
    "LedEmulator", "Light", "LogEntry", "ProgramMismatch", "program_crc32", "run_emulated_session",
]
