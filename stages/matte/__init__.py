"""Matting: an alpha matte for every captured image (MODNet-style network, classical baseline).

Modules, each with one job:
- ``modnet``: the network (semantic, detail and fusion branches, IBNorm, SE block).
- ``losses``: MODNet's supervised losses and the SOC (sub-objectives consistency) loss.
- ``inputs``: linear HDR image -> network input (exposure normalisation, F-frame guide).
- ``synthetic``: procedural head-like shapes with exact alpha (tests, development).
- ``studio_data``: training frames rendered by the virtual studio for other subjects.
- ``augment``: exposure, noise and blur augmentation.
- ``training``: supervised training, SOC adaptation, the shared model cache.
- ``baseline``: threshold + guided filter for a black backdrop.
- ``measures``: MAE, MSE, gradient error.
- ``stage`` / ``eval_stage``: the pipeline adapters.
"""
