"""Per-item result cache for per-frame work: rerun only the items whose content changed.

A stage that maps a function over frames keys each item by a digest of what the result
depends on (the frame file's content, the settings) and keeps results in its persistent
``ctx.cache_dir``; adding frames to a capture then runs the function on the new frames only::

    from pipeline.itemcache import cached_map, content_key

    def key_of(job):  # what the result depends on
        return content_key(job.path, job.settings)

    results = cached_map(ctx, detect, jobs, key_of, desc="frames", code=("scene.image_io",))

Layout: ``<cache_dir>/items/<module.function>/<key[:2]>/<key>.npz``, written atomically; an
unreadable entry is recomputed (with a warning). The entry's key is ``key_of(item)`` mixed
with the code digest of the function's own module and of the ``code`` modules given, with
everything they import (the same comment-blind closure digest as a stage's), so a change to what the code does recomputes every
item while a comment edit reuses them. Nothing in a workspace is unpickled (a cache folder is as
exposed as any other), so results must be made of JSON values (dict with str keys, list,
str, int, float, bool, None; tuples come back as lists) and numpy arrays: the structure is
stored as JSON, the arrays as ``.npy`` members read with ``allow_pickle=False``.

Misses are fanned out through the stage's executor (process pool or Ray) in one call. Each
worker writes its item's entry as soon as the item is done (the driver writes it too when a
worker cannot reach the cache folder), so a failure or a kill part-way loses no finished
item: the rerun finds them. With ``consume``, results go one at a time, in input order, to
``consume(position, result)`` and only what it returns is kept: a stage writes images to its
output there without holding a whole capture in memory.
"""

from __future__ import annotations

import io
import json
import logging
import os
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterator, Sequence, TypeVar

import blake3

import numpy as np

from pipeline.codedigest import modules_code_version
from pipeline.errors import PipelineError
from pipeline.hashing import hash_file
from pipeline.workspace import write_bytes_atomic

T = TypeVar("T")
R = TypeVar("R")
log = logging.getLogger(__name__)


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


def code_digest(modules: Sequence[str]) -> str:
    """Digest of what the named modules and everything they import do (their import closure and
    declared files, as a stage's code digest; docstrings, comments and layout ignored)."""
    hasher = blake3.blake3()
    for dotted in modules:
        hasher.update(dotted.encode() + b"\0")
    version = modules_code_version(modules)  # None for a script or an interactive function
    hasher.update((version.digest if version is not None else "-").encode())
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


def touch_entry(path: Path) -> None:
    """Mark a cache entry as used now (its mtime): ``pipeline gc`` keeps entries used within its window."""
    try:
        os.utime(path)
    except OSError:  # a read-only cache folder still serves hits
        pass


def write_entry(path: Path, result: Any) -> None:
    """Write a result entry atomically (a killed run never leaves half an entry)."""
    arrays: dict[str, np.ndarray] = {}
    try:
        structure = _encode(result, arrays)
    except TypeError as err:
        raise PipelineError(f"per-item cache {path.parent.parent.name}: a result holds {err}; cached "
                            f"results must be JSON values and numpy arrays") from None
    buffer = io.BytesIO()
    np.savez(buffer, __json__=np.frombuffer(json.dumps(structure).encode("utf-8"), np.uint8), **arrays)
    write_bytes_atomic(path, buffer.getvalue())


@dataclass(frozen=True)
class StoringCall:
    """``fn`` run on a worker, its result written to the item's entry there and then (picklable)."""

    fn: Callable[[Any], Any]

    def __call__(self, job: tuple[str, Any]) -> Any:
        path, item = job
        result = self.fn(item)
        try:
            write_entry(Path(path), result)
        except OSError:
            pass  # the cache folder is not reachable from this worker: the driver writes the entry
        return result


@dataclass
class ItemCache:
    """Results of one function, by item key, under ``folder``; counts hits and misses of the last ``map``.

    ``code``: modules whose source counts toward every key, besides the function's own module.
    """

    folder: Path
    code: tuple[str, ...] = ()
    hits: int = 0
    misses: int = 0
    computed: list[int] = field(default_factory=list)  # input positions recomputed by the last map
    _code_digests: dict[str, str] = field(default_factory=dict, repr=False)

    def path(self, fn: Callable, key: str) -> Path:
        """The entry file of ``fn``'s result for ``key``."""
        name = f"{fn.__module__}.{fn.__qualname__}"
        if name not in self._code_digests:
            self._code_digests[name] = code_digest((fn.__module__, *self.code))
        full_key = blake3.blake3(f"{key}\0{self._code_digests[name]}".encode()).hexdigest()
        return self.folder / name / full_key[:2] / f"{full_key}.npz"

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
        write_entry(path, result)

    def map(self, executor: Any, fn: Callable[[T], R], items: Sequence[T], key_of: Callable[[T], str], *,
            desc: str = "items", gpu: bool = False, consume: Callable[[int, Any], Any] | None = None) -> list[Any]:
        """``[fn(item) for item in items]``: cached results reused, the rest run through ``executor``.

        With ``consume``, returns ``[consume(i, fn(items[i])) ...]``, calling it in input order
        as results arrive (see the module doc).
        """
        items = list(items)
        paths = [self.path(fn, key_of(item)) for item in items]
        missing = [i for i, path in enumerate(paths) if not path.is_file()]
        recomputed: list[int] = []
        stream = _start(executor, StoringCall(fn), [(str(paths[i]), items[i]) for i in missing], desc, gpu)
        arrived: dict[int, Any] = {}  # results that came before their turn (input order)
        missing_set = set(missing)
        results: list[Any] = []
        try:
            for i, path in enumerate(paths):
                if i in missing_set:
                    while i not in arrived:
                        position, fresh = next(stream)
                        target = missing[position]
                        if not paths[target].is_file():
                            self.store(paths[target], fresh)
                        arrived[target] = fresh
                    value = arrived.pop(i)
                else:
                    found, value = self.load(path)
                    if found:
                        touch_entry(path)
                    else:
                        log.warning("%s: per-item cache entry %s is unreadable; recomputing it", desc, path)
                        value = self._recompute(executor, fn, items[i], path, desc, gpu)
                        recomputed.append(i)
                results.append(consume(i, value) if consume is not None else value)
        finally:
            close = getattr(stream, "close", None)
            if close is not None:
                close()
        self.computed = sorted(missing + recomputed)
        self.misses = len(self.computed)
        self.hits = len(items) - self.misses
        return results

    def report(self, ctx: Any, desc: str, metrics_prefix: str | None = None) -> None:
        """Log the last ``map``'s reuse; with ``metrics_prefix``, ``<prefix>_reused``/``_computed`` to ``ctx.metrics``."""
        ctx.log.info("%s: %d of %d reused from the per-item cache, %d computed", desc, self.hits,
                     self.hits + self.misses, self.misses)
        if metrics_prefix is not None:
            ctx.metrics[f"{metrics_prefix}_reused"] = self.hits
            ctx.metrics[f"{metrics_prefix}_computed"] = self.misses

    def _recompute(self, executor: Any, fn: Callable, item: Any, path: Path, desc: str, gpu: bool) -> Any:
        value = executor.map(StoringCall(fn), [(str(path), item)], desc=desc, gpu=gpu)[0]
        if not path.is_file():
            self.store(path, value)
        return value


def _start(executor: Any, fn: Callable, jobs: list, desc: str, gpu: bool) -> Iterator[tuple[int, Any]]:
    """The executor's ``imap`` stream over ``jobs`` (its ``map``, enumerated, if it has no ``imap``)."""
    if not jobs:
        return iter(())
    imap = getattr(executor, "imap", None)
    if imap is not None:
        return imap(fn, jobs, desc=desc, gpu=gpu)
    return iter(enumerate(executor.map(fn, jobs, desc=desc, gpu=gpu)))


def cached_map(ctx: Any, fn: Callable[[T], R], items: Sequence[T], key_of: Callable[[T], str], *,
               desc: str = "items", gpu: bool = False, code: Sequence[str] = (),
               consume: Callable[[int, Any], Any] | None = None, metrics_prefix: str | None = None) -> list[Any]:
    """``ctx.executor.map(fn, items)`` with per-item results kept in ``ctx.cache_dir`` (see the module doc).

    ``key_of(item)`` must digest everything the result depends on but code (use
    ``content_key``); ``code`` names the modules besides ``fn``'s own whose source the result
    depends on. ``consume(position, result)``: see the module doc. Logs how many items were
    reused; with ``metrics_prefix``, also writes ``<prefix>_reused`` and ``<prefix>_computed``
    (item counts) to ``ctx.metrics``.
    """
    cache = stage_item_cache(ctx, code)
    results = cache.map(ctx.executor, fn, items, key_of, desc=desc, gpu=gpu, consume=consume)
    cache.report(ctx, desc, metrics_prefix)
    return results


def stage_item_cache(ctx: Any, code: Sequence[str] = ()) -> ItemCache:
    """The stage's per-item cache (``<ctx.cache_dir>/items``), for stages that want its counters."""
    return ItemCache(Path(ctx.cache_dir) / "items", code=tuple(code))
