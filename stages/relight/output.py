"""The relight stage's output folder: the one place that spells its file names.

Files (every sequence in its own folder)::

    <sequence>/frames/<i:06d>.exr     linear RGBA (float16), head at the origin, black backdrop
    <sequence>/previews/<i:06d>.png   sRGB preview
    <sequence>/<sequence>.mp4         the previews as a video
    renders.json                      per sequence and frame: camera, lights, mesh index, map
    meshes.npz                        the driving meshes used ("default": [1, V, 3], "expressions")

``relight_eval`` writes ``truth/<sequence>/<i:06d>.exr`` and ``compare/<sequence>_<i>.png``
(``RelightEvalOutput``). A missing or malformed file raises one ``InputError`` naming it and
saying to rerun relight.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from pipeline.stage_output import StageOutput

_RENDERS = "renders.json"
_PATHS = "paths.json"
_MESHES = "meshes.npz"
_FRAMES = "frames"
_PREVIEWS = "previews"
_VIDEO_SUFFIX = ".mp4"
_EVAL_TRUTH = "truth"
_EVAL_COMPARE = "compare"

#: The names no module outside ``stages/relight`` may spell (``tests/test_output_contracts.py``).
CONTRACT_NAMES = (_RENDERS, _MESHES, _FRAMES, _PREVIEWS)


class RelightOutput(StageOutput):
    """The ``relight`` object (and ``pipeline render``'s folder): rendered sequences."""

    stage = "relight"

    def renders(self) -> dict[str, list[dict[str, Any]]]:
        """``renders.json``: sequence name -> per frame its camera, lights, mesh index and map."""
        return self.read_json(_RENDERS)

    def write_renders(self, renders: dict[str, list[dict[str, Any]]]) -> None:
        self.write_json(renders, _RENDERS, indent=1)

    def write_paths(self, paths: dict[str, dict[str, Any]]) -> None:
        """``paths.json``: sequence name -> the render path it took (bake or voxel-space sum), why,
        and its frame count. The report shows any stage's ``paths.json`` (a report convention,
        like ``tradeoffs/``), so the name is not one of this stage's private contract names."""
        self.write_json(paths, _PATHS, indent=1)

    @property
    def meshes_path(self) -> Path:
        return self.file(_MESHES)

    def write_meshes(self, default: np.ndarray, expressions: np.ndarray) -> None:
        np.savez_compressed(self.meshes_path, default=default, expressions=expressions)

    def sequence_dir(self, name: str) -> Path:
        return self.file(name)

    def frames_dir(self, name: str) -> Path:
        return self.file(name, _FRAMES)

    def frame_path(self, name: str, index: int) -> Path:
        """``<name>/frames/<index:06d>.exr``."""
        return self.file(name, _FRAMES, f"{int(index):06d}.exr")

    def frame(self, name: str, index: int) -> np.ndarray:
        """Frame ``index`` of sequence ``name``: linear RGBA [H, W, 4]."""
        from scene.image_io import read_exr

        return self.load(self.frame_path(name, index), read_exr)

    def previews_dir(self, name: str) -> Path:
        return self.file(name, _PREVIEWS)

    def preview_path(self, name: str, index: int) -> Path:
        return self.file(name, _PREVIEWS, f"{int(index):06d}.png")

    def video_path(self, name: str) -> Path:
        return self.file(name, f"{name}{_VIDEO_SUFFIX}")


class RelightEvalOutput(StageOutput):
    """The ``relight_eval`` object: the studio's references and truth | relit comparisons."""

    stage = "relight_eval"

    def truth_path(self, name: str, index: int) -> Path:
        return self.file(_EVAL_TRUTH, name, f"{int(index):06d}.exr")

    @property
    def compare_dir(self) -> Path:
        return self.file(_EVAL_COMPARE)

    def compare_path(self, name: str, index: int) -> Path:
        return self.file(_EVAL_COMPARE, f"{name}_{int(index)}.png")

    def figure_path(self, kind: str) -> Path:
        """The comparison figure of one kind of light (``envmap``, ``point``): truth | relit | error."""
        return self.file(_EVAL_COMPARE, f"figure_{kind}.png")

    @property
    def captions_path(self) -> Path:
        return self.file(_EVAL_COMPARE, "captions.json")

    def figures(self) -> list[tuple[Path, str]]:
        """(comparison figure, caption in words) per kind of light; empty when none was written."""
        import json

        try:
            captions = json.loads(self.captions_path.read_text())
        except (OSError, ValueError):
            return []
        return [(self.figure_path(kind), str(c)) for kind, c in captions.items() if self.figure_path(kind).is_file()]
