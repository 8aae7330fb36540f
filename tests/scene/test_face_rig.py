"""scene.face_rig: the ICT model in metres, triangulated, with blendshapes and landmarks."""

import numpy as np
import pytest

from scene.face_rig import load_face_rig


@pytest.fixture(scope="module")
def rig():
    return load_face_rig()


def test_dimensions_and_units(rig):
    assert rig.neutral_m.shape == (26719, 3)
    assert rig.expression_deltas_m.shape == (57, 26719, 3)
    assert rig.identity_deltas_m.shape == (20, 26719, 3)
    face = rig.neutral_m[rig.regions["face"].vertex_slice]
    width_m = face[:, 0].max() - face[:, 0].min()
    assert 0.12 < width_m < 0.25  # a face is ~15-20 cm wide: the pack's centimetres became metres
    # Head space: +x to the subject's left, +z out of the face.
    lm = rig.landmarks(rig.neutral_m)
    assert lm.shape == (68, 3)
    assert lm[45, 0] > lm[36, 0]  # left eye's outer corner (45) at +x, right eye's (36) at -x
    assert lm[30, 2] > lm[36, 2]  # nose tip in front of the eyes
    assert lm[8, 1] < lm[30, 1] < lm[27, 1]  # chin below nose tip below nose bridge


def test_triangulation_covers_every_polygon(rig):
    import numpy as np

    data = np.load(rig.path)
    quads = int((data["faces"][:, 3] >= 0).sum())
    assert len(rig.triangles) == len(data["faces"]) + quads
    assert rig.triangles.min() >= 0 and rig.triangles.max() < rig.num_vertices
    assert rig.triangles_uv.max() < len(rig.uv)
    # Regions are contiguous triangle ranges that tile the list.
    stops = sorted((r.triangle_start, r.triangle_stop) for r in rig.regions.values())
    assert stops[0][0] == 0 and stops[-1][1] == len(rig.triangles)
    assert all(a[1] == b[0] for a, b in zip(stops, stops[1:]))


def test_blending_is_linear(rig):
    rng = np.random.default_rng(0)
    ident = rng.normal(size=20).astype(np.float32)
    w = np.zeros(57, np.float32)
    jaw = rig.expression_index("jawOpen")
    w[jaw] = 0.5
    base = rig.vertices(ident)
    half = rig.vertices(ident, w)
    w[jaw] = 1.0
    full = rig.vertices(ident, w)
    np.testing.assert_allclose(full - base, 2 * (half - base), atol=1e-6)
    chin = rig.landmark_vertex_ids[8]
    assert full[chin, 1] < base[chin, 1] - 0.01  # the jaw opens downwards by centimetres
    with pytest.raises(ValueError):
        rig.vertices(ident, np.zeros(3))
    with pytest.raises(KeyError, match="jawOpen"):
        rig.expression_index("nope")
