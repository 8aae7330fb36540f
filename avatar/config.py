"""Typed, frozen configuration of the relightable MVP head (sizes, layout, rendering)."""

from __future__ import annotations

import math
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator


class AvatarConfig(BaseModel):
    """Sizes of the relightable MVP model; ``paper()`` is Xu et al.'s configuration."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    prims_per_side: int = Field(16, description="N: primitives per side of the UV grid (N^2 primitives); a power of two >= 8.")
    voxels_per_side: int = Field(4, description="M: voxels per primitive side (M^3 RGBA voxels, M_z = M); a power of two.")
    latent_dim: int = Field(64, description="Size of the mesh encoder's latent code z.")
    encoder_hidden: int = Field(128, description="Width of the mesh encoder's hidden layers.")
    base_channels: int = Field(64, description="Channels C of the C x 8 x 8 feature map the MLP decodes z into.")
    rgb_channels: tuple[int, ...] = Field(
        (48, 32, 12),
        description="Output channels of the appearance branch's transposed convs, one per layer; "
                    "log2(N*M/8) layers, the last = 3*M (rgb x M_z).")
    alpha_channels: tuple[int, ...] = Field(
        (32, 16, 4),
        description="Output channels of the opacity branch's transposed convs; the last = M.")
    geometry_channels: int = Field(32, description="Hidden channels of the primitive position/rotation/scale delta branch.")
    steps_per_ray: int = Field(32, description="Raymarch samples per ray over its span through the union of primitive boxes.")
    prim_overlap: float = Field(1.6, description="Primitive edge length as a multiple of the spacing of neighbouring guide points.")
    layout_theta_deg: float = Field(105.0, description="Half-width, in degrees around +z, of the UV layout over the head. "
                                    "Widen it if renders leave the shoulders or the back of the neck transparent: the "
                                    "grid's side columns then reach them from the start (the tiny preset uses 120, which "
                                    "raised ours' validation PSNR; docs/experiments.md, section 39). Wider spreads the "
                                    "same N x N boxes thinner over the face.")
    layout_projection: Literal["latlong", "azimuthal"] = Field(
        "latlong",
        description="How the N x N grid maps onto the head (avatar.layout.grid_directions): 'latlong' (rows of "
                    "equal elevation, pole straight up, crown above the top row left out) or 'azimuthal' "
                    "(equidistant map centred in front at layout_centre_elevation_deg, reaching over the crown). "
                    "Keep 'latlong' unless you are experimenting with covering the crown: 'azimuthal' was less "
                    "accurate on the tiny preset (docs/experiments.md, section 3).")
    layout_elevation_deg: tuple[float, float] = Field(
        (-75.0, 70.0), description="Bottom and top of the grid in degrees of elevation (along the central meridian "
                                   "for 'azimuthal', where a top above 90 reaches over the crown towards the back).")
    layout_centre_elevation_deg: float = Field(0.0, description="'azimuthal' only: elevation of the map's centre.")
    direction_frame: Literal["world", "primitive"] = Field(
        "world",
        description="Axes in which the per-primitive view and light directions are fed to the appearance branch: "
                    "'world' (head space, as the paper) or 'primitive' (each primitive's own rotated axes, so the "
                    "cosine to the surface normal is one input channel everywhere on the UV layout). Both models' "
                    "view directions follow it. The same vectors either way. 'world', the paper's, is the default; "
                    "'primitive' gained nothing when measured over seeds, on test figures (docs/experiments.md, "
                    "section 1) and on validation (section 30).")
    untied_bias: bool = Field(False, description="Every transposed conv of the decoder branches also adds a learnt "
                              "bias per output pixel (MVP's untied biases): each texel's static colour and opacity "
                              "is a parameter of its own. Both models alike. Off by default: on the tiny preset it "
                              "lowered ours on validation on every seed measured (docs/experiments.md, section 25).")
    light_basis: int = Field(0, description="TRAvatar*: number of training lights in the fixed one-hot light basis (0 = ours).")

    @model_validator(mode="after")
    def _check(self) -> "AvatarConfig":
        n, m = self.prims_per_side, self.voxels_per_side
        if n < 8 or n & (n - 1):
            raise ValueError(f"prims_per_side={n}: must be a power of two >= 8")
        if m < 2 or m & (m - 1):
            raise ValueError(f"voxels_per_side={m}: must be a power of two >= 2")
        layers = self.appearance_layers
        for key, chans, last in (("rgb_channels", self.rgb_channels, 3 * m), ("alpha_channels", self.alpha_channels, m)):
            if len(chans) != layers or chans[-1] != last:
                raise ValueError(f"{key}={list(chans)}: need {layers} layers (log2(N*M/8) for N={n}, M={m}) "
                                 f"ending in {last}")
        return self

    @property
    def num_prims(self) -> int:
        """N^2."""
        return self.prims_per_side ** 2

    @property
    def appearance_layers(self) -> int:
        """Transposed convs from 8 x 8 to N*M x N*M."""
        return int(round(math.log2(self.prims_per_side * self.voxels_per_side / 8)))

    @property
    def geometry_layers(self) -> int:
        """Transposed convs from 8 x 8 to N x N."""
        return int(round(math.log2(self.prims_per_side / 8)))

    @staticmethod
    def paper() -> "AvatarConfig":
        """The CVPR 2024 paper's configuration: N=64, M=16, z=256, channels 256..48."""
        return AvatarConfig(prims_per_side=64, voxels_per_side=16, latent_dim=256, encoder_hidden=256,
                            base_channels=256, rgb_channels=(256, 128, 128, 64, 64, 32, 48),
                            alpha_channels=(256, 128, 128, 64, 64, 32, 16), geometry_channels=64,
                            steps_per_ray=128, prim_overlap=1.6)

    @staticmethod
    def tiny() -> "AvatarConfig":
        """A CPU-sized model: N=16, M=4 (64 x 64 UV maps, enough for ~64 px wide images), narrow channels."""
        return AvatarConfig()
