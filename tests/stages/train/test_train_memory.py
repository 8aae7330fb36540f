"""The projected training memory: the meta-device count equals a real run's, and the paper's figure."""

from __future__ import annotations

import numpy as np
import torch
import trimesh

from avatar.config import AvatarConfig
from avatar.layout import build_layout
from avatar.model import RelightableMVP
from scene.view import ViewSpec
from stages.train.memory import _saved_bytes, decoder_saved_bytes, project_training_memory


def _layout(config: AvatarConfig):
    mesh = trimesh.creation.icosphere(subdivisions=3, radius=0.1)
    return build_layout(np.asarray(mesh.vertices, np.float32), np.asarray(mesh.faces), config.prims_per_side)


def test_the_meta_count_is_what_a_real_decode_saves():
    config = AvatarConfig.tiny()
    layout = _layout(config)
    torch.manual_seed(0)
    model = RelightableMVP(config, layout, 32)

    def run() -> None:
        mu, _ = model.encode(torch.zeros(3, model.num_guide_vertices, 3))
        geometry = model.decode_geometry(mu)
        model.decode_rgb(geometry, torch.zeros(3, 3), torch.ones(3, 3))

    assert decoder_saved_bytes(config, layout, 3) == _saved_bytes(run)


def test_the_papers_configuration_at_batch_12():
    config = AvatarConfig.paper()
    view = ViewSpec(768, 1024, 0.6, 30.0)
    projection = project_training_memory(config, _layout(config), view.camera(view.front_eye()), 12, 8192,
                                         sample_rays=512)
    figures = projection.as_dict()
    # The RGB voxels alone: 12 images x 4096 primitives x 16^3 voxels x 3 colours x 4 bytes = 2.4 GB.
    assert figures["decoder_activations_gb"] > 2.4
    assert 3.0 < figures["projected_peak_gb"] < 139.0  # fits the lent GPU (an H200, ~139 GiB)
    assert figures["raymarch_activations_gb"] > 0 and figures["model_gb"] > 0.1
