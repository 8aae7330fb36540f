"""The neural head: relightable mixture of volumetric primitives (Xu et al. 2024 on MVP).

Modules: ``config`` (sizes; ``AvatarConfig.tiny()`` / ``.paper()``), ``layout`` (primitive
anchors on the guide mesh), ``model`` (encoder, geometry / appearance / opacity branches),
``raymarch`` (fast paths + slow reference; on the CPU the fused C++ kernel of
``raymarch_fused``, built on first use), ``travatar`` (the TRAvatar* baseline), ``io``
(save / load), ``metrics`` and ``lpips`` (evaluation).

Usage (stable API; all positions in head space, metres; images linear RGB)::

    import torch
    from avatar.io import load_trained
    from avatar.raymarch import raymarch

    # The train stage writes <train output>/models/ours/ (and models/travatar/).
    model, meta = load_trained(train_dir / "models" / "ours")   # eval mode, CPU by default
    image_scale = meta["image_scale"]   # renders are in training units: divide by it for capture units

    # One frame: a tracked head-space mesh [V, 3] (track/meshes.npz) -> latent code.
    mu, _ = model.encode(torch.as_tensor(mesh_vertices)[None])     # [1, Z]
    geo = model.decode_geometry(mu)        # boxes + opacity: independent of light and view

    # A camera in head space (Camera whose cam_from_world is cam_from_head, e.g. from
    # stabilize/cameras_head.json, or cam_from_world @ world_from_head).
    origins, dirs = camera.image_rays()                             # [H, W, 3] each (numpy)
    rays_o = torch.as_tensor(origins, dtype=torch.float32).view(1, -1, 3)
    rays_d = torch.as_tensor(dirs, dtype=torch.float32).view(1, -1, 3)
    cam_pos = torch.as_tensor(camera.center_world, dtype=torch.float32)[None]   # [1, 3]

    # A point light at p (head space): decode RGB voxels, raymarch.
    rgb = model.decode_rgb(geo, cam_pos, torch.tensor([p], dtype=torch.float32))  # [1, P, M, M, M, 3]
    out = raymarch(geo.primitives(rgb), rays_o, rays_d, model.config.steps_per_ray)
    image = out.rgb.view(H, W, 3) / image_scale     # alpha: out.alpha.view(H, W)

    # K lights (an environment map as K directional-ish lights far away, with RGB weights
    # w [K, 3]): opacity does not depend on light, so sum the RGB voxel grids, raymarch once.
    total = 0
    for k in range(0, K, chunk):                    # decode_rgb is batched: B = lights in a chunk
        lp = light_positions[k:k + chunk]           # [k', 3]
        rgb_k = model.decode_rgb(geo.expand(len(lp)), cam_pos.expand(len(lp), 3), lp)   # [k', P, M, M, M, 3]
        total = total + (rgb_k * w[k:k + chunk, None, None, None, None, :]).sum(0, keepdim=True)
    out = raymarch(geo.primitives(total), rays_o, rays_d, model.config.steps_per_ray)

A directional light is a point light far away (e.g. 100 m along the direction): the
network was trained on near-field bars 1-1.5 m away, so very distant lights extrapolate.
TRAvatar* (``meta["kind"] == "travatar"``): build ``LightBasis(meta["basis_directions"])``
and use ``avatar.travatar.interpolated_rgb(model, geo, cam_pos, torch.as_tensor(
basis.weights(light_dirs), dtype=torch.float32))`` instead of ``decode_rgb``.
Run everything under ``torch.no_grad()`` when not training.
"""
