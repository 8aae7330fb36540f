"""scene.image_io and scene.colour: round trips and clear errors on bad files."""

import numpy as np
import pytest

from scene.colour import srgb_decode, srgb_encode
from scene.exr_layers import write_multipart_exr
from scene.image_io import read_exr, read_png, read_png16, write_exr, write_png16, write_png_srgb


@pytest.mark.parametrize("half,tol", [(True, 2e-3), (False, 0.0)])
def test_exr_round_trip_rgb(tmp_path, half, tol):
    img = np.random.default_rng(0).uniform(0, 4, size=(7, 5, 3)).astype(np.float32)
    write_exr(tmp_path / "a.exr", img, half=half)
    back = read_exr(tmp_path / "a.exr")
    assert back.shape == (7, 5, 3) and back.dtype == np.float32
    np.testing.assert_allclose(back, img, rtol=tol, atol=tol)


def test_exr_channel_layouts(tmp_path):
    rgba = np.random.default_rng(1).uniform(0, 1, size=(4, 6, 4)).astype(np.float32)
    write_exr(tmp_path / "rgba.exr", rgba, half=False)
    np.testing.assert_array_equal(read_exr(tmp_path / "rgba.exr"), rgba)  # order R, G, B, A kept
    write_exr(tmp_path / "grey.exr", rgba[..., 0], half=False)
    assert read_exr(tmp_path / "grey.exr").shape == (4, 6, 1)


def test_exr_half_clips_instead_of_inf(tmp_path):
    write_exr(tmp_path / "hot.exr", np.full((2, 2, 3), 1e6, np.float32))
    assert np.isfinite(read_exr(tmp_path / "hot.exr")).all()


def test_truncated_and_missing_exr_name_the_file(tmp_path):
    write_exr(tmp_path / "ok.exr", np.ones((16, 16, 3), np.float32))
    data = (tmp_path / "ok.exr").read_bytes()
    (tmp_path / "cut.exr").write_bytes(data[: len(data) // 3])
    with pytest.raises(ValueError, match="cut.exr"):
        read_exr(tmp_path / "cut.exr")
    with pytest.raises(ValueError, match="nothere.exr"):
        read_exr(tmp_path / "nothere.exr")
    (tmp_path / "junk.png").write_bytes(b"not a png")
    with pytest.raises(ValueError, match="junk.png"):
        read_png(tmp_path / "junk.png")


def test_png16_matte_round_trip(tmp_path):
    alpha = np.linspace(0, 1, 64, dtype=np.float32).reshape(8, 8)
    write_png16(tmp_path / "m.png", alpha)
    back = read_png16(tmp_path / "m.png")
    assert back.shape == (8, 8)
    assert np.abs(back - alpha).max() < 1.0 / 65535 + 1e-7


def test_srgb_png_and_transfer_functions(tmp_path):
    x = np.linspace(0, 1, 101, dtype=np.float32)
    np.testing.assert_allclose(srgb_decode(srgb_encode(x)), x, atol=1e-5)
    assert abs(float(srgb_encode(np.float32(0.5))) - 0.7354) < 1e-3  # known sRGB value
    lin = np.random.default_rng(2).uniform(0, 1, size=(5, 4, 3)).astype(np.float32)
    write_png_srgb(tmp_path / "p.png", lin)
    back = read_png(tmp_path / "p.png", linear=True)
    assert back.shape == (5, 4, 3)
    np.testing.assert_allclose(back, lin, atol=0.01)  # 8-bit quantisation in sRGB


def test_multipart_exr_keeps_each_part_its_name_channels_and_attributes(tmp_path):
    import OpenEXR

    rng = np.random.default_rng(0)
    images = [rng.uniform(0, 4, (5, 7, 4)).astype(np.float32), rng.uniform(0, 4, (5, 7, 3)).astype(np.float32)]
    parts = [("dir000", images[0], {"olatIndex": 0, "olatDirection": np.array([0, 0, 1], np.float32),
                                    "olatSolidAngleSr": 0.25}),
             ("dir001", images[1], {"olatIndex": 1})]
    write_multipart_exr(tmp_path / "m.exr", parts, half=False)
    with OpenEXR.File(str(tmp_path / "m.exr"), separate_channels=True) as exr:
        assert [p.name() for p in exr.parts] == ["dir000", "dir001"]
        assert set(exr.parts[0].channels) == {"dir000.R", "dir000.G", "dir000.B", "dir000.A"}
        np.testing.assert_array_equal(exr.parts[0].channels["dir000.A"].pixels, images[0][..., 3])
        np.testing.assert_array_equal(exr.parts[1].channels["dir001.G"].pixels, images[1][..., 1])
        assert exr.parts[0].header["olatSolidAngleSr"] == 0.25 and exr.parts[1].header["olatIndex"] == 1
        np.testing.assert_array_equal(exr.parts[0].header["olatDirection"], [0, 0, 1])
    write_multipart_exr(tmp_path / "h.exr", parts[:1])  # half by default
    with OpenEXR.File(str(tmp_path / "h.exr"), separate_channels=True) as exr:
        assert exr.parts[0].channels["dir000.R"].pixels.dtype == np.float16
    with pytest.raises(ValueError, match="dir9"):
        write_multipart_exr(tmp_path / "bad.exr", [("dir9", np.zeros((2, 2)), {})])
