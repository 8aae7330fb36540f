"""The virtual studio: a simulated twin of the capture rig (cameras, LED bars, subject).

Quick use (all deterministic; tiny resolution renders in well under a second per image)::

    from scene.rig import default_rig                       # configs/rig.yaml, typed
    from hardware.studio import (VirtualStudio, RenderSettings, make_subject,
                                 make_performance, scan_session)

    rig = default_rig()
    cameras = rig.cameras_at(0.3125)                      # 10 x scene.camera.Camera, 240x320
    subject = make_subject("alice", seed=1)                # ICT identity + procedural materials
    frames = make_performance(seed=1, frames_per_take=48)  # list[FrameState] ("rom", "speech")
    studio = VirtualStudio(rig, subject, RenderSettings(seed=1))

    res = studio.render(frames[0], cameras[0], "F")       # all 32 bars on
    res = studio.render(frames[1], cameras[0], 7)          # bar 7 alone (OLAT)
    res.rgb    # [H, W, 3] float32 linear HDR radiance, black backdrop, sensor noise
    res.alpha  # [H, W] float32 exact coverage of the head (ground-truth matte)
    studio.render(frame, cam, [3, 4], noise=False)         # several bars, noiseless

    # Any light list (relighting ground truth): scene.lights.PointLight / DirectionalLight /
    # LightBar, intensities used as given (bars get settings.bar_intensity_scale):
    from scene.lights import PointLight, DirectionalLight
    res = studio.render_lights(frame, cam, [PointLight([0.5, 0.3, 1.0], [0.4, 0.4, 0.4]),
                                            DirectionalLight([0, 1, 0.3], [0.2, 0.2, 0.2])])

Notes:
- ``FrameState`` (``hardware.studio.performance``) holds ``index``, ``take``, ``time_s``,
  ``expression_weights`` [57] (ICT names, ``scene.face_rig``) and ``world_from_head``
  (``scene.camera.Rigid``). Build your own for other performances:
  ``FrameState(0, "x", 0.0, weights, Rigid.identity())``.
- Other subjects: ``make_subject("bob", seed=2)``; head-space vertices of a frame:
  ``subject.vertices(frame.expression_weights)`` [V, 3] metres, triangles
  ``subject.rig.triangles`` (full ICT topology; ``subject.render_triangles`` are drawn).
- ``studio.geometry(frame)`` builds (and caches, for the last frame) the BVH; rendering
  all cameras of one frame before moving on to the next frame is the fast order.
- The world: metres, +y up, +z out of the face towards the cameras; the head stands at
  ``rig.head_center_m`` (origin). Bars: ``rig.light_bars()`` (``scene.lights.LightBar``).
- ``scan_session(subject)`` -> (names, vertices [S, V, 3], faces): the actor's scans.
- Exposure: with ``RenderSettings()`` a full-on (F) image has skin at about 0.3-0.6 linear,
  an OLAT image about 1/20 of that (HDR floats; scale for previews).
- ``RenderSettings(shadows=False)`` gives the unshadowed reference; ``noise=False`` in the
  render calls gives the noiseless image (ground truth for relighting comparisons).
- ``hardware.studio.renderer.reference_local_lights`` is the slow per-sample reference of
  the batched lighting (tests hold them together).
"""

from hardware.studio.performance import FrameState, make_performance
from hardware.studio.renderer import FrameGeometry, RenderResult, RenderSettings, VirtualStudio, build_geometry
from hardware.studio.scans import scan_session
from hardware.studio.subject import Subject, make_subject

__all__ = ["FrameState", "make_performance", "FrameGeometry", "RenderResult", "RenderSettings",
           "VirtualStudio", "build_geometry", "scan_session", "Subject", "make_subject"]
