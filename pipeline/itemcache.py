"""Per-item result cache for per-frame work: rerun only the items whose content changed.

A stage that maps a function over frames keys each item by a digest of what the result
depends on (the frame file's content, the settings) and keeps results in its persistent
``ctx.cache_dir``; adding frames to a capture then runs the function on the new frames only::

    from pipeline.itemcache import cached_map, content_key

    def key_of(job):  # what the result depends on
        return content_key(job.path, job.settings)

    results = cached_map(ctx, detect, jobs, key_of, desc="frames")

Layout: ``<cache_dir>/items/<module.function>/<key[:2]>/<key>.npz``, written atomically; an
unreadable entry is recomputed. Nothing in a workspace is unpickled (a cache folder is as
exposed as any other), so results must be made of JSON values (dict with str keys, list,
str, int, float, bool, None; tuples come back as lists) and numpy arrays: the structure is
stored as JSON, the arrays as ``.npy`` members read with ``allow_pickle=False``. Misses are
fanned out through the stage's executor (process pool or Ray) in one ``map`` call, in input
order.
"""

from __future__ import annotations

import io
import json
import os
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence, TypeVar

import blake3

import numpy as np

from pipeline.errors import PipelineError
from pipeline.hashing import hash_file

T = TypeVar("T")
R = TypeVar("R")


def content_key(*parts: Any) -> str:
    """BLAKE3 digest of ``parts``: a ``Path`` counts by its file's content, anything else by its JSON/repr form."""
    hasher = blake3.blake3()
    for part in parts:
        if isinstance(part, Path):
            token = "file:" + (hash_file(part) if part.is_file() else f"missing:{part}")
        else:
            try:
                token = "json:" + json.dumps(part, sort_keys=True, default=_model_dump)
            except (TypeError, ValueError):
                token = "repr:" + repr(part)
        hasher.update(token.encode())
        hasher.update(b"\0")
    return hasher.hexdigest()


def _model_dump(value: Any) -> Any:
    if hasattr(value, "model_dump"):  # pydantic params
        return value.model_dump(mode="json")
    if isinstance(value, Path):
        return str(value)
    raise TypeError(type(value).__name__)


def _encode(value: Any, arrays: dict[str, np.ndarray]) -> Any:
    """JSON-able form of ``value``; numpy arrays go to ``arrays`` and leave a reference behind."""
    if isinstance(value, np.ndarray):
        if value.dtype == object:
            raise TypeError("object arrays")
        name = f"a{len(arrays)}"
        arrays[name] = value
        return {"__ndarray__": name}
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, dict):
        if not all(isinstance(k, str) for k in value):
            raise TypeError("dict keys must be str")
        return {"__dict__": {k: _encode(v, arrays) for k, v in value.items()}}
    if isinstance(value, (list, tuple)):
        return [_encode(v, arrays) for v in value]
    if value is None or isinstance(value, (str, bool, int, float)):
        return value
    raise TypeError(type(value).__name__)


def _decode(value: Any, arrays: Any) -> Any:
    if isinstance(value, dict):
        if "__ndarray__" in value:
            return arrays[value["__ndarray__"]]
        return {k: _decode(v, arrays) for k, v in value["__dict__"].items()}
    if isinstance(value, list):
        return [_decode(v, arrays) for v in value]
    return value


@dataclass
class ItemCache:
    """Results of one function, by item key, under ``folder``; counts hits and misses of the last ``map``."""

    folder: Path
    hits: int = 0
    misses: int = 0
    computed: list[int] = field(default_factory=list)  # input positions recomputed by the last map

    def path(self, fn: Callable, key: str) -> Path:
        """The entry file of ``fn``'s result for ``key``."""
        return self.folder / f"{fn.__module__}.{fn.__qualname__}" / key[:2] / f"{key}.npz"

    def load(self, path: Path) -> tuple[bool, Any]:
        """(found, result); a missing or unreadable entry is not found."""
        try:
            with np.load(path, allow_pickle=False) as entry:
                arrays = {name: entry[name] for name in entry.files if name != "__json__"}
                structure = json.loads(entry["__json__"].tobytes().decode("utf-8"))
            return True, _decode(structure, arrays)
        except (OSError, EOFError, KeyError, ValueError, UnicodeDecodeError, zipfile.BadZipFile):
            return False, None

    def store(self, path: Path, result: Any) -> None:
        """Write an entry atomically (a killed run never leaves half an entry)."""
        arrays: dict[str, np.ndarray] = {}
        try:
            structure = _encode(result, arrays)
        except TypeError as err:
            raise PipelineError(f"per-item cache {path.parent.parent.name}: a result holds {err}; cached "
                                f"results must be JSON values and numpy arrays") from None
        buffer = io.BytesIO()
        np.savez(buffer, __json__=np.frombuffer(json.dumps(structure).encode("utf-8"), np.uint8), **arrays)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f"{path.name}.tmp{os.getpid()}")
        tmp.write_bytes(buffer.getvalue())
        os.replace(tmp, path)

    def map(self, executor: Any, fn: Callable[[T], R], items: Sequence[T], key_of: Callable[[T], str], *,
            desc: str = "items", gpu: bool = False) -> list[R]:
        """``[fn(item) for item in items]``: cached results reused, the rest run through ``executor.map``."""
        paths = [self.path(fn, key_of(item)) for item in items]
        results: list[Any] = [None] * len(items)
        missing: list[int] = []
        for i, path in enumerate(paths):
            found, value = self.load(path)
            if found:
                results[i] = value
            else:
                missing.append(i)
        if missing:
            fresh = executor.map(fn, [items[i] for i in missing], desc=desc, gpu=gpu)
            for i, value in zip(missing, fresh):
                self.store(paths[i], value)
                results[i] = value
        self.hits, self.misses, self.computed = len(items) - len(missing), len(missing), missing
        return results


def cached_map(ctx: Any, fn: Callable[[T], R], items: Sequence[T], key_of: Callable[[T], str], *,
               desc: str = "items", gpu: bool = False) -> list[R]:
    """``ctx.executor.map(fn, items)`` with per-item results kept in ``ctx.cache_dir`` (see the module doc).

    ``key_of(item)`` must digest everything the result depends on (use ``content_key``); logs
    how many items were reused.
    """
    cache = ItemCache(Path(ctx.cache_dir) / "items")
    results = cache.map(ctx.executor, fn, items, key_of, desc=desc, gpu=gpu)
    ctx.log.info("%s: %d of %d reused from the per-item cache, %d computed", desc, cache.hits, len(items),
                 cache.misses)
    return results
