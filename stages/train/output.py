"""The train stage's output folder: the one place that spells its file names.

Files::

    models/ours/, models/travatar/   ``avatar.io.save_trained`` folders (``load_trained``)
    splits.json                      test and validation bars / segments, the frames of every split
    learning_curve.png, curve.json   validation-light PSNR against training time
    tradeoffs/learning_curve.json    the same as a report trade-off series
    capacity.json                    the capacity rule's inputs and choice
    table.md                         the paper's table
    previews/<split>_<k>.png         ground truth | ours | TRAvatar*, sRGB, at the training images' size
    comparisons/<split>.png          ground truth | ours | TRAvatar* | their error heat maps, at the capture's size
    comparisons/captions.json        split -> the figure's caption in words
    tensorboard/                     loss terms and validation-light PSNR

A missing or malformed file raises one ``InputError`` naming it and saying to rerun train.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Callable, TypeVar

from pipeline.stage_output import StageOutput

T = TypeVar("T")

_MODELS = "models"
_SPLITS = "splits.json"
_CAPACITY = "capacity.json"
_CURVE_PNG = "learning_curve.png"
_CURVE = "curve.json"
_TRADEOFFS = "tradeoffs"
_CURVE_TRADEOFF = "learning_curve.json"
_TABLE = "table.md"
_PREVIEWS = "previews"
_COMPARISONS = "comparisons"
_CAPTIONS = "captions.json"
_TENSORBOARD = "tensorboard"

#: The names no module outside ``stages/train`` may spell (``tests/test_output_contracts.py``);
#: ``capacity.json`` is also ``benchmarks/bench_capacity.py``'s results file.
CONTRACT_NAMES = (_MODELS, _SPLITS, _CAPACITY, _CURVE_PNG, _CURVE, _TABLE)

#: The output's run records (``Stage.run_records``): wall-clock records, left out of its content key.
RUN_RECORDS = (_CURVE, _CURVE_PNG, f"{_TENSORBOARD}/*", f"{_TRADEOFFS}/{_CURVE_TRADEOFF}")


class TrainOutput(StageOutput):
    """The ``train`` object: the trained heads (ours, TRAvatar*), the splits and the figures."""

    stage = "train"

    def model_dir(self, kind: str = "ours") -> Path:
        """``models/<kind>/``: a head saved by ``avatar.io.save_trained``."""
        return self.file(_MODELS, kind)

    def model(self, load: Callable[[Path], T], kind: str = "ours") -> T:
        """``load(model_dir(kind))`` (pass ``avatar.io.load_trained``); one clear error if it cannot.

        The loader is passed in so that this module imports nothing outside its stage, ``scene``
        and ``pipeline``.
        """
        folder = self.model_dir(kind)
        try:
            return load(folder)
        except (OSError, KeyError, ValueError, RuntimeError) as err:
            raise self.error(folder, f"cannot load the trained head ({err})") from err

    @property
    def splits_path(self) -> Path:
        return self.file(_SPLITS)

    def has_splits(self) -> bool:
        return self.splits_path.is_file()

    def splits(self) -> dict[str, Any]:
        """``splits.json``: held_out_bars, held_out_take, val_bars, val_segment and the frame indices of every split."""
        return self.read_json(_SPLITS)

    @property
    def capacity_path(self) -> Path:
        return self.file(_CAPACITY)

    def capacity(self) -> dict[str, Any]:
        return self.read_json(_CAPACITY)

    @property
    def curve_png_path(self) -> Path:
        return self.file(_CURVE_PNG)

    @property
    def curve_path(self) -> Path:
        return self.file(_CURVE)

    @property
    def curve_tradeoff_path(self) -> Path:
        return self.file(_TRADEOFFS, _CURVE_TRADEOFF)

    @property
    def table_path(self) -> Path:
        return self.file(_TABLE)

    @property
    def previews_dir(self) -> Path:
        return self.file(_PREVIEWS)

    @property
    def comparisons_dir(self) -> Path:
        return self.file(_COMPARISONS)

    def comparisons(self) -> list[tuple[Path, str]]:
        """(figure, caption in words) of every split with a comparison figure; empty when the run wrote none."""
        folder = self.file(_COMPARISONS)
        try:
            captions = json.loads((folder / _CAPTIONS).read_text())
        except (OSError, ValueError):
            return []
        return [(folder / f"{split}.png", str(caption)) for split, caption in captions.items()
                if (folder / f"{split}.png").is_file()]

    @property
    def tensorboard_dir(self) -> Path:
        return self.file(_TENSORBOARD)
