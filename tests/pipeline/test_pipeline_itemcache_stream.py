"""Streaming per-item cache: results reach ``consume`` in input order, items finished before a failure
are kept for the rerun, code changes change keys, and a Ray cluster serves the same cache."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))
from itemcache_stream_support import job_key, square_unless_poisoned  # noqa: E402

from pipeline.executors import LocalExecutor  # noqa: E402
from pipeline.itemcache import ItemCache, code_digest  # noqa: E402


@pytest.fixture
def folder(tmp_path: Path) -> Path:
    (tmp_path / "calls").mkdir()
    return tmp_path


def _calls(folder: Path) -> list[int]:
    values = sorted(int(p.name.split(".")[0]) for p in (folder / "calls").iterdir())
    for p in (folder / "calls").iterdir():
        p.unlink()
    return values


def test_consume_sees_input_order_and_keeps_only_what_it_returns(folder):
    jobs = [(v, str(folder)) for v in range(9)]
    seen: list[int] = []

    def consume(position: int, result: dict) -> int:
        seen.append(position)
        return result["square"] + 1

    cache = ItemCache(folder / "cache")
    with LocalExecutor(workers=2) as pool:
        cache.map(pool, square_unless_poisoned, jobs[:4], job_key)  # some hits among misses
        assert cache.map(pool, square_unless_poisoned, jobs, job_key, consume=consume) == [v * v + 1 for v in range(9)]
    assert seen == list(range(9)) and cache.computed == [4, 5, 6, 7, 8]


def test_items_finished_before_a_failure_are_not_computed_again(folder):
    jobs = [(v, str(folder)) for v in range(6)]
    (folder / "poison").write_text("4")
    cache = ItemCache(folder / "cache")
    serial = LocalExecutor(workers=1)
    with pytest.raises(ValueError, match="item 4 is poisoned"):
        cache.map(serial, square_unless_poisoned, jobs, job_key)
    assert _calls(folder) == [0, 1, 2, 3, 4]
    (folder / "poison").unlink()
    assert cache.map(serial, square_unless_poisoned, jobs, job_key) == [{"square": v * v} for v in range(6)]
    assert _calls(folder) == [4, 5] and cache.computed == [4, 5]


def test_the_code_digest_is_part_of_the_key(folder):
    plain = ItemCache(folder / "cache")
    with_scene = ItemCache(folder / "cache", code=("scene.colour",))
    assert plain.path(square_unless_poisoned, "k") != with_scene.path(square_unless_poisoned, "k")
    assert code_digest(("scene.colour",)) == code_digest(("scene.colour",)) != code_digest(("scene.image_io",))


@pytest.mark.slow
def test_a_ray_cluster_fills_and_reads_the_same_cache(folder):
    pytest.importorskip("ray")
    from pipeline.ray_executor import RayExecutor

    jobs = [(v, str(folder)) for v in range(7)]
    cache = ItemCache(folder / "cache")
    cache.map(LocalExecutor(workers=1), square_unless_poisoned, jobs[:3], job_key)
    _calls(folder)
    with RayExecutor(workers=2) as ray_executor:
        assert cache.map(ray_executor, square_unless_poisoned, jobs, job_key) == [{"square": v * v} for v in range(7)]
    assert _calls(folder) == [3, 4, 5, 6] and cache.hits == 3
