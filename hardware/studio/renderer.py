"""The virtual studio's renderer: embree ray tracing of the subject under the rig's lights.

Per frame the subject's mesh is posed (``Subject.vertices`` then ``world_from_head``) and an
embree BVH is built once (``FrameGeometry``); every camera and light of that frame reuses
it. Per camera:

1. Primary rays through pixel centres (``Camera.pixel_rays``, so lens distortion is exact).
   Pixels on the silhouette (a neighbour's hit status differs) are re-traced with
   ``edge_samples^2`` stratified, jittered sub-pixel rays (a fixed pattern, so renders are
   deterministic); ``alpha`` is the fraction of a pixel's samples that hit the head.
2. Shading of every hit sample: Lambert diffuse (albedo / pi) plus a GGX microfacet
   specular (Smith-Schlick G, Schlick Fresnel, F0 from the material), summed over light
   samples. Bars are integrated with ``bar_samples`` stratified points per bar and per
   pixel (seeded jitter), each with its own shadow ray (embree occlusion query), the
   near-field ``1 / r^2``, the receiver cosine and the bar's emitter cosine.
3. Sensor noise (shot + read, seeded by frame and camera) on the linear radiance: the ideal
   studio's model. The capture stage's ``realism: real`` renders without it and films the clean
   image through ``hardware.studio.real_camera`` instead (electrons, DN, lens, motion).

Output is linear HDR RGB (black backdrop) and the exact coverage alpha.
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
from pydantic import ConfigDict, Field
from pydantic.dataclasses import dataclass as pydantic_dataclass

from scene.camera import Camera
from scene.lights import DirectionalLight, Light, LightBar, PointLight
from scene.rig import RigConfig
from hardware.studio.performance import FrameState
from hardware.studio.subject import MAT_EYE, MAT_MOUTH, MAT_SKIN, MAT_SOCKET, MAT_TEETH, Subject

_SHADOW_OFFSET_M = 2e-4  # lift shadow-ray origins off the surface (float32 BVH, metre scene)
_MISS_T = 1e30


@pydantic_dataclass(frozen=True, config=ConfigDict(extra="forbid"))
class RenderSettings:
    """How the studio renders (all deterministic for fixed values).

    The one declaration of these settings: the capture stage nests it as ``capture.render``;
    every other caller of the virtual studio builds one directly.
    """

    edge_samples: int = Field(
        4, ge=1, le=8, description="n for the n x n jittered samples of a silhouette pixel (1 = no antialiasing). "
        "Raise it for smoother silhouettes and mattes; the cost grows with n^2 on edge pixels only.")
    bar_samples: int = Field(
        4, ge=1, description="Shadow/irradiance samples per bar and pixel when few bars are lit (the OLAT "
        "frames). Raise it for cleaner penumbrae (less light-sample noise in the targets); render time grows "
        "about linearly.")
    full_on_bar_samples: int = Field(
        1, ge=1, description="Shadow samples per bar and pixel when many bars are lit (the full-on F frames); "
        "with 32 bars lit one sample each already averages out, so raise it only to study F-frame noise.")
    many_bars: int = Field(
        8, ge=1, description="From this many lit bars on, full_on_bar_samples is used instead of bar_samples.")
    bar_intensity_scale: float = Field(
        0.45, gt=0, description="Radiant intensity of a bar of relative intensity 1 (sets the exposure); "
        "change it only together with the downstream exposure assumptions.")
    shot_noise_gain: float = Field(
        2e-4, ge=0, description="Variance of the sensor's shot noise per unit of signal (0 = none).")
    read_noise: float = Field(
        1e-3, ge=0, description="Standard deviation of the additive read noise, linear units (0 = none).")
    seed: int = Field(
        0, description="Seed of the light-sample jitter and the sensor noise (the capture stage also seeds "
        "its camera time stamps and calibration-take poses with it). Change it for another noise draw.")
    shadows: bool = Field(
        True, description="Trace shadow rays; False gives the unshadowed reference (tests).")


def gaussian_sensor_noise(rgb: np.ndarray, shot_noise_gain: float, read_noise: float,
                          rng: np.random.Generator) -> np.ndarray:
    """The ideal studio's sensor: Gaussian shot noise (variance ``shot_noise_gain`` per unit of signal) plus
    read noise (sigma ``read_noise``) on linear ``rgb``, clipped at 0."""
    sigma = np.sqrt(shot_noise_gain * np.maximum(rgb, 0) + read_noise ** 2)
    return np.maximum(rgb + sigma * rng.standard_normal(rgb.shape), 0.0)


@dataclass
class RenderResult:
    """One rendered image.

    Attributes:
        rgb: [H, W, 3] float32 linear radiance (with sensor noise unless disabled).
        alpha: [H, W] float32 coverage of the head in each pixel, in [0, 1].
        rays: number of rays traced (primary + shadow), for rate measurements.
    """

    rgb: np.ndarray
    alpha: np.ndarray
    rays: int = 0


@dataclass
class FrameGeometry:
    """The posed subject of one frame with its BVH (build once, render many cameras)."""

    frame_index: int
    vertices_world: np.ndarray  # [V, 3] float64
    vertices_head: np.ndarray  # [V, 3] float32
    triangles: np.ndarray  # [K, 3] int32, the drawn subset
    triangle_rig_ids: np.ndarray  # [K] rig triangle index of each drawn triangle
    normals_world: np.ndarray  # [V, 3] unit vertex normals
    eye_centres_world: np.ndarray  # [2, 3] left, right
    eye_gaze_world: np.ndarray  # [2, 3] unit
    scene: object = field(repr=False)
    shadows: bool = True

    def trace(self, origins: np.ndarray, dirs: np.ndarray) -> dict:
        """First hits of rays [N, 3]: ``primID`` (-1 = miss), ``u``, ``v``, ``tfar``, ``Ng``."""
        return self.scene.run(np.ascontiguousarray(origins, np.float32), np.ascontiguousarray(dirs, np.float32),
                              output=1)

    def occluded(self, origins: np.ndarray, dirs: np.ndarray, dists: np.ndarray) -> np.ndarray:
        """Whether each ray [N] hits anything closer than ``dists`` [N]."""
        if len(origins) == 0 or not self.shadows:
            return np.zeros(len(origins), bool)
        res = self.scene.run(np.ascontiguousarray(origins, np.float32), np.ascontiguousarray(dirs, np.float32),
                             dists=np.ascontiguousarray(dists, np.float32), query="OCCLUDED")
        return np.asarray(res) >= 0


def build_geometry(subject: Subject, frame: FrameState) -> FrameGeometry:
    """Pose ``subject`` for ``frame`` and build its embree BVH."""
    from embreex import rtcore_scene
    from embreex.mesh_construction import TriangleMesh

    verts_head = subject.vertices(frame.expression_weights)
    verts_world = frame.world_from_head.apply(verts_head.astype(np.float64))
    rig_ids = subject.render_triangles
    tris = subject.rig.triangles[rig_ids]
    scene = rtcore_scene.EmbreeScene()
    TriangleMesh(scene=scene, vertices=verts_world.astype(np.float32), indices=np.ascontiguousarray(tris, np.int32))
    normals = vertex_normals(verts_world, tris)
    rig = subject.rig
    centres, gazes = [], []
    for name, pupil in zip(("eyeball_left", "eyeball_right"), subject.eye_pupil_vertices):
        c = verts_world[rig.regions[name].vertex_slice].mean(0)
        g = verts_world[pupil] - c
        centres.append(c)
        gazes.append(g / np.linalg.norm(g))
    return FrameGeometry(frame.index, verts_world, verts_head, tris, rig_ids, normals,
                         np.array(centres), np.array(gazes), scene)


def vertex_normals(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals [V, 3] (vertices not in any triangle get +z)."""
    v0, v1, v2 = (vertices[triangles[:, i]] for i in range(3))
    fn = np.cross(v1 - v0, v2 - v0)  # [K, 3], length = 2 * area
    acc = np.zeros_like(vertices)
    for i in range(3):
        for c in range(3):
            acc[:, c] += np.bincount(triangles[:, i], weights=fn[:, c], minlength=len(vertices))
    norm = np.linalg.norm(acc, axis=1, keepdims=True)
    out = np.where(norm > 1e-20, acc / np.maximum(norm, 1e-30), np.array([0.0, 0.0, 1.0]))
    return out


@dataclass
class _Hits:
    """Shading inputs of N hit samples."""

    pixel: np.ndarray  # [N] flat pixel index
    weight: np.ndarray  # [N] sample weight within its pixel
    position: np.ndarray  # [N, 3]
    normal: np.ndarray  # [N, 3] shading normal, facing the viewer
    geo_normal: np.ndarray  # [N, 3] geometric normal, facing the viewer
    view: np.ndarray  # [N, 3] unit vector towards the camera
    albedo: np.ndarray  # [N, 3]
    roughness: np.ndarray  # [N]
    f0: np.ndarray  # [N]


def _ggx_shade(normal: np.ndarray, view: np.ndarray, albedo: np.ndarray, roughness: np.ndarray,
               f0: np.ndarray, l: np.ndarray, irradiance: np.ndarray) -> np.ndarray:
    """Reflected radiance [N, 3]: (albedo / pi + GGX specular) times irradiance.

    Args:
        normal, view, l: [N, 3] unit shading normal, direction to the camera, direction to the light.
        albedo: [N, 3]; roughness, f0: [N] perceptual roughness (alpha = r^2) and Fresnel F0.
        irradiance: [N, 3] or [N], cosine included.
    """
    half = l + view
    half /= np.maximum(np.linalg.norm(half, axis=1, keepdims=True), 1e-12)
    n_l = np.clip(np.einsum("ij,ij->i", normal, l), 1e-4, 1.0)
    n_v = np.clip(np.einsum("ij,ij->i", normal, view), 1e-4, 1.0)
    n_h = np.clip(np.einsum("ij,ij->i", normal, half), 0.0, 1.0)
    v_h = np.clip(np.einsum("ij,ij->i", view, half), 0.0, 1.0)
    alpha = np.maximum(roughness ** 2, 1e-3)
    a2 = alpha * alpha
    denom = n_h * n_h * (a2 - 1.0) + 1.0
    d = a2 / (np.pi * denom * denom)
    k = alpha / 2.0
    g = (n_l / (n_l * (1 - k) + k)) * (n_v / (n_v * (1 - k) + k))
    fresnel = f0 + (1.0 - f0) * (1.0 - v_h) ** 5
    spec = fresnel * d * g / (4.0 * n_l * n_v)  # [N]
    irr = irradiance if irradiance.ndim == 2 else irradiance[:, None]
    return irr * (albedo / np.pi + spec[:, None])


class VirtualStudio:
    """Renders a subject in the rig. See ``hardware.studio`` for a usage example."""

    def __init__(self, rig: RigConfig, subject: Subject, settings: RenderSettings | None = None) -> None:
        self.rig = rig
        self.subject = subject
        self.settings = settings or RenderSettings()
        self.bars: list[LightBar] = rig.light_bars()
        self._geometry: FrameGeometry | None = None
        self._geometry_key: tuple | None = None
        self._ray_cache: dict[tuple, tuple[np.ndarray, np.ndarray]] = {}
        self._subpixel = self._subpixel_pattern(self.settings.edge_samples)

    # ---- geometry ------------------------------------------------------------------------
    def geometry(self, frame: FrameState) -> FrameGeometry:
        """The frame's posed mesh and BVH (the last one is cached)."""
        key = (frame.index, frame.expression_weights.tobytes(), frame.world_from_head.R.tobytes(),
               frame.world_from_head.t.tobytes())
        if self._geometry is None or self._geometry_key != key:
            self._geometry = build_geometry(self.subject, frame)
            self._geometry.shadows = self.settings.shadows
            self._geometry_key = key
        return self._geometry

    # ---- public rendering API ---------------------------------------------------------
    def render(self, frame: FrameState, camera: Camera, lit_bars: str | int | Sequence[int] = "F",
               noise: bool = True) -> RenderResult:
        """Render ``frame`` from ``camera`` with rig bars lit: ``"F"`` (all), a bar id, or a list of ids."""
        if isinstance(lit_bars, str):
            if lit_bars != "F":
                raise ValueError(f"lit_bars must be 'F', a bar id or a list of bar ids, got '{lit_bars}'")
            ids = list(range(len(self.bars)))
        elif isinstance(lit_bars, (int, np.integer)):
            ids = [int(lit_bars)]
        else:
            ids = [int(b) for b in lit_bars]
        for b in ids:
            if not 0 <= b < len(self.bars):
                raise ValueError(f"bar id {b} out of range: the rig has bars 0..{len(self.bars) - 1}")
        return self.render_lights(frame, camera, [self.bars[b] for b in ids], noise=noise)

    def render_lights(self, frame: FrameState, camera: Camera, lights: Sequence[Light],
                      noise: bool = True) -> RenderResult:
        """Render ``frame`` from ``camera`` under any list of lights (bars, point, directional).

        Bars are scaled by ``settings.bar_intensity_scale``; point and directional lights are
        used as given. Sensor noise is added when ``noise`` (and the settings' noise is not 0).
        """
        geom = self.geometry(frame)
        hits, alpha, rays = self._primary(geom, camera)
        n_bars = sum(isinstance(light, LightBar) for light in lights)
        samples = self.settings.full_on_bar_samples if n_bars >= self.settings.many_bars else self.settings.bar_samples
        cam_key = zlib.crc32(camera.name.encode())
        radiance, n_rays = self._local_lights(geom, hits, lights, samples, (self.settings.seed, frame.index, cam_key))
        rays += n_rays
        for light in lights:
            if isinstance(light, DirectionalLight):
                contrib, n_rays = self._directional(geom, hits, light)
                radiance += contrib
                rays += n_rays
        h, w = camera.height, camera.width
        rgb = np.zeros((h * w, 3))
        for c in range(3):
            rgb[:, c] = np.bincount(hits.pixel, weights=radiance[:, c] * hits.weight, minlength=h * w)
        rgb = rgb.reshape(h, w, 3)
        if noise and (self.settings.shot_noise_gain > 0 or self.settings.read_noise > 0):
            rng = np.random.default_rng([self.settings.seed, frame.index, cam_key, 99])
            rgb = gaussian_sensor_noise(rgb, self.settings.shot_noise_gain, self.settings.read_noise, rng)
        return RenderResult(rgb.astype(np.float32), alpha.astype(np.float32), rays)

    def render_views(self, frame: FrameState, cameras: Sequence[Camera],
                     lit_bars: str | int | Sequence[int] = "F", noise: bool = True) -> list[RenderResult]:
        """Render one frame from several cameras, sharing the frame's BVH."""
        return [self.render(frame, cam, lit_bars, noise=noise) for cam in cameras]

    # ---- internals ----------------------------------------------------------------------
    @staticmethod
    def _subpixel_pattern(n: int) -> np.ndarray:
        """[n*n, 2] stratified, jittered offsets in [-0.5, 0.5) (fixed seed: deterministic)."""
        rng = np.random.default_rng(12345)
        a, b = np.meshgrid(np.arange(n), np.arange(n))
        jitter = rng.uniform(0.1, 0.9, size=(n * n, 2))
        return np.stack([(a.ravel() + jitter[:, 0]) / n - 0.5, (b.ravel() + jitter[:, 1]) / n - 0.5], -1)

    def _centre_rays(self, camera: Camera) -> tuple[np.ndarray, np.ndarray]:
        key = (camera.name, camera.width, camera.height, camera.fx, camera.fy, camera.cx, camera.cy,
               tuple(camera.dist), camera.cam_from_world.R.tobytes(), camera.cam_from_world.t.tobytes())
        if key not in self._ray_cache:
            o, d = camera.image_rays()
            self._ray_cache[key] = (o.reshape(-1, 3), d.reshape(-1, 3))
            if len(self._ray_cache) > 64:
                self._ray_cache.pop(next(iter(self._ray_cache)))
        return self._ray_cache[key]

    def _primary(self, geom: FrameGeometry, camera: Camera) -> tuple[_Hits, np.ndarray, int]:
        h, w = camera.height, camera.width
        origins, dirs = self._centre_rays(camera)
        res = geom.trace(origins, dirs)
        hit = (res["primID"] >= 0).reshape(h, w)
        rays = len(origins)
        # Silhouette pixels: hit status differs from any 8-neighbour.
        pad = np.pad(hit, 1, mode="edge")
        edge = np.zeros_like(hit)
        for dy in (-1, 0, 1):
            for dx in (-1, 0, 1):
                edge |= pad[1 + dy:1 + dy + h, 1 + dx:1 + dx + w] != hit
        alpha = hit.astype(np.float64)
        flat_edge = edge.ravel()
        keep = (~flat_edge) & hit.ravel()
        parts = [self._hit_samples(geom, np.nonzero(keep)[0], origins[keep], dirs[keep], res, keep, 1.0)]
        if self.settings.edge_samples > 1 and flat_edge.any():
            edge_ids = np.nonzero(flat_edge)[0]
            s = len(self._subpixel)
            uv = np.stack([edge_ids % w, edge_ids // w], -1).astype(np.float64)  # [E, 2] (x, y)
            sub_uv = (uv[:, None, :] + self._subpixel[None]).reshape(-1, 2)
            o2, d2 = camera.pixel_rays(sub_uv)
            res2 = geom.trace(o2, d2)
            rays += len(o2)
            sub_hit = res2["primID"] >= 0
            alpha.reshape(-1)[edge_ids] = sub_hit.reshape(-1, s).mean(1)
            pix = np.repeat(edge_ids, s)
            parts.append(self._hit_samples(geom, pix[sub_hit], o2[sub_hit], d2[sub_hit], res2, sub_hit, 1.0 / s))
        elif flat_edge.any():
            sel = flat_edge & hit.ravel()
            parts.append(self._hit_samples(geom, np.nonzero(sel)[0], origins[sel], dirs[sel], res, sel, 1.0))
        hits = _Hits(*(np.concatenate([getattr(p, f) for p in parts]) for f in _Hits.__dataclass_fields__))
        return hits, alpha, rays

    def _hit_samples(self, geom: FrameGeometry, pixel: np.ndarray, origins: np.ndarray, dirs: np.ndarray,
                     res: dict, mask: np.ndarray, weight: float) -> _Hits:
        """Surface attributes at the hits ``res[mask]`` of rays (origins, dirs) [N, 3]."""
        subject = self.subject
        prim = res["primID"][mask]
        u = res["u"][mask].astype(np.float64)
        v = res["v"][mask].astype(np.float64)
        t = res["tfar"][mask].astype(np.float64)
        tri = geom.triangles[prim]  # [N, 3]
        rig_tri = geom.triangle_rig_ids[prim]
        bary = np.stack([1.0 - u - v, u, v], -1)  # [N, 3]
        position = origins + dirs * t[:, None]
        view = -dirs
        geo_n = np.asarray(res["Ng"][mask], np.float64)
        geo_n /= np.maximum(np.linalg.norm(geo_n, axis=1, keepdims=True), 1e-20)
        geo_n *= np.where(np.einsum("ij,ij->i", geo_n, view) < 0, -1.0, 1.0)[:, None]
        normal = np.einsum("nk,nkc->nc", bary, geom.normals_world[tri])
        normal *= np.where(np.einsum("ij,ij->i", normal, geo_n) < 0, -1.0, 1.0)[:, None]
        # Silhouette: bend interpolated normals that face away from the camera back towards it.
        n_v = np.einsum("ij,ij->i", normal, view)
        normal += np.clip(0.02 - n_v, 0, None)[:, None] * view
        normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-20)

        material = subject.triangle_material[rig_tri]
        uv = np.einsum("nk,nkc->nc", bary, subject.rig.uv[subject.rig.triangles_uv[rig_tri]])
        albedo = np.zeros((len(prim), 3))
        rough = np.zeros(len(prim))
        f0 = np.full(len(prim), 0.028)
        skin = (material == MAT_SKIN) | (material == MAT_SOCKET)
        if skin.any():
            a, r, s = _sample_atlas(subject, uv[skin])
            sock = material[skin] == MAT_SOCKET
            a[sock] = subject.skin_albedo * np.array([0.8, 0.55, 0.55])
            albedo[skin], rough[skin], f0[skin] = a, r, s
        mouth = material == MAT_MOUTH
        albedo[mouth], rough[mouth], f0[mouth] = (0.32, 0.07, 0.07), 0.35, 0.03
        teeth = material == MAT_TEETH
        albedo[teeth], rough[teeth], f0[teeth] = (0.72, 0.68, 0.58), 0.3, 0.04
        eye = material == MAT_EYE
        if eye.any():
            is_right = rig_tri[eye] >= subject.rig.regions["eyeball_right"].triangle_start
            albedo[eye] = _eye_albedo(subject, position[eye], geom.eye_centres_world[is_right.astype(int)],
                                      geom.eye_gaze_world[is_right.astype(int)])
            rough[eye], f0[eye] = 0.08, 0.04
        return _Hits(pixel.astype(np.int64), np.full(len(prim), weight), position, normal, geo_n, view,
                     albedo, rough, f0)

    def _directional(self, geom: FrameGeometry, hits: _Hits, light: DirectionalLight) -> tuple[np.ndarray, int]:
        """Radiance [N, 3] a directional light reflects at the hits (shadowed); and rays traced."""
        out = np.zeros((len(hits.pixel), 3))
        l_dir = light.direction_world
        cos_i = hits.normal @ l_dir
        live = np.nonzero((cos_i > 0) & (hits.geo_normal @ l_dir > -0.2))[0]
        origin = hits.position[live] + _SHADOW_OFFSET_M * hits.geo_normal[live]
        vis = ~geom.occluded(origin, np.broadcast_to(l_dir, (len(live), 3)), np.full(len(live), _MISS_T))
        idx = live[vis]
        l = np.broadcast_to(l_dir, (len(idx), 3))
        out[idx] = _ggx_shade(hits.normal[idx], hits.view[idx], hits.albedo[idx], hits.roughness[idx], hits.f0[idx],
                              l, cos_i[idx][:, None] * light.irradiance_rgb)
        return out, len(live)

    def _local_lights(self, geom: FrameGeometry, hits: _Hits, lights: Sequence[Light], samples: int,
                      seed: tuple[int, int, int], chunk: int = 8192) -> tuple[np.ndarray, int]:
        """Radiance [N, 3] that bars and point lights reflect at the hits, with shadows; rays traced.

        Every light contributes point samples (a bar ``samples`` stratified points per hit,
        jittered by a generator seeded with ``seed`` and the light's index in ``lights``; a
        point light itself). All samples of a chunk of hits are shaded in one batch and
        their shadow rays go to embree in one call.
        """
        n = len(hits.pixel)
        out = np.zeros((n, 3))
        # Per sample slot: which light, its stratum, intensity [3], emitter normal [3] (0 = isotropic).
        slots: list[tuple[int, int]] = []
        intensity, emit = [], []
        jitter: dict[int, np.ndarray] = {}
        for li, light in enumerate(lights):
            if isinstance(light, LightBar):
                rng = np.random.default_rng([*seed, li, 17])
                jitter[li] = rng.uniform(size=(n, samples))  # [N, K]
                for j in range(samples):
                    slots.append((li, j))
                    intensity.append(np.full(3, light.intensity * self.settings.bar_intensity_scale / samples))
                    emit.append(light.normal_world)
            elif isinstance(light, PointLight):
                slots.append((li, 0))
                intensity.append(light.intensity_rgb)
                emit.append(np.zeros(3) if light.normal_world is None else light.normal_world)
        if not slots or n == 0:
            return out, 0
        intensity_l = np.array(intensity)  # [L, 3]
        emit_l = np.array(emit)  # [L, 3]
        has_emit = np.linalg.norm(emit_l, axis=1) > 0  # [L]
        rays = 0
        for c0 in range(0, n, chunk):
            c1 = min(n, c0 + chunk)
            pos = np.empty((c1 - c0, len(slots), 3))  # [n_c, L, 3] sample positions
            for s, (li, j) in enumerate(slots):
                light = lights[li]
                if isinstance(light, LightBar):
                    t = (j + jitter[li][c0:c1, j]) / samples - 0.5  # [n_c]
                    pos[:, s] = light.center_world + (t * light.length_m)[:, None] * light.axis_world
                else:
                    pos[:, s] = light.position_world
            p_hit = hits.position[c0:c1]
            to_light = pos - p_hit[:, None, :]  # [n_c, L, 3]
            r2 = np.einsum("nlc,nlc->nl", to_light, to_light)
            r = np.sqrt(r2)
            l = to_light / r[..., None]
            cos_i = np.einsum("nlc,nc->nl", l, hits.normal[c0:c1])
            cos_e = np.where(has_emit[None], -np.einsum("nlc,lc->nl", l, emit_l), 1.0)
            ni, si = np.nonzero((cos_i > 0) & (cos_e > 0))
            rays += len(ni)
            origin = p_hit[ni] + _SHADOW_OFFSET_M * hits.geo_normal[c0:c1][ni]
            vis = ~geom.occluded(origin, l[ni, si], r[ni, si] - 2 * _SHADOW_OFFSET_M)
            ni, si = ni[vis], si[vis]
            hi = ni + c0
            irr = (cos_e[ni, si] * cos_i[ni, si] / r2[ni, si])[:, None] * intensity_l[si]  # [M, 3]
            shaded = _ggx_shade(hits.normal[hi], hits.view[hi], hits.albedo[hi], hits.roughness[hi], hits.f0[hi],
                                l[ni, si], irr)
            for ch in range(3):
                out[c0:c1, ch] += np.bincount(ni, weights=shaded[:, ch], minlength=c1 - c0)
        return out, rays


def _sample_atlas(subject: Subject, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Bilinear lookup of albedo [N, 3], roughness [N], F0 [N] at UV [N, 2] (u in [0, 2])."""
    hgt, wid = subject.roughness_atlas.shape
    x = np.clip(uv[:, 0] / 2.0, 0, 1) * wid - 0.5
    y = np.clip(1.0 - uv[:, 1], 0, 1) * hgt - 0.5
    x0 = np.clip(np.floor(x).astype(int), 0, wid - 2)
    y0 = np.clip(np.floor(y).astype(int), 0, hgt - 2)
    fx = np.clip(x - x0, 0, 1)[:, None]
    fy = np.clip(y - y0, 0, 1)[:, None]

    def lerp(img: np.ndarray) -> np.ndarray:
        im = img if img.ndim == 3 else img[..., None]
        top = im[y0, x0] * (1 - fx) + im[y0, x0 + 1] * fx
        bot = im[y0 + 1, x0] * (1 - fx) + im[y0 + 1, x0 + 1] * fx
        return top * (1 - fy) + bot * fy

    return lerp(subject.albedo_atlas), lerp(subject.roughness_atlas)[:, 0], lerp(subject.specular_atlas)[:, 0]


def _eye_albedo(subject: Subject, position: np.ndarray, centre: np.ndarray, gaze: np.ndarray) -> np.ndarray:
    """Sclera / iris / pupil albedo [N, 3] from the angle between (hit - eye centre) and the gaze."""
    d = position - centre
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    cos_a = np.einsum("ij,ij->i", d, gaze)
    angle = np.degrees(np.arccos(np.clip(cos_a, -1, 1)))
    sclera = np.array([0.70, 0.66, 0.60])
    iris = subject.iris_albedo
    pupil = np.array([0.01, 0.01, 0.01])
    # Smooth transitions (a few degrees) so the limbus is not aliased.
    t_iris = np.clip((33.0 - angle) / 3.0, 0, 1)[:, None]
    t_pupil = np.clip((13.0 - angle) / 2.0, 0, 1)[:, None]
    limbus = 1.0 - 0.5 * np.exp(-0.5 * ((angle - 31.0) / 2.0) ** 2)[:, None]
    col = sclera * (1 - t_iris) + iris * limbus * t_iris
    return col * (1 - t_pupil) + pupil * t_pupil


def reference_local_lights(studio: VirtualStudio, geom: FrameGeometry, hits: _Hits, lights: Sequence[Light],
                           samples: int, seed: tuple[int, int, int]) -> np.ndarray:
    """Slow, obvious version of ``VirtualStudio._local_lights``: one light, one sample, one hit at a time.

    Uses the same jitter, so the two agree to rounding (tests hold them together).
    """
    n = len(hits.pixel)
    out = np.zeros((n, 3))
    for li, light in enumerate(lights):
        if isinstance(light, LightBar):
            jitter = np.random.default_rng([*seed, li, 17]).uniform(size=(n, samples))
            points = [[light.center_world + ((j + jitter[i, j]) / samples - 0.5) * light.length_m * light.axis_world
                       for j in range(samples)] for i in range(n)]
            power = np.full(3, light.intensity * studio.settings.bar_intensity_scale / samples)
            emit_n = light.normal_world
        elif isinstance(light, PointLight):
            points = [[light.position_world] for _ in range(n)]
            power, emit_n = light.intensity_rgb, light.normal_world
        else:
            continue
        for i in range(n):
            for p in points[i]:
                to_light = p - hits.position[i]
                r = float(np.linalg.norm(to_light))
                l = to_light / r
                cos_i = float(hits.normal[i] @ l)
                cos_e = 1.0 if emit_n is None else float(-(l @ emit_n))
                if cos_i <= 0 or cos_e <= 0:
                    continue
                origin = hits.position[i] + _SHADOW_OFFSET_M * hits.geo_normal[i]
                if geom.occluded(origin[None], l[None], np.array([r - 2 * _SHADOW_OFFSET_M]))[0]:
                    continue
                irr = power * cos_e * cos_i / r ** 2
                out[i] += _ggx_shade(hits.normal[i:i + 1], hits.view[i:i + 1], hits.albedo[i:i + 1],
                                     hits.roughness[i:i + 1], hits.f0[i:i + 1], l[None], irr[None])[0]
    return out
