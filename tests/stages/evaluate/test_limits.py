"""The warning zone: limits.json round trip and the light check a renderer calls."""

from __future__ import annotations

import numpy as np
import pytest

from stages.evaluate.limits import LightLimits, light_warning, read_limits, write_limits


def _limits(censored: bool = False) -> LightLimits:
    fan = np.radians(np.linspace(-60, 60, 5))
    dirs = tuple(tuple(float(v) for v in (np.sin(a), 0.0, np.cos(a))) for a in fan)
    return LightLimits(20.0, censored, 25.0, (0.0, 0.0, 0.05), dirs)


def test_round_trip(tmp_path):
    write_limits(tmp_path / "limits.json", _limits(), {"expression_scale_limit_high": 1.6})
    back = read_limits(tmp_path / "limits.json")
    assert back == _limits()


def test_lights_inside_the_limit_pass_and_beyond_it_warn():
    limits = _limits()
    centre = np.array(limits.centre_head)
    assert light_warning(centre + [0.0, 0.0, 3.0], limits) is None  # a training direction
    a = np.radians(75.0)  # 15 degrees past the fan's edge
    assert light_warning(centre + 3.0 * np.array([np.sin(a), 0.0, np.cos(a)]), limits) is None
    message = light_warning(centre + [0.0, 0.0, -3.0], limits, what="orbit frame 4")
    assert message is not None and "orbit frame 4" in message and "120 degrees" in message and "20" in message
    b = np.radians(85.0)  # 25 degrees past: beyond the 20 degree limit
    assert light_warning(centre + 3.0 * np.array([np.sin(b), 0.0, np.cos(b)]), limits) is not None


def test_a_censored_limit_never_warns():
    assert light_warning(np.array([0.0, 0.0, -3.0]), _limits(censored=True)) is None


def test_a_broken_file_names_itself_and_the_fix(tmp_path):
    path = tmp_path / "limits.json"
    path.write_text('{"light_extrapolation_limit_deg": 20}')
    with pytest.raises(ValueError, match="limits.json.*evaluate"):
        read_limits(path)


def test_requested_lights_and_orbits_are_checked(tmp_path):
    from stages.evaluate.limits import requested_light_warnings

    path = tmp_path / "limits.json"
    write_limits(path, _limits())
    assert requested_light_warnings(tmp_path / "missing.json", [[0.0, 0.0, -3.0]]) == []
    messages = requested_light_warnings(path, [[0.0, 0.0, 3.0], [0.0, 0.0, -3.0]], orbit_radius_m=3.0, orbit_frames=8)
    assert len(messages) == 2 and messages[0].startswith("point light 1")
    # An 8-frame orbit (45 degree steps, from the front): frames 3, 4, 5 are 75, 120, 75 degrees
    # from the +-60 degree fan, beyond the 20 degree limit; frame 2 (90 degrees) is 30 degrees off too.
    assert "frames [2, 3, 4, 5, 6]" in messages[1]


def test_workspace_without_an_evaluate_output_gives_no_warnings(tmp_path):
    from pipeline.workspace import Workspace
    from stages.evaluate.limits import workspace_light_warnings

    assert workspace_light_warnings(Workspace(tmp_path, "alice"), [[0.0, 0.0, -3.0]]) == []
