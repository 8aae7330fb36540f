"""Relight: render a trained head under environment maps, point lights, new views and expressions.

- ``render``: one frame as an executor item and its cache key (rendering is ``avatar.render``).
- ``bake``: light-transfer bakes of a (view, expression) as executor items, cached; which
  sequences render from one (``choose_paths``) and their frames (``avatar.bake``).
- ``sequences``: what each frame shows (cameras, lights, driving mesh; the default camera is ``scene.view``).
- ``expressions``: ARKit-named blendshape CSVs and OBJ sequences through the actor rig.
- ``outputs``: EXR + PNG per frame as it completes, MP4 at the end.
- ``olat``: the virtual one-light-at-a-time basis for compositors (``pipeline render --olat-basis``).
- ``stage`` (``relight``), ``eval_stage`` (``relight_eval``), ``cli`` (``pipeline render``).
"""
