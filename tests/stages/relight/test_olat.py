"""``pipeline render --olat-basis``: a compositor rebuilds ``pipeline render --envmap``'s frames from the
written multi-part EXR and its JSON alone (read with OpenEXR; the map integrated with the JSON's rules,
none of this project's code)."""

from __future__ import annotations

import json
import math
import shutil

import numpy as np
import OpenEXR
import pytest

from stages.relight.cli import main
from stages.relight.params import ASSETS
from tests.stages.relight.test_stage import inputs  # noqa: F401  (fixture)

COUNT = 40
SIZE = ["--width", "16", "--height", "20"]


@pytest.fixture(scope="module")
def workspace(tmp_path_factory, inputs):  # noqa: F811
    """A workspace whose train/track/capture refs point at the tiny head's folders."""
    root = tmp_path_factory.mktemp("olat_ws")
    ws = root / "alice"
    (ws / "refs").mkdir(parents=True)
    for stage, folder in inputs.items():
        shutil.copytree(folder, ws / "objects" / f"digest_{stage}")
        (ws / "refs" / f"{stage}.json").write_text(json.dumps(
            {"stage": stage, "action": "a", "outputs": {"out": f"digest_{stage}"}, "updated": ""}))
    return root


def _read_layers(path):
    """Per part (file order): name, RGB [H, W, 3], alpha [H, W], header; with OpenEXR only."""
    layers = []
    with OpenEXR.File(str(path), separate_channels=True) as exr:
        for part in exr.parts:
            name = part.name()
            ch = {k.split(".")[-1]: np.asarray(v.pixels, np.float64) for k, v in part.channels.items()}
            layers.append((name, np.stack([ch["R"], ch["G"], ch["B"]], -1), ch["A"], dict(part.header)))
    return layers


def _read_rgba(path):
    with OpenEXR.File(str(path), separate_channels=True) as exr:
        ch = {k: np.asarray(v.pixels, np.float64) for k, v in exr.channels().items()}
    return np.stack([ch["R"], ch["G"], ch["B"]], -1), ch.get("A")


def _weights(radiance: np.ndarray, spec: dict) -> np.ndarray:
    """The layers' weights for a lat-long map, from the JSON's description alone."""
    h, w, _ = radiance.shape
    theta = math.pi * (0.5 - (np.arange(h) + 0.5) / h)
    phi = 2 * math.pi * (0.5 - (np.arange(w) + 0.5) / w)
    d = np.stack([np.sin(phi)[None] * np.cos(theta)[:, None], np.broadcast_to(np.sin(theta)[:, None], (h, w)),
                  np.cos(phi)[None] * np.cos(theta)[:, None]], -1)  # [H, W, 3]
    edges = math.pi * (0.5 - np.arange(h + 1) / h)
    solid = (2 * math.pi / w) * (np.sin(edges[:-1]) - np.sin(edges[1:]))  # [H]
    rules = spec["pipeline_render_envmap"]
    mask = rules["back_mask"]
    back = np.clip(-d[..., 2], 0.0, 1.0)
    attenuation = np.cos(np.arcsin(back)) ** mask["attenuation_power"]
    attenuation[-d[..., 2] > math.cos(math.radians(mask["cone_half_angle_deg"]))] = 0.0
    energy = radiance * (solid[:, None] * attenuation)[..., None]  # [H, W, 3]
    directions = np.asarray(spec["directions_head"])
    nearest = np.argmax(d.reshape(-1, 3) @ directions.T, axis=1)  # each pixel's cell
    weights = np.stack([np.bincount(nearest, energy.reshape(-1, 3)[:, c], minlength=len(directions))
                        for c in range(3)], -1)
    lum = weights @ np.array([0.2126, 0.7152, 0.0722])
    lit = np.flatnonzero(lum > 0)
    dropped = lit[np.argsort(lum[lit], kind="stable")[:int(math.floor(rules["drop_fraction"] * len(lit)))]]
    weights[dropped] = 0.0
    return weights * rules["envmap_scale"]


def test_olat_layers_rebuild_the_envmap_render(workspace, tmp_path, capsys):
    olat_out, env_out = tmp_path / "olat", tmp_path / "env"
    code = main(["-S", "alice", "--workspaces", str(workspace), "--olat-basis", str(COUNT), *SIZE,
                 "--out", str(olat_out)])
    assert code == 0, capsys.readouterr().err
    envmap = ASSETS / "blender-cc0/sunrise.exr"
    code = main(["-S", "alice", "--workspaces", str(workspace), "--envmap", str(envmap), "--directions", str(COUNT),
                 "--frames", "2", "--rotate-deg-per-frame", "90", *SIZE, "--out", str(env_out)])
    assert code == 0, capsys.readouterr().err
    assert not (olat_out / "turntable").exists()  # the OLAT alone was asked for

    spec = json.loads((olat_out / "olat" / f"olat_{COUNT}dirs.json").read_text())
    layers = _read_layers(olat_out / "olat" / f"olat_{COUNT}dirs.exr")
    assert [name for name, *_ in layers] == [layer["part"] for layer in spec["layers"]]
    assert len(layers) == COUNT and abs(sum(spec["solid_angles_sr"]) - 4 * math.pi) < 1e-9
    for (name, _, alpha, header), layer in zip(layers, spec["layers"]):
        assert header["olatIndex"] == layer["index"]
        np.testing.assert_allclose(header["olatDirection"], layer["direction_head"], atol=1e-6)
        np.testing.assert_array_equal(alpha, layers[0][2])  # opacity does not depend on the light
    rgb = np.stack([layer[1] for layer in layers])  # [D, H, W, 3]

    radiance, _ = _read_rgba(envmap)
    for frame, turn_columns in ((0, 0), (1, radiance.shape[1] // 4)):  # 90 degrees: a quarter of the columns
        weights = _weights(np.roll(radiance, -turn_columns, axis=1), spec)
        rebuilt = np.einsum("dc,dhwc->hwc", weights, rgb)
        reference, ref_alpha = _read_rgba(env_out / "envmap_sunrise" / "frames" / f"{frame:06d}.exr")
        assert float(reference.max()) > 0.0 and float(np.abs(rebuilt - reference).max()) > 0.0
        # Both files are half floats (relative rounding 2^-11 each, every term non-negative), so the two
        # agree to within twice that per pixel; the renders themselves agree to ~1e-6.
        np.testing.assert_allclose(rebuilt, reference, rtol=2.5 * 2.0 ** -11, atol=1e-6 * float(reference.max()))
        np.testing.assert_allclose(layers[0][2], ref_alpha, atol=2.0 ** -10)
    # The frames really differ (the map turned), so the rebuild had to follow the rotation.
    assert float(np.abs(_read_rgba(env_out / "envmap_sunrise/frames/000001.exr")[0]
                        - _read_rgba(env_out / "envmap_sunrise/frames/000000.exr")[0]).max()) > 1e-3


def test_olat_float_layers_and_one_set_per_camera(workspace, tmp_path, capsys):
    out = tmp_path / "o"
    code = main(["-S", "alice", "--workspaces", str(workspace), "--olat-basis", "6", "--olat-float",
                 "--camera", "0.2,0.0,0.8", "--camera=-0.2,0.1,0.8", *SIZE, "--out", str(out)])
    assert code == 0, capsys.readouterr().err
    for k in (0, 1):
        layers = _read_layers(out / "olat" / f"olat_6dirs_view{k}.exr")
        spec = json.loads((out / "olat" / f"olat_6dirs_view{k}.json").read_text())
        assert len(layers) == 6 and spec["pixel_type"] == "float"
        with OpenEXR.File(str(out / "olat" / f"olat_6dirs_view{k}.exr"), separate_channels=True) as exr:
            assert exr.parts[0].channels["dir000.R"].pixels.dtype == np.float32
    views = [json.loads((out / "olat" / f"olat_6dirs_view{k}.json").read_text())["camera"] for k in (0, 1)]
    assert views[0]["cam_from_head"] != views[1]["cam_from_head"]
    assert not (out / "views").exists()  # --camera chose the OLAT views, no key-light sequence


def test_bad_olat_count_is_a_usage_error(capsys, tmp_path):
    assert main(["-S", "nobody", "--olat-basis", "-3", "--workspaces", str(tmp_path)]) == 2
    assert "--olat-basis" in capsys.readouterr().err
