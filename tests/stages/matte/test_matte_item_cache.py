"""Matting inference is cached per image: with the statistics window fixed, frames appended to a
capture are the only ones matted again, and the mattes equal those of a run without a cache."""

import json
from pathlib import Path

import pytest
import torch

from pipeline.testing import run_stage_for_test
from stages.matte.mini_capture import render_mini_capture
from stages.matte.stage import STAGE

TINY = {
    "train": {"iterations": 3, "batch_size": 2, "crop_px": 32},
    "data": {"identity_seeds": [1001], "frames_per_take": 4, "frame_pairs_per_identity": 1, "cameras_per_frame": 1},
    "soc": {"iterations": 2, "batch_size": 2, "crop_px": 32},
    "soc_frames": 4,
    "threads": 1,
}


@pytest.fixture(scope="module")
def captures(tmp_path_factory):
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    root = tmp_path_factory.mktemp("matte_cache")
    for name, count in (("short", 4), ("long", 7)):  # the long take: the short one plus 3 frames
        render_mini_capture(root / name, root / f"{name}.truth", identity_seed=1, image_scale=0.0625,
                            frame_count=count)
    yield root
    torch.set_num_threads(threads)


def _run(root: Path, work: str, capture: str, params: dict, share_cache_of: str | None = None, workers: int = 1):
    (root / work).mkdir()
    (root / work / ".shared_cache").symlink_to(root / "shared", target_is_directory=True)  # trained model
    if share_cache_of:
        (root / work / ".cache").symlink_to(root / share_cache_of / ".cache", target_is_directory=True)
    out = run_stage_for_test(STAGE, root / work, inputs={"capture": root / capture}, params=params, workers=workers)
    return out, json.loads((out / "metrics.json").read_text())


def _mattes(out: Path) -> dict[str, bytes]:
    return {str(p.relative_to(out)): p.read_bytes() for p in sorted((out / "mattes").rglob("*.png"))}


def test_appended_frames_are_the_only_ones_matted_again(captures):
    (captures / "shared").mkdir()
    params = {**TINY, "statistics_frames": 4}
    _, first = _run(captures, "w1", "short", params)
    assert (first["images_reused"], first["images_computed"]) == (0, 8)

    out, second = _run(captures, "w2", "long", params, share_cache_of="w1", workers=2)
    assert second["model_cached"] == 1 and (second["images_reused"], second["images_computed"]) == (8, 6)

    fresh, third = _run(captures, "w3", "long", params)
    assert third["images_computed"] == 14
    assert _mattes(out) == _mattes(fresh) and len(_mattes(out)) == 14


def test_without_a_statistics_window_new_frames_change_the_adapted_model(captures):
    # SOC samples frames of the whole capture: a longer capture adapts to other weights, so the
    # per-image keys change and every image is matted again (correct, not incremental).
    _, first = _run(captures, "v1", "short", TINY)
    out, second = _run(captures, "v2", "long", TINY, share_cache_of="v1")
    assert first["images_computed"] == 8 and (second["images_reused"], second["images_computed"]) == (0, 14)
