"""BLAKE3 content digests of files and folder trees, with a stat cache for big imports.

A tree digest is BLAKE3 over its sorted manifest (``relpath \\t size \\t file digest`` per
line), so the same files give the same digest wherever they live. The manifest is kept
beside each committed object so ``pipeline status --verify`` can say which file changed.
"""

from __future__ import annotations

import array
import json
import os
import sqlite3
import stat as statmod
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable

import blake3

from pipeline.errors import InputError

# Files above this size are hashed with memory mapping and BLAKE3's own threads.
_MMAP_MIN_BYTES = 8 << 20
_CHUNK_BYTES = 1 << 20
# A file modified this recently may be modified again within the same mtime tick ("racy
# git"): its digest is not cached, so a later edit is never hidden behind a stale entry.
_RACY_WINDOW_NS = 2_000_000_000


def hash_bytes(data: bytes) -> str:
    """BLAKE3 hex digest of ``data``."""
    return blake3.blake3(data).hexdigest()


def hash_file(path: Path | str) -> str:
    """BLAKE3 hex digest of one file's content."""
    size = os.path.getsize(path)
    if size >= _MMAP_MIN_BYTES:
        hasher = blake3.blake3(max_threads=blake3.blake3.AUTO)
        hasher.update_mmap(path)
        return hasher.hexdigest()
    hasher = blake3.blake3()
    with open(path, "rb") as handle:
        while chunk := handle.read(_CHUNK_BYTES):
            hasher.update(chunk)
    return hasher.hexdigest()


@dataclass(frozen=True)
class ManifestEntry:
    """One file of a tree: path relative to the tree root (``/``-separated), size, digest."""

    relpath: str
    size: int
    digest: str


def manifest_text(entries: Iterable[ManifestEntry]) -> str:
    """The canonical manifest: sorted lines ``"relpath" TAB size TAB digest`` (the path JSON-quoted,
    so tabs, newlines or undecodable bytes in file names cannot break the format)."""
    return "".join(f"{json.dumps(e.relpath)}\t{e.size}\t{e.digest}\n"
                   for e in sorted(entries, key=lambda e: e.relpath))


def parse_manifest(text: str) -> list[ManifestEntry]:
    """Inverse of ``manifest_text``."""
    entries = []
    for line in text.splitlines():
        relpath, size, digest = line.rsplit("\t", 2)
        entries.append(ManifestEntry(json.loads(relpath), int(size), digest))
    return entries


def manifest_digest(entries: Iterable[ManifestEntry]) -> str:
    """The digest of a tree: BLAKE3 of its canonical manifest."""
    return hash_bytes(manifest_text(entries).encode("utf-8"))


# A file found by a walk: (path relative to the root, absolute path, lstat result). A plain
# tuple: a 30k-file walk builds 30k of them on the no-op path, where every microsecond counts.
_FileRef = tuple[str, str, os.stat_result]


def _walk_files(root: Path, *, allow_symlinks: bool) -> list[_FileRef]:
    """Every regular file under ``root``; symlinks refused, or followed only inside ``root``."""
    real_root = os.path.realpath(root)
    found: list[_FileRef] = []
    visited: set[str] = {real_root}
    stack: list[tuple[str, str]] = [(str(root), "")]
    while stack:
        folder, prefix = stack.pop()
        with os.scandir(folder) as entries:
            for entry in entries:
                rel = f"{prefix}{entry.name}"
                if entry.is_symlink():
                    if not allow_symlinks:
                        raise InputError(f"{os.path.join(folder, entry.name)}: stage outputs may not "
                                         f"contain symlinks; write a copy of the file instead")
                    target = os.path.realpath(entry.path)
                    if target != real_root and not target.startswith(real_root + os.sep):
                        raise InputError(f"{entry.path}: symlink points outside its folder {root} "
                                         f"(to {target}); imported folders must be self-contained, "
                                         f"copy the file in instead")
                    if os.path.isdir(target):
                        if target in visited:
                            continue
                        visited.add(target)
                        stack.append((entry.path, rel + "/"))
                        continue
                    if not os.path.exists(target):
                        raise InputError(f"{entry.path}: broken symlink (to {target})")
                    found.append((rel, entry.path, os.stat(entry.path)))
                elif entry.is_dir(follow_symlinks=False):
                    stack.append((entry.path, rel + "/"))
                elif entry.is_file(follow_symlinks=False):
                    found.append((rel, entry.path, entry.stat(follow_symlinks=False)))
                else:
                    raise InputError(f"{entry.path}: not a regular file or folder (socket, fifo or "
                                     f"device); remove it")
    return found


def safe_join(root: Path, relpath: str) -> Path:
    """``root / relpath`` for a path read from a file, refusing ``..``, absolute paths and
    symlinks that lead outside ``root``."""
    rel = Path(relpath)
    if rel.is_absolute() or ".." in rel.parts:
        raise InputError(f"{relpath}: path escapes its folder {root}; only paths inside it are allowed")
    joined = root / rel
    real_root = os.path.realpath(root)
    real = os.path.realpath(joined)
    if real != real_root and not real.startswith(real_root + os.sep):
        raise InputError(f"{joined}: resolves to {real}, outside {root} (a symlink out); refused")
    return joined


def _storable(path: str) -> bool:
    """Whether sqlite can store this path (names with undecodable bytes are simply not cached)."""
    try:
        path.encode("utf-8")
    except UnicodeEncodeError:
        return False
    return True


class StatCache:
    """``(path, device, inode, size, mtime_ns) -> BLAKE3 digest`` kept in one sqlite file.

    Loaded whole into memory on open (a 30k-file capture is a few MB); new digests are written
    in one transaction by ``flush`` (sqlite makes each flush atomic; concurrent readers and a
    writer are safe).
    """

    def __init__(self, db_path: Path) -> None:
        self.db_path = db_path
        self._loaded: dict[str, tuple[int, int, int, int, str]] | None = None
        self._pending: dict[str, tuple[int, int, int, int, str]] = {}
        self._pending_trees: dict[str, tuple[str, str]] = {}
        self.hits = 0
        self.misses = 0
        db_path.parent.mkdir(parents=True, exist_ok=True)
        with self._connect() as db:
            db.execute("CREATE TABLE IF NOT EXISTS files (path TEXT PRIMARY KEY, dev INTEGER, ino INTEGER, "
                       "size INTEGER, mtime_ns INTEGER, digest TEXT)")
            db.execute("CREATE TABLE IF NOT EXISTS trees (root TEXT PRIMARY KEY, fingerprint TEXT, digest TEXT)")

    @property
    def _entries(self) -> dict[str, tuple[int, int, int, int, str]]:
        # Loaded on the first per-file lookup: a warm tree whose fingerprint matches never needs it.
        if self._loaded is None:
            with self._connect() as db:
                self._loaded = {path: (dev, ino, size, mtime_ns, digest)
                                for path, dev, ino, size, mtime_ns, digest in db.execute("SELECT * FROM files")}
        return self._loaded

    def tree_lookup(self, root: str, fingerprint: str) -> str | None:
        """The digest of a whole tree whose stat fingerprint is unchanged since it was stored."""
        if not _storable(root):
            return None
        pending = self._pending_trees.get(root)
        if pending is not None:
            return pending[1] if pending[0] == fingerprint else None
        with self._connect() as db:
            row = db.execute("SELECT fingerprint, digest FROM trees WHERE root = ?", (root,)).fetchone()
        return row[1] if row is not None and row[0] == fingerprint else None

    def tree_store(self, root: str, fingerprint: str, digest: str) -> None:
        """Remember a tree's digest under the fingerprint of its files' stats."""
        if not _storable(root):
            return
        self._pending_trees[root] = (fingerprint, digest)

    def _connect(self) -> sqlite3.Connection:
        return sqlite3.connect(self.db_path, timeout=30.0)

    def lookup(self, abspath: str, st: os.stat_result) -> str | None:
        """The cached digest if the file's identity and stat are unchanged."""
        hit = self._entries.get(abspath)
        if hit is not None and hit[:4] == (st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns):
            self.hits += 1
            return hit[4]
        self.misses += 1
        return None

    def store(self, abspath: str, st: os.stat_result, digest: str) -> bool:
        """Remember a digest (not for files modified in the last two seconds: racy); whether stored."""
        if time.time_ns() - st.st_mtime_ns < _RACY_WINDOW_NS or not _storable(abspath):
            return False
        row = (st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns, digest)
        self._entries[abspath] = row
        self._pending[abspath] = row
        return True

    def flush(self) -> None:
        """Write new digests to disk in one transaction."""
        if not self._pending and not self._pending_trees:
            return
        with self._connect() as db:
            db.executemany("INSERT OR REPLACE INTO files VALUES (?, ?, ?, ?, ?, ?)",
                           [(path, *row) for path, row in self._pending.items()])
            db.executemany("INSERT OR REPLACE INTO trees VALUES (?, ?, ?)",
                           [(root, *row) for root, row in self._pending_trees.items()])
        self._pending.clear()
        self._pending_trees.clear()


def hash_tree(root: Path, *, stat_cache: StatCache | None = None, allow_symlinks: bool = False,
              threads: int | None = None) -> tuple[str, list[ManifestEntry]]:
    """(tree digest, manifest) of every file under ``root``.

    Stage outputs refuse symlinks; external inputs (``allow_symlinks=True``) follow only
    symlinks that stay inside ``root``. With a ``stat_cache`` unchanged files are not re-read.
    """
    return _hash_files(_walk_files(root, allow_symlinks=allow_symlinks), stat_cache, threads)


def _hash_files(files: list[_FileRef], stat_cache: StatCache | None,
                threads: int | None = None) -> tuple[str, list[ManifestEntry]]:
    digests: dict[str, str] = {}
    todo: list[_FileRef] = []
    for ref in files:
        cached = stat_cache.lookup(ref[1], ref[2]) if stat_cache is not None else None
        if cached is None:
            todo.append(ref)
        else:
            digests[ref[0]] = cached
    if todo:
        workers = threads or min(8, 2 * (os.cpu_count() or 1))
        if len(todo) > 8 and workers > 1:
            # BLAKE3 releases the GIL while hashing, so threads overlap reads and hashing.
            with ThreadPoolExecutor(max_workers=workers) as pool:
                results = list(pool.map(lambda r: hash_file(r[1]), todo, chunksize=64))
        else:
            results = [hash_file(r[1]) for r in todo]
        for ref, digest in zip(todo, results):
            digests[ref[0]] = digest
            if stat_cache is not None:
                stat_cache.store(ref[1], ref[2], digest)
    entries = [ManifestEntry(rel, st.st_size, digests[rel]) for rel, _, st in files]
    return manifest_digest(entries), sorted(entries, key=lambda e: e.relpath)


def hash_path(path: Path, *, stat_cache: StatCache | None = None) -> str:
    """Digest of an external input: a file's content digest, or a folder's tree digest."""
    st = os.stat(path)
    if statmod.S_ISDIR(st.st_mode):
        if stat_cache is None:
            return hash_tree(path, stat_cache=None, allow_symlinks=True)[0]
        return _cached_tree_digest(Path(path), stat_cache)
    abspath = os.path.abspath(path)
    cached = stat_cache.lookup(abspath, st) if stat_cache is not None else None
    if cached is not None:
        return cached
    digest = hash_file(path)
    if stat_cache is not None:
        stat_cache.store(abspath, st, digest)
    return digest


def _stat_fingerprint(files: list[_FileRef]) -> str:
    numbers = array.array("q")
    for _, _, st in files:
        numbers.extend((st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns))
    hasher = blake3.blake3("\0".join([ref[0] for ref in files]).encode("utf-8", "surrogateescape"))
    hasher.update(numbers.tobytes())
    return hasher.hexdigest()


def _cached_tree_digest(root: Path, stat_cache: StatCache) -> str:
    """A folder's tree digest; when no file's (path, inode, size, mtime) changed since the last
    time, the stored digest is returned without a per-file lookup (the no-op fast path)."""
    files = _walk_files(root, allow_symlinks=True)
    files.sort()
    fingerprint = _stat_fingerprint(files)
    key = os.path.abspath(root)
    digest = stat_cache.tree_lookup(key, fingerprint)
    if digest is not None:
        stat_cache.hits += len(files)
        return digest
    digest, _ = _hash_files(files, stat_cache)
    now = time.time_ns()
    if all(now - ref[2].st_mtime_ns >= _RACY_WINDOW_NS for ref in files):
        stat_cache.tree_store(key, fingerprint, digest)
    return digest
