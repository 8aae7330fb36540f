"""The relightable MVP head: mesh encoder (VAE), geometry branch, relightable appearance and opacity.

Shapes: B = batch, U = guide vertices, P = N^2 primitives, M = voxels per side.
Everything lives in head space (metres); ``cam_pos`` and ``light_pos`` are head-space points.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from avatar.config import AvatarConfig
from avatar.layout import GuideLayout
from avatar.raymarch import Primitives

#: Sigmoid input giving a scale of 1.1 x the base size at initialisation.
_SCALE_INIT = float(np.log(0.1 / 0.9))

#: softplus(-2) ~ 0.13: initial density = 0.13 / base half size.
_ALPHA_INIT = -2.0

#: Vertex offsets are fed to and decoded from the networks in centimetres (values O(1)).
OFFSET_SCALE_M = 0.01


class MeshEncoder(nn.Module):
    """Deep-Appearance-Model style geometry encoder: guide-vertex offsets -> (mu, logvar) of z."""

    def __init__(self, num_vertices: int, hidden: int, latent_dim: int) -> None:
        super().__init__()
        self.net = nn.Sequential(nn.Linear(3 * num_vertices, hidden), nn.LeakyReLU(0.2),
                                 nn.Linear(hidden, hidden), nn.LeakyReLU(0.2))
        self.mu = nn.Linear(hidden, latent_dim)
        self.logvar = nn.Linear(hidden, latent_dim)
        nn.init.zeros_(self.logvar.weight)
        nn.init.constant_(self.logvar.bias, -4.0)

    def forward(self, offsets_cm: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``offsets_cm`` [B, U, 3] -> mu [B, Z], logvar [B, Z]."""
        h = self.net(offsets_cm.flatten(1))
        return self.mu(h), self.logvar(h)


class _UpBranch(nn.Module):
    """Transposed convs (k4 s2 p1) from 8 x 8 up, each fed the conditioning image at its input size.

    With ``untied_bias`` every layer also adds a bias of its own per output pixel (MVP's
    untied biases): a texel's static part (its mean colour, its usual opacity) is then one
    parameter, not something the shared kernels must compose from the 8 x 8 feature map.
    The untied biases start at zero, so the branch starts as without them.
    """

    def __init__(self, in_channels: int, channels: tuple[int, ...], cond_channels: int,
                 untied_bias: bool = False) -> None:
        super().__init__()
        self.cond_channels = cond_channels
        layers, c_in = [], in_channels
        for c_out in channels:
            layers.append(nn.ConvTranspose2d(c_in + cond_channels, c_out, 4, 2, 1))
            c_in = c_out
        self.layers = nn.ModuleList(layers)
        self.untied = nn.ParameterList(
            [nn.Parameter(torch.zeros(1, c, 8 << (i + 1), 8 << (i + 1))) for i, c in enumerate(channels)]
            if untied_bias else [])

    def forward(self, feature: torch.Tensor, cond: "callable | None" = None) -> torch.Tensor:
        """``feature`` [B, C, 8, 8]; ``cond(size)`` -> [B, cond_channels, size, size]. Output before the last activation."""
        x = feature
        for i, layer in enumerate(self.layers):
            if self.cond_channels:
                x = torch.cat([x, cond(x.shape[-1])], 1)
            x = layer(x)
            if self.untied:
                x = x + self.untied[i]
            if i < len(self.layers) - 1:
                x = F.leaky_relu(x, 0.2)
        return x


@dataclass
class DecodedGeometry:
    """The light-independent part of a decoded frame: boxes, densities, guide mesh and the shared feature."""

    centre: torch.Tensor  # [B, P, 3]
    rotation: torch.Tensor  # [B, P, 3, 3]
    half_extent: torch.Tensor  # [B, P, 3]
    density: torch.Tensor  # [B, P, M, M, M]
    guide_vertices: torch.Tensor  # [B, U, 3]
    feature: torch.Tensor  # [B, C, 8, 8]
    keep: torch.Tensor | None = None  # [P'] long: primitives left after pruning (None = all)
    # The alpha branch's output before the softplus [B, M_z, N*M, N*M], for the trainer's opacity
    # floor (``opacity_floor_penalty``); the copies below leave it out (rendering never reads it).
    raw_alpha: torch.Tensor | None = None

    def expand(self, k: int) -> "DecodedGeometry":
        """A batch-1 geometry repeated ``k`` times (views, no copy), e.g. to decode k lights at once."""
        return DecodedGeometry(*(t.expand(k, *t.shape[1:]) for t in (
            self.centre, self.rotation, self.half_extent, self.density, self.guide_vertices, self.feature)),
            keep=self.keep)

    def repeat(self, k: int) -> "DecodedGeometry":
        """Every item repeated ``k`` times in a row (copies: [B] -> [B * k], item-major), e.g. k basis lights per item."""
        return DecodedGeometry(*(t.repeat_interleave(k, 0) for t in (
            self.centre, self.rotation, self.half_extent, self.density, self.guide_vertices, self.feature)),
            keep=self.keep)

    def primitives(self, rgb: torch.Tensor) -> Primitives:
        """Assemble raymarchable primitives with colours ``rgb`` [B, P, M, M, M, 3].

        Pruned primitives (see ``RelightableMVP.prune``) are left out, so the raymarcher
        never tests rays against them.
        """
        if self.keep is None:
            return Primitives(self.centre, self.rotation, self.half_extent, rgb, self.density)
        k = self.keep
        return Primitives(self.centre[:, k], self.rotation[:, k], self.half_extent[:, k], rgb[:, k],
                          self.density[:, k])


def _rodrigues(rotvec: torch.Tensor) -> torch.Tensor:
    """Axis-angle [..., 3] -> rotation matrices [..., 3, 3] (smooth at 0)."""
    theta2 = (rotvec * rotvec).sum(-1, keepdim=True)[..., None]  # [..., 1, 1]
    theta = torch.sqrt(theta2 + 1e-12)
    x, y, z = rotvec.unbind(-1)
    zero = torch.zeros_like(x)
    k = torch.stack([zero, -z, y, z, zero, -x, -y, x, zero], -1).reshape(*rotvec.shape[:-1], 3, 3)
    eye = torch.eye(3, dtype=rotvec.dtype, device=rotvec.device).expand_as(k)
    a = torch.sin(theta) / theta
    b = (1.0 - torch.cos(theta)) / (theta2 + 1e-12)
    return eye + a * k + b * (k @ k)


class RelightableMVP(nn.Module):
    """Relightable mixture of volumetric primitives (Xu et al. 2024 on top of MVP).

    ``config.light_basis == 0``: the paper's model, appearance conditioned on the 6-channel
    image of per-primitive view and light directions. ``config.light_basis == L > 0``: the
    TRAvatar* baseline's network, conditioned on the view directions and on L light-basis
    weights (see ``avatar.travatar``).
    """

    def __init__(self, config: AvatarConfig, layout: GuideLayout, num_bars: int) -> None:
        super().__init__()
        self.config = config
        n, m = config.prims_per_side, config.voxels_per_side
        for name, arr in layout.as_arrays().items():
            tensor = torch.as_tensor(arr)
            # The networks run in float32: a float64 array (e.g. a basis straight from numpy) is stored as one.
            self.register_buffer(name, tensor.float() if tensor.is_floating_point() else tensor)
        self.num_guide_vertices = int(layout.mean_guide_vertices.shape[0])
        self.encoder = MeshEncoder(self.num_guide_vertices, config.encoder_hidden, config.latent_dim)
        self.mesh_decoder = nn.Sequential(nn.Linear(config.latent_dim, config.encoder_hidden), nn.LeakyReLU(0.2),
                                          nn.Linear(config.encoder_hidden, 3 * self.num_guide_vertices))
        c = config.base_channels
        self.feature_mlp = nn.Sequential(nn.Linear(config.latent_dim, c * 64), nn.LeakyReLU(0.2))
        cond = 6 if config.light_basis == 0 else 3 + config.light_basis
        untied = config.untied_bias
        self.rgb_branch = _UpBranch(c, config.rgb_channels, cond, untied)
        self.alpha_branch = _UpBranch(c, config.alpha_channels, 0, untied)
        geo_channels = (config.geometry_channels,) * config.geometry_layers
        self.geometry_branch = _UpBranch(c, geo_channels, 0, untied) if geo_channels else None
        self.geometry_head = nn.Conv2d(geo_channels[-1] if geo_channels else c, 9, 1)
        nn.init.zeros_(self.geometry_head.weight)
        nn.init.zeros_(self.geometry_head.bias)
        nn.init.constant_(self.rgb_branch.layers[-1].bias, 0.05)
        # Start semi-transparent (a ray through one box gathers ~0.3 opacity): a saturated ray
        # has no opacity gradient, so boxes that start opaque where the matte is empty could
        # never be cleared by the matte loss.
        nn.init.constant_(self.alpha_branch.layers[-1].bias, _ALPHA_INIT)
        self.log_bar_intensity = nn.Parameter(torch.zeros(num_bars))
        self.density_scale = float(1.0 / float(np.mean(layout.half_extent_m)))
        self.n, self.m = n, m
        # Primitives still raymarched (False = pruned as empty); saved with the weights.
        self.register_buffer("prim_keep", torch.ones(n * n, dtype=torch.bool))
        self._register_load_state_dict_pre_hook(self._default_prim_keep)
        # Training only (the trainer sets it from ``train.loss_weights.lift``; never saved): opacity
        # logits under this value answer pulls towards more opacity with the softplus' slope here
        # (``lifted_softplus``). None = the plain softplus. The forward pass is the same either way.
        self.lift_below_logit: float | None = None

    def _default_prim_keep(self, state_dict, prefix, *args, **kwargs) -> None:
        """Heads saved before pruning existed have no ``prim_keep``: every primitive is kept."""
        state_dict.setdefault(prefix + "prim_keep", torch.ones(self.n * self.n, dtype=torch.bool))

    # ---- pruning -------------------------------------------------------------------------
    def prune(self, keep: torch.Tensor) -> int:
        """Drop the primitives where ``keep`` [P] (bool) is False from rendering; returns how many are pruned now.

        Pruning only accumulates (a pruned primitive never comes back). The decoder still
        computes every primitive's voxels (they are pixels of one UV image); the raymarcher,
        whose cost grows with the number of boxes, skips them.
        """
        keep = keep.to(device=self.prim_keep.device, dtype=torch.bool).reshape(-1)
        if keep.numel() != self.prim_keep.numel():
            raise ValueError(f"prune: keep has {keep.numel()} entries for {self.prim_keep.numel()} primitives")
        with torch.no_grad():
            self.prim_keep &= keep
        return int((~self.prim_keep).sum())

    @property
    def num_pruned(self) -> int:
        """Primitives pruned so far."""
        return int((~self.prim_keep).sum())

    def kept_index(self) -> torch.Tensor | None:
        """Indices [P'] of the primitives still rendered, or None when none is pruned."""
        if bool(self.prim_keep.all()):
            return None
        return torch.nonzero(self.prim_keep, as_tuple=True)[0]

    # ---- encoder -------------------------------------------------------------------------
    def guide_vertices_of(self, mesh_vertices: torch.Tensor) -> torch.Tensor:
        """Guide vertices [B, U, 3] of full tracked meshes [B, V, 3] (or of guide meshes, passed through)."""
        if mesh_vertices.shape[1] == self.num_guide_vertices:
            return mesh_vertices
        return mesh_vertices[:, self.guide_vertex_ids]

    def encode(self, mesh_vertices: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Tracked meshes [B, V, 3] (head space, metres) -> mu, logvar [B, Z].

        With the layout's expression basis the offsets are first projected onto it.
        """
        offsets = (self.guide_vertices_of(mesh_vertices) - self.mean_guide_vertices) / OFFSET_SCALE_M
        basis = getattr(self, "expression_basis", None)
        if basis is not None:
            flat = offsets.flatten(1)
            offsets = ((flat @ basis.T) @ basis).view_as(offsets)
        return self.encoder(offsets)

    # ---- decoder -------------------------------------------------------------------------
    def decode_geometry(self, z: torch.Tensor) -> DecodedGeometry:
        """Latent codes [B, Z] -> primitive boxes and densities (both independent of light and view)."""
        b, n, m = z.shape[0], self.n, self.m
        verts = self.mean_guide_vertices + OFFSET_SCALE_M * self.mesh_decoder(z).view(b, -1, 3)  # [B, U, 3]
        tri = verts[:, self.anchor_tris]  # [B, P, 3, 3]
        base = (tri * self.anchor_bary[None, :, :, None]).sum(2)  # [B, P, 3]
        e1, e2 = tri[:, :, 1] - tri[:, :, 0], tri[:, :, 2] - tri[:, :, 0]
        normal = F.normalize(torch.cross(e1, e2, dim=-1), dim=-1, eps=1e-12) * self.normal_sign[:, None]
        tangent = F.normalize(e1 - (e1 * normal).sum(-1, keepdim=True) * normal, dim=-1, eps=1e-12)
        bitangent = torch.cross(normal, tangent, dim=-1)
        tbn = torch.stack([tangent, bitangent, normal], -1)  # [B, P, 3, 3] head_from_tbn (columns)
        feature = self.feature_mlp(z).view(b, -1, 8, 8)
        g = feature if self.geometry_branch is None else F.leaky_relu(self.geometry_branch(feature), 0.2)
        delta = self.geometry_head(g).flatten(2).transpose(1, 2)  # [B, P, 9], P in row-major grid order
        half0 = self.half_extent_m[None, :, None]  # [1, P, 1]
        # Position deltas, in the primitive's tangent frame, are bounded to one base half size so
        # a primitive stays attached to its patch of the guide mesh.
        centre = base + (tbn @ (torch.tanh(delta[..., :3, None]) * half0[..., None]))[..., 0]
        rotation = tbn @ _rodrigues(delta[..., 3:6])
        # Scales stay within [1, 2] x the base size (which overlaps the neighbours by
        # prim_overlap). The grid at its base size leaves the edges of the layout (shoulders,
        # back of the head) partly outside every box: a volume prior strong enough to press every
        # box to its base opens holes there (share_of_boxes_at_smallest).
        half_extent = half0 * (1.0 + torch.sigmoid(delta[..., 6:9] + _SCALE_INIT))
        raw_alpha = self.alpha_branch(feature)  # [B, M_z, N*M, N*M]
        if self.lift_below_logit is None:
            density = F.softplus(raw_alpha) * self.density_scale
        else:
            density = lifted_softplus(raw_alpha, self.lift_below_logit) * self.density_scale
        density = density.view(b, m, n, m, n, m).permute(0, 2, 4, 1, 3, 5).reshape(b, n * n, m, m, m)
        return DecodedGeometry(centre, rotation, half_extent, density, verts, feature, keep=self.kept_index(),
                               raw_alpha=raw_alpha)

    def _tile(self, per_prim: torch.Tensor) -> torch.Tensor:
        """Per-primitive values [B, P, C] -> UV image [B, C, N*M, N*M], constant over each M x M tile."""
        b, _, c = per_prim.shape
        img = per_prim.transpose(1, 2).reshape(b, c, self.n, self.n)
        return img.repeat_interleave(self.m, 2).repeat_interleave(self.m, 3)

    def _to_voxels(self, raw_rgb: torch.Tensor) -> torch.Tensor:
        """[B, 3*M, N*M, N*M] (channel = z*3 + rgb) -> [B, P, M, M, M, 3]."""
        b, n, m = raw_rgb.shape[0], self.n, self.m
        return raw_rgb.view(b, m, 3, n, m, n, m).permute(0, 3, 5, 1, 4, 6, 2).reshape(b, n * n, m, m, m, 3)

    def _directions(self, geometry: DecodedGeometry, points: torch.Tensor) -> torch.Tensor:
        """Unit directions [B, P, 3] from each primitive centre to ``points`` [B, 3], in ``config.direction_frame``."""
        d = F.normalize(points[:, None] - geometry.centre, dim=-1)  # [B, P, 3] head space
        if self.config.direction_frame == "primitive":
            # R_k^T d: the primitive's axes are its guide triangle's tangent frame (plus the learnt
            # rotation), so the third component is the cosine to the surface normal.
            d = (d[..., None, :] * geometry.rotation.transpose(-1, -2)).sum(-1)  # [B, P, 3]
        return d

    def direction_image(self, geometry: DecodedGeometry, cam_pos: torch.Tensor, light_pos: torch.Tensor) -> torch.Tensor:
        """The paper's conditioning image I [B, 6, N*M, N*M]: unit v_k = p_cam - c_k and l_k = p_light - c_k."""
        view = self._directions(geometry, cam_pos)  # [B, P, 3]
        light = self._directions(geometry, light_pos)  # [B, P, 3]
        return self._tile(torch.cat([view, light], -1))

    def decode_rgb(self, geometry: DecodedGeometry, cam_pos: torch.Tensor, light_pos: torch.Tensor | None = None,
                   light_weights: torch.Tensor | None = None, intensity: torch.Tensor | None = None) -> torch.Tensor:
        """RGB voxels [B, P, M, M, M, 3] for cameras at ``cam_pos`` [B, 3] under one light per item.

        Ours: ``light_pos`` [B, 3] (head space). TRAvatar*: ``light_weights`` [B, L] over its light
        basis. ``intensity`` [B] scales the result (e.g. ``bar_intensity(bar_ids)``).
        """
        if self.config.light_basis == 0:
            if light_pos is None:
                raise ValueError("decode_rgb: the relightable model needs light_pos [B, 3]")
            image = self.direction_image(geometry, cam_pos, light_pos)  # [B, 6, NM, NM]

            def cond(size: int) -> torch.Tensor:
                return F.interpolate(image, size=(size, size), mode="bilinear", antialias=True, align_corners=False)
        else:
            if light_weights is None:
                raise ValueError("decode_rgb: the TRAvatar* model needs light_weights [B, L]")
            view = self._tile(self._directions(geometry, cam_pos))  # [B, 3, NM, NM]

            def cond(size: int) -> torch.Tensor:
                v = F.interpolate(view, size=(size, size), mode="bilinear", antialias=True, align_corners=False)
                w = light_weights[:, :, None, None].expand(-1, -1, size, size)
                return torch.cat([v, w], 1)
        rgb = F.relu(self.rgb_branch(geometry.feature, cond))
        if intensity is not None:
            rgb = rgb * intensity[:, None, None, None]
        return self._to_voxels(rgb)

    def bar_intensity(self, bar_index: torch.Tensor) -> torch.Tensor:
        """Learnt intensity [B] of LED bars ``bar_index`` [B] (an index < 0, a novel light, gets 1)."""
        known = bar_index >= 0
        scale = torch.exp(self.log_bar_intensity[bar_index.clamp(min=0)])
        return torch.where(known, scale, torch.ones_like(scale))

    def volume_ratio(self, geometry: DecodedGeometry) -> torch.Tensor:
        """Each box's volume over its base volume [B, P] (1 = the smallest a box can be)."""
        base = (self.half_extent_m ** 3)[None]  # [1, P]
        return geometry.half_extent.prod(-1) / base

    def volume_prior(self, geometry: DecodedGeometry) -> torch.Tensor:
        """MVP's volume loss: mean over the batch of the summed primitive volumes (in units of the base volume)."""
        return self.volume_ratio(geometry).sum(-1).mean() / self.half_extent_m.numel()


#: The opacity floor's logit: ``softplus``'s slope there is 3.4e-4 (at -18, where training
#: without the floor leaves many voxels, it is 1.5e-8), while a box whose voxels all sit there
#: adds an optical depth of about 7e-4 to a ray: far under the pruning's 0.01, and no visible haze.
OPACITY_FLOOR_LOGIT = -8.0


class _LiftedSoftplus(torch.autograd.Function):
    """``softplus`` whose backward gives logits under ``floor`` the slope at ``floor`` when the pull is upwards."""

    @staticmethod
    def forward(ctx, raw: torch.Tensor, floor: float) -> torch.Tensor:
        ctx.save_for_backward(raw)
        ctx.floor = floor
        return F.softplus(raw)

    @staticmethod
    def backward(ctx, grad: torch.Tensor) -> tuple[torch.Tensor, None]:
        (raw,) = ctx.saved_tensors
        # grad < 0: a descent step raises the logit (the loss wants more opacity there).
        lifted = (raw < ctx.floor) & (grad < 0)
        slope = torch.sigmoid(raw).masked_fill(lifted, 1.0 / (1.0 + math.exp(-ctx.floor)))  # softplus' slope, lifted
        return grad * slope, None


def lifted_softplus(raw_alpha: torch.Tensor, floor: float = OPACITY_FLOOR_LOGIT) -> torch.Tensor:
    """``softplus(raw_alpha)``, with a surrogate gradient for logits on its flat tail (not the paper's).

    The value is the softplus' own. In the backward pass, a logit under ``floor`` whose loss
    gradient asks for more opacity gets the softplus' slope at ``floor`` (3.4e-4 at -8) instead of
    its own, which vanishes (1.5e-8 at -18, 1e-21 at -48); a pull towards less opacity keeps the
    true slope. So a voxel that went transparent where the head is solid still hears the
    photometric and matte losses and can refill (a hole, docs/experiments.md, section 34), while
    nothing holds the logits of empty space up, as ``opacity_floor_penalty`` does.
    """
    return _LiftedSoftplus.apply(raw_alpha, float(floor))


def opacity_floor_penalty(raw_alpha: torch.Tensor, floor: float = OPACITY_FLOOR_LOGIT) -> torch.Tensor:
    """Mean squared distance of the opacity logits ``raw_alpha`` below ``floor`` (0 where none is below).

    Why: the matte loss is an L1, whose pull towards zero opacity does not fade as the opacity
    vanishes, so outside the head it drives the logits ever lower, and the shared kernels carry
    that into neighbouring voxels of the head. Below about -10 the softplus is flat: a voxel
    there no longer answers the photometric loss, and a patch of them is a hole that stays
    open (docs/experiments.md, section 34). The floor keeps every logit where it can still learn.
    """
    return F.relu(floor - raw_alpha).pow(2).mean()


@torch.no_grad()
def _prior_mean_geometry(model: RelightableMVP) -> DecodedGeometry:
    """``model``'s decoded geometry at the latent prior's mean (z = 0), batch of one."""
    return model.decode_geometry(torch.zeros(1, model.config.latent_dim, device=model.prim_keep.device))


def share_below_floor(model: RelightableMVP, floor: float = OPACITY_FLOOR_LOGIT) -> float:
    """Share of ``model``'s opacity logits under ``floor`` at the latent prior's mean (z = 0).

    Logits there sit on the softplus' flat tail: a large share is how a run that left holes in
    the head can show, whether or not the floor penalty was on (docs/experiments.md, section 34).
    """
    raw = _prior_mean_geometry(model).raw_alpha
    return float((raw < floor).float().mean())


#: A box within this fraction of its base volume counts as pressed to its smallest size.
SMALLEST_BOX_TOLERANCE = 0.01


def share_of_boxes_at_smallest(model: RelightableMVP, tolerance: float = SMALLEST_BOX_TOLERANCE) -> float:
    """Share of ``model``'s kept boxes whose volume at the latent prior's mean (z = 0) is within ``tolerance``
    of their base volume, the smallest a box can have.

    A box's half-extent is ``base * (1 + sigmoid(delta))``: it can only grow from its base, and the
    sigmoid is flat where the volume prior presses it, so a box held there hardly answers a ray asking
    it to reach further. When nearly every box sits there, the boxes at the layout's edges cannot
    stretch over the shoulders and the back of the head, and the run leaves them transparent
    (docs/experiments.md, section 37).
    """
    ratio = model.volume_ratio(_prior_mean_geometry(model))[0]  # [P]
    return float((ratio[model.prim_keep] < 1.0 + tolerance).float().mean())


def latent_noise_to_code_spread(model: RelightableMVP, mesh_vertices: torch.Tensor) -> float:
    """How much of the code the decoder trains on is the encoder's noise, over the frames of ``mesh_vertices``.

    The trainer decodes ``z = mu + sigma * eps``: the mean noise ``sigma`` (over frames and the
    code's dimensions) over the mean spread of the codes ``mu`` (their standard deviation over the
    frames, per dimension). Over 1, a training code is more the seed's noise draw than the
    expression it encodes; the KL weight (``train.loss_weights.kld``) sets it. NaN with fewer
    than 2 frames.

    Args:
        mesh_vertices: [F, V, 3] tracked (or guide) meshes in head space, metres, as the trainer encodes them.
    """
    if mesh_vertices.shape[0] < 2:
        return float("nan")
    with torch.no_grad():
        mu, logvar = model.encode(mesh_vertices)
    spread = mu.std(0).mean()
    return float(torch.exp(0.5 * logvar).mean() / spread.clamp(min=1e-12))


def kl_divergence(mu: torch.Tensor, logvar: torch.Tensor) -> torch.Tensor:
    """KL(q(z|x) || N(0, I)), averaged over the batch and latent dimensions."""
    return 0.5 * (mu.pow(2) + logvar.exp() - 1.0 - logvar).mean()


def count_parameters(model: nn.Module) -> int:
    """Number of trainable parameters."""
    return sum(p.numel() for p in model.parameters() if p.requires_grad)


__all__ = ["RelightableMVP", "DecodedGeometry", "MeshEncoder", "kl_divergence", "count_parameters",
           "opacity_floor_penalty", "share_below_floor", "share_of_boxes_at_smallest", "lifted_softplus",
           "latent_noise_to_code_spread",
           "OPACITY_FLOOR_LOGIT", "SMALLEST_BOX_TOLERANCE"]
