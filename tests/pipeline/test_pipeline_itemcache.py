"""Per-item caching: adding frames reruns only the new ones; changed content reruns; results equal."""

from __future__ import annotations

import logging
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest

sys.path.insert(0, str(Path(__file__).parent))
from itemcache_support import frame_sum  # noqa: E402

from pipeline.executors import LocalExecutor  # noqa: E402
from pipeline.itemcache import ItemCache, cached_map, content_key  # noqa: E402


def _frames(folder: Path, values: dict[str, list[float]]) -> list[Path]:
    folder.mkdir(parents=True, exist_ok=True)
    for name, numbers in values.items():
        (folder / f"{name}.txt").write_text(" ".join(map(str, numbers)))
    return sorted(folder.glob("*.txt"))


def _calls(folder: Path) -> list[str]:
    names = sorted(p.name.split(".")[0] for p in folder.iterdir())
    for p in folder.iterdir():
        p.unlink()
    return names


@pytest.fixture
def setup(tmp_path):
    calls = tmp_path / "calls"
    calls.mkdir()
    return tmp_path, calls


def key_of(job: tuple[str, str]) -> str:
    return content_key(Path(job[0]), {"op": "sum"})


def test_adding_frames_reruns_only_the_new_ones(setup):
    tmp_path, calls = setup
    frames = _frames(tmp_path / "frames", {"000000": [1, 2], "000001": [3], "000002": [4, 5]})
    cache = ItemCache(tmp_path / "cache")
    with LocalExecutor(workers=2) as pool:  # misses go through a real process pool
        first = cache.map(pool, frame_sum, [(str(p), str(calls)) for p in frames], key_of, desc="frames")
    assert first == [3.0, 3.0, 9.0] and cache.misses == 3 and _calls(calls) == ["000000", "000001", "000002"]

    frames = _frames(tmp_path / "frames", {"000003": [10], "000004": [1, 1, 1]})
    serial = LocalExecutor(workers=1)
    second = cache.map(serial, frame_sum, [(str(p), str(calls)) for p in frames], key_of)
    assert second == [3.0, 3.0, 9.0, 10.0, 3.0]
    assert cache.hits == 3 and cache.misses == 2 and cache.computed == [3, 4]
    assert _calls(calls) == ["000003", "000004"]

    _frames(tmp_path / "frames", {"000001": [7, 7]})  # a re-shot frame: new content, new result
    third = cache.map(serial, frame_sum, [(str(p), str(calls)) for p in frames], key_of)
    assert third == [3.0, 14.0, 9.0, 10.0, 3.0] and _calls(calls) == ["000001"]


def test_unreadable_entry_is_recomputed_and_settings_are_part_of_the_key(setup):
    tmp_path, calls = setup
    frames = _frames(tmp_path / "frames", {"000000": [1], "000001": [2]})
    jobs = [(str(p), str(calls)) for p in frames]
    cache = ItemCache(tmp_path / "cache")
    serial = LocalExecutor(workers=1)
    cache.map(serial, frame_sum, jobs, key_of)
    _calls(calls)
    cache.path(frame_sum, key_of(jobs[0])).write_bytes(b"truncated")
    assert cache.map(serial, frame_sum, jobs, key_of) == [1.0, 2.0] and _calls(calls) == ["000000"]
    assert content_key(frames[0], {"op": "sum"}) != content_key(frames[0], {"op": "max"})
    assert content_key(frames[0], {"op": "sum"}) != content_key(frames[1], {"op": "sum"})


def test_cached_map_uses_the_stage_cache_dir_and_executor(setup, caplog):
    tmp_path, calls = setup
    frames = _frames(tmp_path / "frames", {"000000": [1], "000001": [2]})
    ctx = SimpleNamespace(cache_dir=tmp_path / "stage_cache", executor=LocalExecutor(workers=1),
                          log=logging.getLogger("test.itemcache"))
    jobs = [(str(p), str(calls)) for p in frames]
    assert cached_map(ctx, frame_sum, jobs, key_of, desc="frames") == [1.0, 2.0]
    with caplog.at_level(logging.INFO):
        assert cached_map(ctx, frame_sum, jobs, key_of, desc="frames") == [1.0, 2.0]
    assert "frames: 2 of 2 reused" in caplog.text
    assert any((tmp_path / "stage_cache" / "items").rglob("*.npz"))


def test_results_round_trip_without_pickle(tmp_path: Path) -> None:
    import numpy as np

    from pipeline.errors import PipelineError
    from pipeline.itemcache import ItemCache

    cache = ItemCache(tmp_path)
    value = {"landmarks": np.arange(6, dtype=np.float32).reshape(3, 2), "score": 0.9, "ok": True,
             "views": [1, "cam00", None], "pair": (1, 2)}
    cache.store(tmp_path / "entry.npz", value)
    found, loaded = cache.load(tmp_path / "entry.npz")
    assert found and loaded["score"] == 0.9 and loaded["views"] == [1, "cam00", None]
    assert loaded["pair"] == [1, 2]  # tuples come back as lists
    np.testing.assert_array_equal(loaded["landmarks"], value["landmarks"])
    with pytest.raises(PipelineError, match="JSON values and numpy arrays"):
        cache.store(tmp_path / "bad.npz", {"obj": object()})
    (tmp_path / "torn.npz").write_bytes(b"PK\x03\x04 not a zip")
    assert cache.load(tmp_path / "torn.npz") == (False, None)
