"""A whole emulated capture session through the real client."""

from __future__ import annotations

import pytest

from hardware.led import DeviceGone, Faults, run_emulated_session

pytestmark = pytest.mark.timeout(30)

PATTERN = ["F", 3, 0, "F", 2, 1]


def test_session_lights_follow_the_pattern_and_the_log_matches() -> None:
    times = [i / 24 for i in range(14)]
    session = run_emulated_session(PATTERN, 14, intensities=[0.9, 1.0, 0.8, 0.7], trigger_times_s=times)
    assert session.lit_per_pulse == (PATTERN * 3)[:14]
    assert [e.light for e in session.log] == session.lit_per_pulse
    assert [e.pulse for e in session.log] == list(range(14))
    assert session.log[13].time_us == round(13 / 24 * 1e6)
    assert session.controller.bars == 4


def test_missed_pulses_are_dark_and_absent_from_the_log() -> None:
    session = run_emulated_session(PATTERN, 8, n_bars=4, faults=Faults(drop_pulses=frozenset({2})))
    assert session.lit_per_pulse == ["F", 3, None, 0, "F", 2, 1, "F"]
    assert [e.light for e in session.log] == ["F", 3, 0, "F", 2, 1, "F"]


def test_link_noise_is_absorbed_by_retries() -> None:
    faults = Faults(corrupt_rate=0.2, seed=3)
    session = run_emulated_session(PATTERN, 30, n_bars=4, faults=faults, timeout_s=0.3, retries=6)
    assert [e.light for e in session.log] == (PATTERN * 5)[:30]


def test_unplugged_controller_raises() -> None:
    with pytest.raises(DeviceGone):
        run_emulated_session(PATTERN, 8, n_bars=4, faults=Faults(unplug_after=4))
