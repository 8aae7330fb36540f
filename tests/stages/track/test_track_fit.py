"""The per-frame fit and the tracker on synthetic projected landmarks (no images)."""

from __future__ import annotations

import numpy as np

from stages.track.fit import FitParams, FramePose, LandmarkModel, _Problem, fit_frame
from stages.track.geometry import PinholeArrays, rotation_angle_deg, triangulate
from stages.track.tracker import KeyFrameObservations, Tracker, TrackerParams, observation_confidence

FACE = slice(0, 9409)  # ICT face-region vertices


def _ideal(scene, uv):
    return observation_confidence(scene.cameras, uv, np.ones(uv.shape[:2]))


def test_analytic_jacobian_matches_finite_differences(scene):
    model = scene.embedding.model(scene.rig)
    cams = PinholeArrays.from_cameras(scene.cameras)
    uv, conf = _ideal(scene, scene.project(noise_px=1.0))
    prev = FramePose(scene.R[1], scene.t[1], scene.weights[1])
    problem = _Problem(model, cams, uv[2], conf[2], scene.R[2], prev, FitParams(), None)
    x = np.concatenate([[0.02, -0.03, 0.01], scene.t[2] + 0.001, np.full(model.num_shapes, 0.3)])
    analytic = problem.jacobian(x)
    eps = 1e-6
    numeric = np.stack([(problem.residuals(x + eps * e) - problem.residuals(x - eps * e)) / (2 * eps)
                        for e in np.eye(len(x))], axis=1)
    assert np.abs(analytic - numeric).max() < 1e-4 * np.abs(numeric).max()


def test_fit_recovers_pose_and_weights_with_noise_and_outliers(scene):
    model = scene.embedding.model(scene.rig)
    cams = PinholeArrays.from_cameras(scene.cameras)
    uv, conf = _ideal(scene, scene.project(noise_px=0.5, outlier_rate=0.05, seed=3))
    f = 4
    fit = fit_frame(model, cams, uv[f], conf[f], None, None, FitParams())
    assert fit is not None
    assert rotation_angle_deg(fit.pose.R, scene.R[f]) < 0.3
    assert np.linalg.norm(fit.pose.t - scene.t[f]) < 1e-3
    err = np.linalg.norm(scene.rig.mesh(fit.pose.weights)[FACE] - scene.rig.mesh(scene.weights[f])[FACE], axis=1)
    assert err.mean() < 0.3e-3
    # The robust loss keeps the median residual at the noise level despite 5 % outliers.
    assert np.nanmedian(fit.residual_px) < 1.5


def test_fit_drops_a_view_that_sees_another_face(scene):
    model = scene.embedding.model(scene.rig)
    cams = PinholeArrays.from_cameras(scene.cameras)
    uv, conf = _ideal(scene, scene.project(noise_px=0.3, seed=4))
    f = 3
    uv[f, 2] = uv[f, 2, ::-1]  # a wrong detection: landmarks scrambled in cam02
    uv[f, 2] += 30.0
    fit = fit_frame(model, cams, uv[f], conf[f], None, None, FitParams())
    assert fit is not None and "cam02" in fit.dropped_views
    assert rotation_angle_deg(fit.pose.R, scene.R[f]) < 0.3


def test_fit_returns_none_with_a_single_view(scene):
    model = scene.embedding.model(scene.rig)
    cams = PinholeArrays.from_cameras(scene.cameras)
    uv, conf = _ideal(scene, scene.project())
    conf[0, 1:] = 0.0
    assert fit_frame(model, cams, uv[0], conf[0], None, None, FitParams()) is None


def test_triangulation_rejects_an_outlier_view(scene):
    cams = PinholeArrays.from_cameras(scene.cameras)
    uv, conf = _ideal(scene, scene.project(noise_px=0.2, seed=5))
    uv[0, 1, :10] += 50.0
    points, valid, _ = triangulate(cams, uv[0], conf[0])
    assert valid[:10].all()
    assert np.linalg.norm(points - scene.landmarks_world(0), axis=1).max() < 2e-3


def test_tracker_embeds_and_tracks_a_sequence_with_bad_input(scene):
    uv = scene.project(noise_px=0.5, outlier_rate=0.03, seed=6)
    score = np.ones(uv.shape[:2])
    uv[2, 3] = np.nan  # a view with no face
    score[2, 3] = 0.0
    uv[5, :, : uv.shape[2] // 2] = np.nan  # half the landmarks occluded in every view
    uv[6, 0] += np.array([400.0, 0.0])  # the head left cam00's frustum: landmarks off the image
    tracker = Tracker(scene.rig, scene.cameras, scene.skin_triangles, None, TrackerParams(embed_frames=4))
    names = [str(i) for i in range(len(scene.times_s))]
    result = tracker.run(KeyFrameObservations(uv, score, scene.embedding.landmark_ids), names)
    assert all(fit is not None for fit in result.fits)
    rot = [rotation_angle_deg(fit.pose.R, scene.R[f]) for f, fit in enumerate(result.fits)]
    vert_mm = [np.linalg.norm(scene.rig.mesh(fit.pose.weights)[FACE] - scene.rig.mesh(scene.weights[f])[FACE],
                              axis=1).mean() * 1000 for f, fit in enumerate(result.fits)]
    assert np.mean(rot) < 0.5 and max(rot) < 1.0
    assert np.mean(vert_mm) < 0.5
    # The landmark embedding found the true surface points to within about a millimetre.
    est = result.embedding.points(scene.rig.faces, scene.rig.neutral_m)
    true = scene.embedding.points(scene.rig.faces, scene.rig.neutral_m)
    assert np.median(np.linalg.norm(est - true, axis=1)) < 1.0e-3
