"""A persistent cache of stage declarations and validated params, so that ``pipeline status``
and a no-op ``pipeline run`` need not import stage modules (which may import torch: seconds).

For each stage it keeps the declaration (inputs, extra outputs, code modules, ...) together
with the (path, size, mtime_ns) of every project source file loaded when the module was
imported; if any of those files changed, the entry is ignored and the module imported again.
For each distinct raw configuration of a stage (merged YAML + ``--set``) it keeps the
validated, canonical params and the stage's external input paths. It also keeps the
normalised-source digests and import scans of project files by stat, so code digests need not
re-parse unchanged files. Only JSON is stored; a damaged cache file is ignored.
"""

from __future__ import annotations

import json
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pipeline.hashing import hash_bytes
from pipeline.stage import Stage

_VERSION = 4
_MAX_PARAM_ENTRIES = 32
# Files modified this recently may change again within the same mtime tick with the same size
# ("racy git"): nothing derived from them is cached until they have settled.
_RACY_WINDOW_NS = 2_000_000_000


def _settled(mtime_ns: int) -> bool:
    return time.time_ns() - mtime_ns >= _RACY_WINDOW_NS


@dataclass(frozen=True)
class StageDecl:
    """What the graph, ``status`` and the action key need to know of a stage, without its module."""

    name: str
    module: str
    inputs: tuple[str, ...]
    extra_outputs: tuple[str, ...]
    reads_truth: bool | None
    evaluates: str | None
    code: tuple[str, ...]
    has_rig: bool
    has_external: bool
    reads_metrics: bool = False
    run_records: tuple[str, ...] = ()

    @property
    def may_read_truth(self) -> bool:
        """Same rule as ``Stage.may_read_truth``."""
        if self.reads_truth is not None:
            return self.reads_truth
        return self.name.endswith("_eval")

    @classmethod
    def from_stage(cls, stage: Stage, module: str) -> "StageDecl":
        """The declaration of an imported stage."""
        return cls(name=stage.name, module=module, inputs=tuple(stage.inputs),
                   extra_outputs=tuple(stage.extra_outputs), reads_truth=stage.reads_truth,
                   evaluates=stage.evaluates, code=tuple(stage.code),
                   has_rig="rig" in stage.params.model_fields, has_external=stage.external_inputs is not None,
                   reads_metrics=stage.reads_metrics, run_records=tuple(stage.run_records))

    def to_json(self) -> dict[str, Any]:
        """JSON form for the cache file."""
        return {"name": self.name, "module": self.module, "inputs": list(self.inputs),
                "extra_outputs": list(self.extra_outputs), "reads_truth": self.reads_truth,
                "evaluates": self.evaluates, "code": list(self.code), "has_rig": self.has_rig,
                "has_external": self.has_external, "reads_metrics": self.reads_metrics,
                "run_records": list(self.run_records)}

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> "StageDecl":
        """Inverse of ``to_json``."""
        return cls(name=data["name"], module=data["module"], inputs=tuple(data["inputs"]),
                   extra_outputs=tuple(data["extra_outputs"]), reads_truth=data["reads_truth"],
                   evaluates=data["evaluates"], code=tuple(data["code"]), has_rig=bool(data["has_rig"]),
                   has_external=bool(data["has_external"]), reads_metrics=bool(data.get("reads_metrics", False)),
                   run_records=tuple(data.get("run_records", ())))


def _stat_key(path: str) -> tuple[int, int] | None:
    try:
        st = os.stat(path)
    except OSError:
        return None
    return st.st_size, st.st_mtime_ns


def project_source_files(root: Path) -> list[str]:
    """Source files of every loaded module that lives in the project (the import-time closure)."""
    prefix = str(root.resolve()) + os.sep
    files = set()
    for module in list(sys.modules.values()):
        path = getattr(module, "__file__", None)
        if path and path.endswith(".py"):
            path = os.path.realpath(path)
            if path.startswith(prefix) and f"{os.sep}.venv{os.sep}" not in path \
                    and f"{os.sep}site-packages{os.sep}" not in path:
                files.add(path)
    return sorted(files)


class DeclCache:
    """The cache file of one project, kept under the workspace root."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.dirty = False
        self._stat_memo: dict[str, tuple[int, int] | None] = {}
        data: dict[str, Any] = {}
        try:
            data = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            data = {}
        if not isinstance(data, dict) or data.get("version") != _VERSION:
            data = {"version": _VERSION, "stages": {}, "files": {}, "scans": {}}
        self.data = data

    @classmethod
    def for_project(cls, cache_root: Path, project_root: Path) -> "DeclCache":
        """The cache of ``project_root``, stored in ``cache_root``."""
        name = hash_bytes(str(project_root.resolve()).encode())[:16]
        return cls(cache_root / f"{name}.json")

    def _stat(self, path: str) -> tuple[int, int] | None:
        if path not in self._stat_memo:
            self._stat_memo[path] = _stat_key(path)
        return self._stat_memo[path]

    # -- declarations -------------------------------------------------------------------

    def decl(self, name: str, module: str) -> StageDecl | None:
        """The cached declaration if the module and every file it loaded are unchanged."""
        entry = self.data["stages"].get(name)
        if not entry or entry.get("module") != module:
            return None
        for path, size, mtime_ns in entry.get("files", []):
            if self._stat(path) != (size, mtime_ns):
                return None
        try:
            return StageDecl.from_json(entry["decl"])
        except (KeyError, TypeError):
            return None

    def put_decl(self, decl: StageDecl, files: list[str]) -> None:
        """Remember a freshly imported stage's declaration (its params entries are dropped)."""
        stamped = []
        for path in files:
            key = _stat_key(path)
            if key is not None:
                if not _settled(key[1]):
                    self.data["stages"].pop(decl.name, None)
                    return
                stamped.append([path, *key])
        self.data["stages"][decl.name] = {"module": decl.module, "decl": decl.to_json(), "files": stamped,
                                          "params": {}}
        self.dirty = True

    # -- params -------------------------------------------------------------------------

    def params(self, name: str, raw_key: str) -> dict[str, Any] | None:
        """Cached ``{"canonical": ..., "external": [...]}`` for a raw configuration."""
        entry = self.data["stages"].get(name)
        return None if not entry else entry.get("params", {}).get(raw_key)

    def put_params(self, name: str, raw_key: str, canonical: dict[str, Any], external: list[str]) -> None:
        """Remember the validated params of one raw configuration (the newest 32 are kept)."""
        entry = self.data["stages"].get(name)
        if entry is None:
            return
        table = entry.setdefault("params", {})
        table.pop(raw_key, None)
        table[raw_key] = {"canonical": canonical, "external": external}
        while len(table) > _MAX_PARAM_ENTRIES:
            table.pop(next(iter(table)))
        self.dirty = True

    # -- normalised source digests ------------------------------------------------------

    def file_digest(self, path: str) -> str | None:
        """A normalised-source digest stored for this file, if its stat is unchanged."""
        hit = self.data["files"].get(path)
        if hit and self._stat(path) == (hit[0], hit[1]):
            return hit[2]
        return None

    def put_file_digest(self, path: str, size: int, mtime_ns: int, digest: str) -> None:
        """Store a normalised-source digest (not for files modified in the last two seconds)."""
        if not _settled(mtime_ns):
            return
        self.data["files"][path] = [size, mtime_ns, digest]
        self.dirty = True

    def file_scan(self, path: str) -> tuple[list[str], list[str]] | None:
        """A stored (imports, declared files) scan of a Python file, if its stat is unchanged."""
        hit = self.data.setdefault("scans", {}).get(path)
        if hit and self._stat(path) == (hit[0], hit[1]):
            return hit[2], hit[3]
        return None

    def put_file_scan(self, path: str, size: int, mtime_ns: int, imports: list[str], code_files: list[str]) -> None:
        """Store a file's import scan (not for files modified in the last two seconds)."""
        if not _settled(mtime_ns):
            return
        self.data.setdefault("scans", {})[path] = [size, mtime_ns, imports, code_files]
        self.dirty = True

    def save(self) -> None:
        """Write the cache if it changed (atomically; a concurrent writer's copy may win)."""
        if not self.dirty:
            return
        from pipeline.workspace import write_json_atomic

        try:
            write_json_atomic(self.path, self.data)
        except OSError:
            return  # a read-only workspace root only costs speed
        self.dirty = False
