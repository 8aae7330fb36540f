"""A small synthetic capture in the shared contracts' layout, for the train stage's tests.

Renders the ICT head (neutral identity, a few expressions, a small head motion) with a
Lambertian, shadowed point light at each OLAT bar's centre, for a few cameras of the rig at
a tiny resolution, and writes the folders that capture/stabilize/track/matte/lightcal
produce: ``capture/manifest.json`` + ``frames``, ``stabilize/cameras_head.json``,
``track/meshes.npz`` + ``tracking.npz``, ``matte/mattes``, ``lightcal/bars.json``.
"""

from __future__ import annotations

import contextlib
import json
from pathlib import Path

import numpy as np

from scene.camera import Camera, Rigid, look_at
from scene.face_rig import load_face_rig
from scene.image_io import write_exr, write_png16
from scene.rig import default_rig


def _albedo(points: np.ndarray) -> np.ndarray:
    """Procedural skin-like albedo with some spatial detail [K, 3]."""
    base = np.array([0.55, 0.38, 0.30])
    pattern = 0.5 + 0.5 * np.sin(points[:, 0] * 90.0) * np.sin(points[:, 1] * 70.0)
    return base[None] * (0.7 + 0.3 * pattern[:, None])


def make_capture(root: Path, width_px: int = 48, cameras: int = 6, frames_per_take: tuple[int, ...] = (30, 12),
                 seed: int = 0) -> dict[str, Path]:
    """Write the synthetic upstream outputs under ``root``; returns the input folder of each stage."""
    import trimesh

    rng = np.random.default_rng(seed)
    rig = default_rig()
    face = load_face_rig()
    scale = width_px / rig.width_px
    cams: list[Camera] = []
    for spec in rig.cameras[:cameras]:
        pose = look_at(np.array(spec.position_m), np.array(spec.look_at_m))
        cam = Camera(spec.name, rig.width_px, rig.height_px, spec.focal_px, spec.focal_px,
                     rig.width_px / 2 - 0.5, rig.height_px / 2 - 0.5, pose=pose)
        cams.append(cam.scaled(scale))
    bars = rig.bars
    names = list(face.expression_names)
    expr = np.zeros(len(names))
    keep = face.regions["face"].triangle_slice, face.regions["head_neck"].triangle_slice
    tris_outer = np.concatenate([face.triangles[s] for s in keep])
    out = {k: root / k for k in ("capture", "stabilize", "track", "matte", "lightcal")}
    for p in out.values():
        p.mkdir(parents=True, exist_ok=True)
    manifest_frames, meshes, rots, trans, indices, cam_frames = [], [], [], [], [], []
    olat_cursor = 0
    index = 0
    takes = ["rom", "speech"][:len(frames_per_take)]
    # A fixed shuffled OLAT order, restarted at every take (so short takes share their bars).
    olat_order = np.random.default_rng(7).permutation(len(bars))
    for take, count in zip(takes, frames_per_take):
        olat_cursor = 0
        for i in range(count):
            light = "F" if index % 3 == 0 else int(olat_order[olat_cursor % len(bars)])
            if light != "F":
                olat_cursor += 1
            phase = index * 0.37 + (2.0 if take == "speech" else 0.0)
            expr[:] = 0
            expr[face.expression_index("jawOpen")] = 0.35 + 0.35 * np.sin(phase)
            expr[face.expression_index("mouthSmile_L")] = 0.4 + 0.4 * np.cos(1.3 * phase)
            expr[face.expression_index("mouthSmile_R")] = 0.4 + 0.4 * np.cos(1.3 * phase)
            verts = face.vertices(None, expr)  # [V, 3] head space
            world_from_head = Rigid.from_rotvec(np.array([0.05 * np.sin(phase), 0.08 * np.cos(0.7 * phase), 0.0]),
                                                np.array([0.004 * np.sin(phase), 0.0, 0.003]))
            verts_world = world_from_head.apply(verts)
            mesh = trimesh.Trimesh(verts_world, tris_outer, process=False)
            frame_cams = []
            for cam in cams:
                origins, dirs = cam.image_rays()
                o, d = origins.reshape(-1, 3), dirs.reshape(-1, 3)
                locs, ray_ids, tri_ids = mesh.ray.intersects_location(o, d, multiple_hits=False)
                img = np.zeros((cam.height * cam.width, 3))
                matte = np.zeros(cam.height * cam.width)
                if len(ray_ids):
                    normals = mesh.face_normals[tri_ids]
                    normals = np.where(((normals * d[ray_ids]).sum(-1) > 0)[:, None], -normals, normals)
                    if light == "F":
                        shade = np.full(len(ray_ids), 0.8)
                    else:
                        bar = bars[light]
                        lp = np.array(bar.center_m)
                        to_l = lp - locs
                        dist2 = (to_l ** 2).sum(-1)
                        ldir = to_l / np.sqrt(dist2)[:, None]
                        shade = bar.intensity * np.maximum((normals * ldir).sum(-1), 0) / dist2 * 1.2
                        lit = shade > 0
                        if lit.any():
                            shadow = mesh.ray.intersects_any(locs[lit] + ldir[lit] * 1e-4, ldir[lit])
                            shade[np.flatnonzero(lit)[shadow]] = 0.0
                    img[ray_ids] = _albedo(locs - world_from_head.t) * shade[:, None]
                    matte[ray_ids] = 1.0
                img = img.reshape(cam.height, cam.width, 3)
                (out["capture"] / "frames" / cam.name).mkdir(parents=True, exist_ok=True)
                (out["matte"] / "mattes" / cam.name).mkdir(parents=True, exist_ok=True)
                write_exr(out["capture"] / "frames" / cam.name / f"{index:06d}.exr", img.astype(np.float32))
                write_png16(out["matte"] / "mattes" / cam.name / f"{index:06d}.png", matte.reshape(cam.height, cam.width))
                cam_from_head = cam.cam_from_world @ world_from_head
                frame_cams.append(cam.with_pose(cam_from_head, "head").to_dict())
            manifest_frames.append({"index": index, "take": take, "time_s": index / 24.0, "light": light, "status": "ok"})
            meshes.append(verts.astype(np.float32))
            rots.append(world_from_head.R)
            trans.append(world_from_head.t)
            indices.append(index)
            cam_frames.append({"index": index, "cameras": frame_cams})
            index += 1
    manifest = {"subject": "synthetic", "fps": 24.0, "width": cams[0].width, "height": cams[0].height,
                "cameras": [c.name for c in cams], "bars": len(bars), "takes": takes, "frames": manifest_frames}
    (out["capture"] / "manifest.json").write_text(json.dumps(manifest))
    # The stabilize stage's format: {"frames": {"<index>": [Camera.to_dict() of head-frame cameras]}}.
    (out["stabilize"] / "cameras_head.json").write_text(json.dumps(
        {"space": "head", "frames": {str(f["index"]): f["cameras"] for f in cam_frames}}))
    np.savez(out["track"] / "meshes.npz", index=np.array(indices), vertices=np.stack(meshes),
             faces=face.triangles.astype(np.int32))
    np.savez(out["track"] / "tracking.npz", index=np.array(indices), weights=np.zeros((len(indices), len(names))),
             world_from_head_R=np.stack(rots), world_from_head_t=np.stack(trans))
    noise = rng.normal(0, 0.002, (len(bars), 3))
    (out["lightcal"] / "bars.json").write_text(json.dumps({"bars": [
        {"id": b.id, "center_world": (np.array(b.center_m) + noise[b.id]).tolist(), "axis_world": list(b.axis),
         "length_m": b.length_m, "intensity": 1.0} for b in bars]}))
    return out


# The small relightable head the train tests train (8 x 8 primitives of 4^3 voxels).
SMALL_AVATAR = {"prims_per_side": 8, "voxels_per_side": 4, "latent_dim": 8, "encoder_hidden": 32,
                "base_channels": 16, "rgb_channels": [16, 12], "alpha_channels": [8, 4], "geometry_channels": 8,
                "steps_per_ray": 12}


def small_model(data, seed: int = 0):
    """``SMALL_AVATAR`` laid out on ``data``'s mean mesh, with its training tensors (CPU) and renderer.

    Returns ``(config, tensors, model, renderer)``; the model's weights come from ``torch.manual_seed(seed)``.
    """
    import torch

    from avatar.config import AvatarConfig
    from avatar.layout import build_layout
    from avatar.model import RelightableMVP
    from stages.train import trainer as trainer_mod
    from stages.train.setup import training_tensors

    config = AvatarConfig(**SMALL_AVATAR)
    layout = build_layout(data.vertices.mean(0), data.triangles, config.prims_per_side)
    tensors = training_tensors(data, layout.guide_vertex_ids, torch.device("cpu"))
    torch.manual_seed(seed)
    model = RelightableMVP(config, layout, data.num_bars)
    renderer = trainer_mod.Renderer(model, "ours", None, sorted(set(data.bar.tolist())))
    return config, tensors, model, renderer


@contextlib.contextmanager
def weights_restored(model):
    """Gives ``model`` (a shared fixture's) its present weights back on exit, whatever a test trained into it."""
    state = {k: v.clone() for k, v in model.state_dict().items()}
    try:
        yield model
    finally:
        model.load_state_dict(state)


def train_steps(renderer, tensors, ckpt_path: Path, weights, *, steps: int, lr: float, frames: int = 4,
                rays_per_image: int = 16):
    """A ``ModelTrainer`` on ``renderer``'s model, stepped ``steps`` times with the iteration advancing as
    ``ModelTrainer.run`` advances it; returns the trainer and every step's loss terms."""
    import logging

    from stages.train import trainer as trainer_mod

    tr = trainer_mod.ModelTrainer(renderer, tensors, np.arange(frames), iterations=steps, batch_size=2,
                                  rays_per_image=rays_per_image, lr=lr, weights=weights, seed=0, ckpt_path=ckpt_path,
                                  checkpoint_every=1000, spike_factor=1e9, log=logging.getLogger("test"))
    terms = []
    for _ in range(steps):
        terms.append(tr.step())
        tr.state.iteration += 1
    return tr, terms
