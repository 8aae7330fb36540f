"""A virtual OLAT basis for compositors: the head under one distant light at a time, one EXR part per light.

``pipeline render -S alice --olat-basis 256`` renders the trained head, for one view and one
expression, under a unit distant light from each of the paper's uniform directions
(``scene.envmap.fibonacci_sphere(256)``: the directions the envmap renders use, each standing
for its Voronoi cell of the sphere), and writes

- ``olat/olat_<D>dirs[_view<k>].exr``: a multi-part EXR, part ``dir<i:03d>`` per direction with
  channels ``dir<i:03d>.R/.G/.B/.A`` (linear, the capture's units, half float by default; alpha
  is the same in every part) and header attributes ``olatIndex`` (int), ``olatDirection``
  (V3f, head space), ``olatSolidAngleSr`` (float);
- ``olat/olat_<D>dirs[_view<k>].json``: the directions, their cells' solid angles, the frame and
  lat-long conventions, the camera, and the rule by which ``pipeline render --envmap``
  weights the layers (below), so the layers can be recombined without this code.

Relighting (what a compositor does in Nuke with a light-stage capture): a map of radiance
``L`` gives layer ``i`` the weight ``E_i`` = the integral of ``L`` over direction ``i``'s cell
(the map's pixels whose centres are nearest to direction ``i``, radiance times pixel solid
angle; about ``L(d_i) * solid_angle_i`` for a smooth map), and the image is ``sum_i E_i *
layer_i`` per channel. ``pipeline render --envmap`` also attenuates light from behind the head
(``back_mask``) and drops the dimmest ``drop_fraction`` of the lit directions, both recorded in
the JSON; ``tests/stages/relight/test_olat.py`` rebuilds its frames from the files alone.

The layers are the full-rank light-transfer bake (``avatar.bake.direction_images``: every
direction decoded by the network and rendered through one colour transport of the view).
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np

from avatar.bake import direction_images
from avatar.render import decode
from scene.envmap import fibonacci_sphere, uniform_solid_angles_sr
from scene.exr_layers import write_multipart_exr
from stages.relight import sequences as seq

OLAT_FORMAT = "olat-basis/1"


def olat_description(directions: np.ndarray, solid_angles: np.ndarray, camera, params, image_scale: float,
                     centre_head, layer_names: list[str], half: bool) -> dict:
    """The JSON beside an OLAT EXR: layers, directions, solid angles and the conventions to recombine them."""
    return {
        "format": OLAT_FORMAT,
        "layers": [{"part": name, "index": i, "direction_head": directions[i].tolist(),
                    "solid_angle_sr": float(solid_angles[i])} for i, name in enumerate(layer_names)],
        "directions_head": directions.tolist(),
        "solid_angles_sr": solid_angles.tolist(),
        "frame": "head space, metres: +y up, +z out of the face (towards the default camera), +x the subject's "
                 "left; directions point from the head towards the light",
        "latlong": "an H x 2H map's pixel (row i, column j) looks along (sin(phi) cos(theta), sin(theta), "
                   "cos(phi) cos(theta)), phi = 2 pi (0.5 - (j + 0.5) / W), theta = pi (0.5 - (i + 0.5) / H), "
                   "and has solid angle (2 pi / W) (sin(pi (0.5 - i / H)) - sin(pi (0.5 - (i + 1) / H))); "
                   "turning the map by a about +y shifts it by a / (2 pi) * W columns (new column j = old column "
                   "j + shift, linear between two columns)",
        "light": "each layer is the head under a distant light of unit irradiance from its direction (a point light "
                 f"{params.light_distance_m} m from centre_head along it); a light of irradiance E scales it by E",
        "relight": "image = sum_i E_i * layer_i per channel; E_i = the map's radiance integrated over direction i's "
                   "cell: the pixels whose centre is nearest to direction i, each radiance times its solid angle "
                   "(about radiance(direction_i) * solid_angle_sr for a smooth map)",
        "pipeline_render_envmap": {
            "back_mask": {"cone_half_angle_deg": params.back_mask.cone_half_angle_deg,
                          "attenuation_power": params.back_mask.attenuation_power,
                          "enabled": params.back_mask.enabled,
                          "rule": "a pixel looking along d counts with weight 0 if -d_z > cos(cone_half_angle_deg), "
                                  "else cos(asin(clip(-d_z, 0, 1))) ** attenuation_power (1 in front, d_z >= 0)"},
            "drop_fraction": params.drop_fraction,
            "drop_rule": "directions with no light are left out, then the floor(drop_fraction * lit) dimmest by "
                         "Rec. 709 luminance (0.2126 R + 0.7152 G + 0.0722 B; ties in index order)",
            "envmap_scale": params.envmap_scale,
        },
        "centre_head": [float(v) for v in centre_head],
        "light_distance_m": params.light_distance_m,
        "camera": camera.to_dict(),
        "camera_convention": "OpenCV pinhole; the pose is cam_from_head (head space, metres)",
        "expression": "the first tracked mesh (track/meshes.npz)",
        "image_scale": image_scale,
        "units": "linear RGB in the capture's units (the network's divided by image_scale)",
        "pixel_type": "half" if half else "float",
        "alpha": "opacity, the same in every layer (it does not depend on the light)",
        "width": int(camera.width), "height": int(camera.height),
    }


def export_olat_basis(inputs: dict[str, Path], params, count: int, out: Path, eyes: list, log: logging.Logger,
                      half: bool = True) -> list[Path]:
    """Write the OLAT basis of ``count`` uniform directions for the default view (or each of ``eyes``); returns the EXRs.

    ``params`` is the render's ``RelightParams`` (view size and distance, light distance, the
    envmap conventions recorded in the JSON, device).
    """
    from pipeline.devices import resolve_device
    from stages.relight.inputs import load_inputs

    if count < 1:
        raise ValueError(f"--olat-basis {count}: needs at least one direction")
    device = resolve_device(params.device, "relight.device")
    model, meta, default_mesh, _ = load_inputs(inputs, params, device)
    image_scale = float(meta.get("image_scale", 1.0))
    centre = tuple(float(v) for v in default_mesh.mean(0))
    view = seq.ViewSpec(params.width_px, params.height_px, params.distance_m, params.fov_deg, centre)
    cameras = [view.camera(view.front_eye())] if not eyes else [view.camera(np.asarray(e, float)) for e in eyes]
    directions = fibonacci_sphere(count)
    solid = uniform_solid_angles_sr(count)
    names = [f"dir{i:03d}" for i in range(count)]
    geometry = decode(model, default_mesh)
    (out / "olat").mkdir(parents=True, exist_ok=True)
    written = []
    for k, camera in enumerate(cameras):
        images = direction_images(model, geometry, camera, directions, distance_m=params.light_distance_m,
                                  centre=centre, steps=params.steps_per_ray or model.config.steps_per_ray,
                                  light_batch=params.light_batch)
        rgb = images.rgb.cpu().numpy() / np.float32(image_scale)  # [D, H, W, 3]
        alpha = images.alpha.cpu().numpy()[..., None]  # [H, W, 1]
        stem = f"olat_{count}dirs" + (f"_view{k}" if eyes else "")
        parts = [(names[i], np.concatenate([rgb[i], alpha], -1),
                  {"olatIndex": i, "olatDirection": directions[i].astype(np.float32),
                   "olatSolidAngleSr": float(solid[i])}) for i in range(count)]
        exr = out / "olat" / f"{stem}.exr"
        write_multipart_exr(exr, parts, half=half)
        (out / "olat" / f"{stem}.json").write_text(json.dumps(
            olat_description(directions, solid, camera, params, image_scale, centre, names, half), indent=1))
        log.info("wrote %s: %d one-light layers (%dx%d) and %s", exr, count, camera.width, camera.height,
                 exr.with_suffix(".json").name)
        written.append(exr)
    return written


__all__ = ["OLAT_FORMAT", "export_olat_basis", "olat_description"]
