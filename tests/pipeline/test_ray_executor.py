"""The Ray executor on a local cluster: same results as the local executor, killed workers retried."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

ray = pytest.importorskip("ray")

from pipeline.executors import LocalExecutor  # noqa: E402
from pipeline.ray_executor import RayExecutor  # noqa: E402


def square_plus_pid_free(x: int) -> int:
    return x * x + 1


def die_once_per_item(item: tuple[int, str]) -> int:
    """Kills its worker process the first time it sees an item (a marker file remembers)."""
    value, marker_dir = item
    marker = Path(marker_dir) / f"{value}.seen"
    if not marker.exists():
        marker.write_text("1")
        os._exit(1)  # a hard worker death, as SIGKILL / OOM would cause
    return value * 10


def fails(x: int) -> int:
    raise ValueError(f"bad item {x}")


@pytest.fixture(scope="module")
def ray_executor():
    executor = RayExecutor(workers=2)
    yield executor
    executor.close()


@pytest.mark.slow
def test_ray_matches_local(ray_executor: RayExecutor) -> None:
    items = list(range(37))
    with LocalExecutor(workers=1) as local:
        expected = local.map(square_plus_pid_free, items)
    assert ray_executor.map(square_plus_pid_free, items) == expected


@pytest.mark.slow
def test_killed_worker_items_are_retried(ray_executor: RayExecutor, tmp_path: Path) -> None:
    items = [(i, str(tmp_path)) for i in range(3)]
    assert ray_executor.map(die_once_per_item, items) == [0, 10, 20]
    assert len(list(tmp_path.glob("*.seen"))) == 3


@pytest.mark.slow
def test_application_errors_surface_unretried(ray_executor: RayExecutor) -> None:
    with pytest.raises(ValueError, match="bad item"):
        ray_executor.map(fails, [1, 2])


@pytest.mark.slow
def test_a_per_item_stage_gives_the_same_object_on_ray_and_local(tmp_path: Path) -> None:
    """`pipeline run --executor ray` commits the very object the local process pool commits."""
    import json

    from pipeline_toy_support import ToyProject

    digests = {}
    for kind in ("local", "ray"):
        toy = ToyProject(tmp_path / kind)
        toy.cli("run", "-S", "alice", "--until", "double", "--workers", "2", "--executor", kind)
        shown = json.loads(toy.cli("show", "-S", "alice", "double", "--json", "--full").stdout)
        digests[kind] = Path(shown["path"]).name
    assert digests["ray"] == digests["local"]
