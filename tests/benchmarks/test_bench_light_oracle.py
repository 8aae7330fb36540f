"""The light-sampling ceiling's three predictions (``benchmarks.bench_light_oracle``)."""

import numpy as np

from benchmarks.bench_light_oracle import ORACLES, exposure_fit, oracle_predictions


def _basis(seed: int = 0, lights: int = 6) -> np.ndarray:
    return np.random.default_rng(seed).uniform(0.0, 1.0, (lights, 10, 12, 3))  # 2 x 2 tiles of 8 px, 2 cut short


def test_a_light_inside_the_span_of_its_triangle_is_recovered_by_every_oracle():
    basis = _basis()
    bary = np.array([0.0, 0.2, 0.0, 0.5, 0.3, 0.0])
    target = 1.7 * np.tensordot(bary, basis, axes=1)  # a brighter exposure of the barycentric mix
    preds = oracle_predictions(target, basis, bary)
    assert set(preds) == set(ORACLES)
    for name, pred in preds.items():
        np.testing.assert_allclose(pred, target, rtol=1e-9, atol=1e-9, err_msg=name)


def test_the_fitted_oracles_only_use_their_own_lights_and_rank_as_ceilings():
    basis = _basis(1)
    bary = np.array([0.6, 0.0, 0.4, 0.0, 0.0, 0.0])
    # The target needs light 5, outside the triangle {0, 2}: only the all-bars fit can use it.
    target = 0.3 * basis[0] + 0.9 * basis[5]
    preds = oracle_predictions(target, basis, bary)
    err = {name: float(((pred - target) ** 2).mean()) for name, pred in preds.items()}
    assert err["all_bars_fit"] < 1e-18
    assert err["all_bars_fit"] <= err["triangle_fit"] <= err["barycentric"] + 1e-15
    assert err["triangle_tile_fit"] <= err["triangle_fit"] + 1e-15
    assert err["triangle_fit"] > 1e-4 and err["triangle_tile_fit"] > 1e-4
    # The triangle fit is a non-negative mix of the triangle's lights only.
    flat = basis.reshape(len(basis), -1).T
    weights, *_ = np.linalg.lstsq(flat[:, [0, 2]], preds["triangle_fit"].reshape(-1), rcond=None)
    np.testing.assert_allclose(flat[:, [0, 2]] @ weights, preds["triangle_fit"].reshape(-1), atol=1e-12)
    assert (weights >= -1e-12).all()


def test_the_barycentric_prediction_is_scaled_to_the_target_like_the_train_stage_scores_it():
    basis = _basis(2)
    bary = np.array([0.0, 0.0, 1 / 3, 1 / 3, 1 / 3, 0.0])
    target = basis[1]
    mix = np.tensordot(bary, basis, axes=1)
    pred = oracle_predictions(target, basis, bary)["barycentric"]
    scale = float((mix * target).sum() / (mix * mix).sum())
    np.testing.assert_allclose(pred, scale * mix, rtol=1e-12)
    np.testing.assert_array_equal(exposure_fit(np.zeros((2, 2, 3)), target[:2, :2]), np.zeros((2, 2, 3)))


def test_the_tile_fit_mixes_the_triangle_differently_in_each_tile():
    basis = _basis(3)
    bary = np.array([0.0, 0.5, 0.25, 0.25, 0.0, 0.0])
    target = 0.4 * basis[1] + 0.1 * basis[3]
    target[:8, :8] = 0.9 * basis[2, :8, :8]  # the top-left tile is lit by another mix
    preds = oracle_predictions(target, basis, bary)
    np.testing.assert_allclose(preds["triangle_tile_fit"], target, rtol=1e-9, atol=1e-9)
    assert float(((preds["triangle_fit"] - target) ** 2).mean()) > 1e-3
