"""The neural head: relightable mixture of volumetric primitives (Xu et al. 2024 on MVP).

Modules: ``config`` (sizes; ``AvatarConfig.tiny()`` / ``.paper()``), ``layout`` (primitive
anchors on the guide mesh), ``model`` (encoder, geometry / appearance / opacity branches),
``render`` (the public render API: mesh + camera + lights -> image), ``raymarch`` (fast
paths + slow reference; on the CPU the fused C++ kernel of ``raymarch_fused``, built on
first use), ``travatar`` (the TRAvatar* baseline), ``io`` (save / load), ``metrics`` and
``lpips`` (evaluation), ``transport`` (a raymarch's voxel-to-pixel weights as a sparse matrix) and
``bake`` (the light-transfer bake: any distant lighting of one view and expression as a
weighted sum of basis images).

Usage (stable API; all positions in head space, metres; images linear RGB)::

    from avatar.io import load_trained
    from avatar.render import DirectionalLights, PointLights, decode, render

    # The train stage writes <train output>/models/ours/ (and models/travatar/).
    model, meta = load_trained(train_dir / "models" / "ours")   # eval mode, CPU by default
    image_scale = meta["image_scale"]   # renders are in training units; render() divides by it

    # A camera in head space: a scene.camera.Camera posed in the head frame, cam.cam_from_head (e.g.
    # from stabilize's cameras_head(), or cam.with_pose(cam.cam_from_world @ world_from_head, "head")).
    # A tracked head-space mesh [V, 3] (track/meshes.npz) drives the head; decode it once to render
    # it many times.
    geometry = decode(model, mesh_vertices)   # boxes + opacity: independent of light and view

    # Point lights: positions [K, 3] with RGB intensities [K, 3] (1 = the network's unit light,
    # a training bar at its own distance).
    image = render(model, geometry, camera, PointLights([[0.5, 0.3, 1.0]], [[1.0, 1.0, 1.0]]),
                   image_scale=image_scale)
    rgb, alpha = image.numpy()   # [H, W, 3], [H, W] float32 (image.rgb / .alpha: torch tensors)

    # An environment map: K directional lights with RGB weights (scene.envmap.select_lights),
    # rendered as point lights 50 m away. Opacity does not depend on light, so render() sums
    # the RGB voxel grids of all lights (decoded light_batch at a time) and raymarches once;
    # method="per_light" raymarches each light and sums the images (the slow reference).
    lights = DirectionalLights(env_lights.directions_world, env_lights.irradiance_rgb, distance_m=50.0)
    image = render(model, geometry, camera, lights, image_scale=image_scale, light_batch=16)

The network was trained on near-field bars 1-1.5 m away, so very distant lights
extrapolate. TRAvatar* (``meta["kind"] == "travatar"``): pass its light basis,
``render(..., basis=LightBasis(meta["basis_directions"]))`` (``avatar.travatar``); point and
directional lights are blended over it, ``BasisLights(weights)`` feeds basis weights as they
are. ``camera`` may also be ``avatar.render.Rays`` (origins, directions, camera centre, size).
The building blocks ``render`` uses are public too: ``model.encode`` / ``decode_geometry`` /
``decode_rgb``, ``geometry.primitives(rgb)`` and ``avatar.raymarch.raymarch``.
"""
