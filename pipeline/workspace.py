"""A subject's workspace: content-addressed objects, action records, refs, lock, stat cache.

Layout of ``<root>/<subject>/``::

    objects/<digest>/          immutable output trees, read-only once committed
    objects/<digest>.manifest  the tree's manifest (for ``status --verify``)
    objects/<digest>.corrupt   marker left by ``status --verify``: treat as missing
    actions/<key>.json         what a run with this key produced (+ timings, versions)
    refs/<stage>.json          the current outputs of each stage
    logs/<stage>/*.log         one log per run
    cache/<stage>/             per-stage scratch caches that survive reruns
    tmp/                       outputs being written (removed when a run starts)
    statcache.sqlite           stat -> digest cache for external inputs
    lock                       fcntl lock of the ``pipeline run`` writing here

The root is ``--workspace-root``, else ``$PIPELINE_WORKSPACES``, else ``<project>/workspaces``.
"""

from __future__ import annotations

import errno
import fcntl
import fnmatch
import json
import os
import shutil
import socket
import stat as statmod
import tempfile
import time
import uuid
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator

from pipeline.errors import InputError, PipelineError, WorkspaceLocked
from pipeline.hashing import (ManifestEntry, StatCache, hash_tree, manifest_digest, manifest_text,
                              parse_manifest)

ENV_WORKSPACES = "PIPELINE_WORKSPACES"

#: The file the runner writes into every output beside the stage's own files: the stage's
#: figures, wall-clock timings included, so it differs between two runs of identical work.
RUNNER_METRICS_FILE = "metrics.json"


def is_run_record(relpath: str, patterns: tuple[str, ...] = ()) -> bool:
    """Whether an object's file ``relpath`` records the run rather than its data: the runner's
    ``metrics.json`` or a match of one of the stage's ``run_records`` patterns."""
    return relpath == RUNNER_METRICS_FILE or any(fnmatch.fnmatchcase(relpath, pat) for pat in patterns)


def workspace_root(project_root: Path, override: str | Path | None = None) -> Path:
    """Where workspaces live: the override, ``$PIPELINE_WORKSPACES`` or ``<project>/workspaces``."""
    if override:
        return Path(override).expanduser().resolve()
    env = os.environ.get(ENV_WORKSPACES)
    if env:
        return Path(env).expanduser().resolve()
    return project_root / "workspaces"


@contextmanager
def atomic_path(path: Path) -> Iterator[Path]:
    """A temp file beside ``path`` to write in the ``with`` block; on leaving it the file is
    fsynced and renamed over ``path`` (all or nothing: a reader, or a run killed half-way, sees
    the old file or the new one, never a torn one). On an error the temp file is removed."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp_name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        yield tmp
        with open(tmp, "rb+") as handle:
            os.fsync(handle.fileno())
        os.replace(tmp, path)
    except BaseException:
        if tmp.exists():
            tmp.unlink()
        raise


def write_bytes_atomic(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically (``atomic_path``)."""
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def write_json_atomic(path: Path, data: Any) -> None:
    """Write JSON to ``path`` atomically (``atomic_path``): indented, keys sorted, a final newline."""
    write_bytes_atomic(path, (json.dumps(data, indent=1, sort_keys=True) + "\n").encode("utf-8"))


def read_json(path: Path) -> Any | None:
    """Parsed JSON, or None when the file does not exist."""
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        return None
    except json.JSONDecodeError as err:
        raise PipelineError(f"{path}: not valid JSON ({err}); delete it and rerun the stage") from None


def _make_writable(path: Path) -> None:
    for folder, dirs, files in os.walk(path):
        os.chmod(folder, 0o755)
        for name in files:
            full = os.path.join(folder, name)
            if not os.path.islink(full):
                os.chmod(full, 0o644)


def remove_tree(path: Path) -> None:
    """Delete a tree, including read-only committed objects."""
    if not path.exists() and not path.is_symlink():
        return
    if path.is_dir() and not path.is_symlink():
        _make_writable(path)
        shutil.rmtree(path)
    else:
        path.unlink()


def _make_read_only(path: Path) -> None:
    for folder, dirs, files in os.walk(path, topdown=False):
        for name in files:
            os.chmod(os.path.join(folder, name), 0o444)
        os.chmod(folder, 0o555)


@dataclass(frozen=True)
class Ref:
    """A stage's current outputs for a subject: output name (``out``, ``truth``) -> digest."""

    stage: str
    action: str
    outputs: dict[str, str]
    updated: str

    def to_json(self) -> dict:
        """JSON form of the ref file."""
        return {"stage": self.stage, "action": self.action, "outputs": self.outputs, "updated": self.updated}


class WorkspaceLock:
    """An exclusive, non-blocking ``fcntl.flock`` on ``<workspace>/lock``.

    The kernel releases it when the holder dies, so a crash never leaves a stale lock; the
    file's text (PID, host, command) only serves to name the holder in the error.
    """

    def __init__(self, path: Path) -> None:
        self.path = path
        self._fd: int | None = None

    def acquire(self) -> None:
        """Take the lock or raise ``WorkspaceLocked`` naming its holder."""
        self.path.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as err:
            os.close(fd)
            if err.errno not in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                raise
            try:
                holder = json.loads(self.path.read_text() or "{}")
            except (OSError, ValueError):
                holder = {}
            who = (f"PID {holder.get('pid', '?')} on {holder.get('host', '?')} since "
                   f"{holder.get('since', '?')}: {holder.get('command', '?')}")
            raise WorkspaceLocked(f"workspace {self.path.parent} is in use by another pipeline run ({who}); "
                                  f"wait for it to finish (or stop that process), then retry") from None
        info = {"pid": os.getpid(), "host": socket.gethostname(),
                "since": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "command": _command_line()}
        os.ftruncate(fd, 0)
        os.pwrite(fd, json.dumps(info).encode(), 0)
        self._fd = fd

    def release(self) -> None:
        """Release the lock (the file stays; its text is overwritten by the next holder)."""
        if self._fd is not None:
            fcntl.flock(self._fd, fcntl.LOCK_UN)
            os.close(self._fd)
            self._fd = None

    def __enter__(self) -> "WorkspaceLock":
        self.acquire()
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()


def _command_line() -> str:
    import shlex
    import sys

    return shlex.join(["pipeline" if i == 0 else a for i, a in enumerate(sys.argv)])


class Workspace:
    """One subject's workspace folder (see the module docstring for its layout)."""

    def __init__(self, root: Path, subject: str) -> None:
        self.root = Path(root)
        self.subject = subject
        self.path = self.root / subject
        self.objects_dir = self.path / "objects"
        self._content_keys: dict[str, str] = {}
        self.actions_dir = self.path / "actions"
        self.refs_dir = self.path / "refs"
        self.logs_dir = self.path / "logs"
        self.cache_dir = self.path / "cache"
        self.tmp_dir = self.path / "tmp"
        self.shared_cache_dir = self.root / ".shared_cache"
        self._stat_cache: StatCache | None = None

    # -- lock and housekeeping ----------------------------------------------------------

    def lock(self) -> WorkspaceLock:
        """The run lock of this workspace (use as a context manager)."""
        return WorkspaceLock(self.path / "lock")

    def ensure(self) -> None:
        """Create the workspace folders."""
        for folder in (self.objects_dir, self.actions_dir, self.refs_dir, self.logs_dir,
                       self.cache_dir, self.tmp_dir, self.shared_cache_dir):
            folder.mkdir(parents=True, exist_ok=True)

    def clean_tmp(self) -> list[str]:
        """Remove leftovers of killed runs (call only while holding the lock)."""
        removed = []
        if self.tmp_dir.is_dir():
            for entry in self.tmp_dir.iterdir():
                remove_tree(entry)
                removed.append(entry.name)
        return removed

    def stat_cache(self) -> StatCache:
        """The workspace's stat cache (opened once per process)."""
        if self._stat_cache is None:
            self._stat_cache = StatCache(self.path / "statcache.sqlite")
        return self._stat_cache

    # -- objects ------------------------------------------------------------------------

    def object_path(self, digest: str) -> Path:
        """The folder of an object (present or not)."""
        return self.objects_dir / digest

    def _manifest_path(self, digest: str) -> Path:
        return self.objects_dir / f"{digest}.manifest"

    def _corrupt_path(self, digest: str) -> Path:
        return self.objects_dir / f"{digest}.corrupt"

    def is_corrupt(self, digest: str) -> bool:
        """Whether ``status --verify`` found this object damaged."""
        return self._corrupt_path(digest).exists()

    def has_object(self, digest: str) -> bool:
        """Present, with its manifest, and not marked corrupt."""
        return (self.object_path(digest).is_dir() and self._manifest_path(digest).is_file()
                and not self.is_corrupt(digest))

    def new_temp_dir(self, prefix: str) -> Path:
        """A fresh folder under ``tmp/`` (same file system as ``objects/`` so commit is a rename)."""
        self.tmp_dir.mkdir(parents=True, exist_ok=True)
        return Path(tempfile.mkdtemp(prefix=f"{prefix}-", dir=self.tmp_dir))

    def commit(self, folder: Path) -> str:
        """Hash ``folder`` and move it into ``objects/`` as an immutable object; its digest.

        An identical object already present is reused (``folder`` is deleted); one marked
        corrupt is replaced. Symlinks are refused.
        """
        digest, entries = hash_tree(folder, allow_symlinks=False)
        target = self.object_path(digest)
        if self.has_object(digest):
            remove_tree(folder)
            return digest
        corrupt = self.is_corrupt(digest)
        if target.exists():
            # A corrupt or half-registered object: move it aside so the rename below is atomic.
            graveyard = self.tmp_dir / f"replaced-{digest[:16]}-{uuid.uuid4().hex[:8]}"
            os.rename(target, graveyard)
            remove_tree(graveyard)
        write_manifest = self._manifest_path(digest)
        tmp_manifest = folder.parent / f"{folder.name}.manifest"
        tmp_manifest.write_text(manifest_text(entries), encoding="utf-8")
        os.replace(tmp_manifest, write_manifest)
        _make_read_only(folder)
        os.rename(folder, target)
        if corrupt:
            self._corrupt_path(digest).unlink(missing_ok=True)
        return digest

    def verify_object(self, digest: str) -> list[str]:
        """Re-hash an object against its manifest; the problems found (empty: intact)."""
        folder = self.object_path(digest)
        if not folder.is_dir():
            return ["object missing"]
        manifest_file = self._manifest_path(digest)
        if not manifest_file.is_file():
            return ["manifest missing"]
        expected = parse_manifest(manifest_file.read_text(encoding="utf-8"))
        problems = []
        if manifest_digest(expected) != digest:
            problems.append("manifest does not match the object's name")
        try:
            _, actual = hash_tree(folder, allow_symlinks=False)
        except InputError as err:
            return [str(err)]
        want = {e.relpath: e for e in expected}
        have = {e.relpath: e for e in actual}
        for rel in sorted(set(want) | set(have)):
            if rel not in have:
                problems.append(f"{rel}: missing")
            elif rel not in want:
                problems.append(f"{rel}: unexpected file")
            elif want[rel] != have[rel]:
                problems.append(f"{rel}: content changed")
        return problems

    def mark_corrupt(self, digest: str, problems: list[str]) -> None:
        """Leave a marker so every later run treats this object as missing and rebuilds it."""
        write_json_atomic(self._corrupt_path(digest), {"problems": problems[:50],
                                                        "found": time.strftime("%Y-%m-%dT%H:%M:%S%z")})

    def manifest(self, digest: str) -> list[ManifestEntry]:
        """The stored manifest of an object."""
        return parse_manifest(self._manifest_path(digest).read_text(encoding="utf-8"))

    def content_key(self, digest: str, run_records: tuple[str, ...] = ()) -> str:
        """The digest of an object's data: its manifest without the runner's ``metrics.json``
        and without the files matching ``run_records`` (the producing stage's ``Stage.run_records``).

        Two runs of a stage that produce the same files differ in their timings, hence in
        ``metrics.json`` (and in any wall-clock record) and in the object digest; keying
        downstream actions on this instead lets a rerun whose data come out identical stop
        there (early cutoff) rather than rebuild everything below it. An object with none of
        those files keys as its own digest, and so does one whose manifest is missing or
        unreadable (the caller reports it). Objects are immutable, so the keys are kept for the
        life of this ``Workspace``.
        """
        cache_key = digest if not run_records else f"{digest}|{'|'.join(run_records)}"
        cached = self._content_keys.get(cache_key)
        if cached is not None:
            return cached
        try:
            entries = self.manifest(digest)
        except (OSError, ValueError):
            return digest
        data = [e for e in entries if not is_run_record(e.relpath, run_records)]
        key = digest if len(data) == len(entries) else manifest_digest(data)
        self._content_keys[cache_key] = key
        return key

    # -- actions and refs ---------------------------------------------------------------

    def read_action(self, key: str) -> dict | None:
        """The action record of ``key``, or None."""
        return read_json(self.actions_dir / f"{key}.json")

    def write_action(self, key: str, record: dict) -> None:
        """Record an action (atomic)."""
        write_json_atomic(self.actions_dir / f"{key}.json", record)

    def read_ref(self, stage: str) -> Ref | None:
        """The current ref of a stage, or None if it never ran for this subject."""
        data = read_json(self.refs_dir / f"{stage}.json")
        if data is None:
            return None
        return Ref(stage=data["stage"], action=data["action"], outputs=dict(data["outputs"]),
                   updated=data.get("updated", ""))

    def write_ref(self, ref: Ref) -> None:
        """Point a stage at new outputs (atomic; call only after the objects are committed)."""
        write_json_atomic(self.refs_dir / f"{ref.stage}.json", ref.to_json())

    def output_path(self, stage: str, output: str = "out") -> Path:
        """The current output folder of ``stage`` (``output``: ``out`` or an extra output name);
        a clear error if the stage has not produced it for this subject."""
        ref = self.read_ref(stage)
        if ref is None or output not in ref.outputs:
            raise PipelineError(f"subject '{self.subject}' has no '{stage}' output yet; run "
                                f"`pipeline run -S {self.subject} --until {stage}` first")
        path = self.object_path(ref.outputs[output])
        if not path.is_dir():
            raise PipelineError(f"the '{stage}' output of subject '{self.subject}' ({path}) is missing; "
                                f"rebuild it with `pipeline run -S {self.subject} --only {stage}`")
        return path

    def refs(self) -> dict[str, Ref]:
        """Every stage ref of this workspace."""
        found = {}
        if self.refs_dir.is_dir():
            for path in sorted(self.refs_dir.glob("*.json")):
                ref = self.read_ref(path.stem)
                if ref is not None:
                    found[ref.stage] = ref
        return found

    def iter_actions(self) -> Iterator[tuple[Path, dict]]:
        """Every (path, record) of ``actions/``."""
        if self.actions_dir.is_dir():
            for path in self.actions_dir.glob("*.json"):
                data = read_json(path)
                if data is not None:
                    yield path, data

    # -- logs ---------------------------------------------------------------------------

    def new_log_path(self, stage: str, key: str) -> Path:
        """A new log file ``logs/<stage>/<timestamp>-<key8>.log``."""
        folder = self.logs_dir / stage
        folder.mkdir(parents=True, exist_ok=True)
        stamp = time.strftime("%Y%m%dT%H%M%S")
        return folder / f"{stamp}-{key[:8]}.log"

    def latest_log(self, stage: str) -> Path | None:
        """The newest log of a stage, or None."""
        folder = self.logs_dir / stage
        logs = sorted(folder.glob("*.log"), key=lambda p: (p.stat().st_mtime_ns, p.name)) if folder.is_dir() else []
        return logs[-1] if logs else None

    # -- garbage collection -------------------------------------------------------------

    def gc(self, keep_days: float = 7.0) -> dict[str, Any]:
        """Delete objects no ref and no action younger than ``keep_days`` reaches.

        Older action records are deleted too, and stage-cache files unused for ``keep_days``
        (``_gc_cache``). Call while holding the lock.
        """
        keep: set[str] = set()
        for ref in self.refs().values():
            keep.update(ref.outputs.values())
        cutoff = time.time() - keep_days * 86400.0
        dropped_actions = 0
        for path, record in list(self.iter_actions()):
            outputs = set((record.get("outputs") or {}).values())
            if path.stat().st_mtime >= cutoff or outputs & keep:
                keep.update(outputs)
            else:
                path.unlink()
                dropped_actions += 1
        removed, freed = [], 0
        if self.objects_dir.is_dir():
            for entry in self.objects_dir.iterdir():
                digest = entry.name.split(".", 1)[0]
                if digest in keep:
                    continue
                if entry.is_dir() and not entry.is_symlink():
                    for folder, _, files in os.walk(entry):
                        freed += sum(os.lstat(os.path.join(folder, f)).st_size for f in files)
                    removed.append(digest)
                remove_tree(entry)
        self.clean_tmp()
        cache_removed, cache_freed = self._gc_cache(cutoff)
        return {"objects_removed": len(removed), "bytes_freed": freed, "actions_removed": dropped_actions,
                "objects_kept": len([d for d in keep if self.object_path(d).is_dir()]),
                "cache_files_removed": cache_removed, "cache_bytes_freed": cache_freed}

    def _gc_cache(self, cutoff: float) -> tuple[int, int]:
        """Delete stage-cache files neither read nor written since ``cutoff`` (epoch seconds).

        Per-item results are keyed by content and code, so every code change leaves the old
        entries behind; nothing else ever removes them. A file counts as used by the later of
        its access and modification times (item-cache hits also refresh the modification time,
        for file systems mounted without access times). Emptied folders go too; the per-stage
        folders stay. Returns (files removed, bytes freed).
        """
        if not self.cache_dir.is_dir():
            return 0, 0
        removed = freed = 0
        for folder, dirs, files in os.walk(self.cache_dir, topdown=False):
            for name in files:
                path = os.path.join(folder, name)
                st = os.lstat(path)
                if max(st.st_atime, st.st_mtime) < cutoff:
                    os.unlink(path)
                    removed += 1
                    freed += st.st_size
            depth = len(Path(folder).relative_to(self.cache_dir).parts)
            if depth >= 2 and not os.listdir(folder):
                os.rmdir(folder)
        return removed, freed


def is_read_only(path: Path) -> bool:
    """Whether a file has no write permission bits (committed objects)."""
    return not (os.stat(path).st_mode & (statmod.S_IWUSR | statmod.S_IWGRP | statmod.S_IWOTH))
