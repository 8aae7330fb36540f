"""Relight: render a trained head under environment maps, point lights, new views and expressions.

- ``render``: the voxel-space light sum (fast) and the per-light reference (naive).
- ``sequences``: what each frame shows (cameras, lights, driving mesh).
- ``expressions``: ARKit-named blendshape CSVs and OBJ sequences through the actor rig.
- ``outputs``: EXR + PNG per frame as it completes, MP4 at the end.
- ``stage`` (``relight``), ``eval_stage`` (``relight_eval``), ``cli`` (``pipeline render``).
"""
