"""Hashing, the stat cache, commits, verification and the lock."""

from __future__ import annotations

import os
import time
from pathlib import Path

import pytest

from pipeline.errors import InputError, WorkspaceLocked
from pipeline.hashing import StatCache, hash_tree, safe_join
from pipeline.workspace import Workspace, is_read_only, is_run_record


def _tree(root: Path) -> Path:
    (root / "a").mkdir(parents=True)
    (root / "a" / "x.bin").write_bytes(b"x" * 100)
    (root / "y.txt").write_text("y")
    return root


def test_tree_digest_depends_on_content_and_names_only(tmp_path: Path) -> None:
    d1, entries = hash_tree(_tree(tmp_path / "one"))
    d2, _ = hash_tree(_tree(tmp_path / "two"))
    assert d1 == d2 and [e.relpath for e in entries] == ["a/x.bin", "y.txt"]
    (tmp_path / "two" / "y.txt").write_text("z")
    assert hash_tree(tmp_path / "two")[0] != d1
    os.rename(tmp_path / "one" / "y.txt", tmp_path / "one" / "w.txt")
    assert hash_tree(tmp_path / "one")[0] != d1


def test_stat_cache_skips_unchanged_files_and_sees_edits(tmp_path: Path) -> None:
    root = _tree(tmp_path / "cap")
    old = time.time() - 60
    for path in (root / "a" / "x.bin", root / "y.txt"):
        os.utime(path, (old, old))
    cache = StatCache(tmp_path / "cache.sqlite")
    first = hash_tree(root, stat_cache=cache, allow_symlinks=True)[0]
    cache.flush()
    warm = StatCache(tmp_path / "cache.sqlite")
    assert hash_tree(root, stat_cache=warm, allow_symlinks=True)[0] == first
    assert warm.hits == 2 and warm.misses == 0
    (root / "y.txt").write_text("changed")
    assert hash_tree(root, stat_cache=warm, allow_symlinks=True)[0] != first


def test_symlinks(tmp_path: Path) -> None:
    root = _tree(tmp_path / "cap")
    (root / "inside").symlink_to(root / "y.txt")
    hash_tree(root, allow_symlinks=True)  # inside the folder: followed
    with pytest.raises(InputError, match="may not contain symlinks"):
        hash_tree(root, allow_symlinks=False)
    (tmp_path / "secret").write_text("s")
    (root / "out").symlink_to(tmp_path / "secret")
    with pytest.raises(InputError, match="outside its folder"):
        hash_tree(root, allow_symlinks=True)
    with pytest.raises(InputError, match="escapes its folder"):
        safe_join(root, "../secret")
    with pytest.raises(InputError, match="outside"):
        safe_join(root, "out")
    assert safe_join(root, "a/x.bin") == root / "a" / "x.bin"


def test_commit_is_read_only_deduplicated_and_verifiable(tmp_path: Path) -> None:
    ws = Workspace(tmp_path / "ws", "alice")
    ws.ensure()
    digest = ws.commit(_tree(ws.new_temp_dir("s")))
    obj = ws.object_path(digest)
    assert ws.has_object(digest) and is_read_only(obj / "y.txt")
    again = ws.new_temp_dir("s")
    assert ws.commit(_tree(again)) == digest and not again.exists()
    assert ws.verify_object(digest) == []
    os.chmod(obj / "a" / "x.bin", 0o644)
    (obj / "a" / "x.bin").write_bytes(b"x" * 99 + b"y")
    problems = ws.verify_object(digest)
    assert problems == ["a/x.bin: content changed"]
    ws.mark_corrupt(digest, problems)
    assert not ws.has_object(digest)
    assert ws.commit(_tree(ws.new_temp_dir("s"))) == digest  # rebuilt, replaces the corrupt copy
    assert ws.has_object(digest) and ws.verify_object(digest) == []
    link_dir = ws.new_temp_dir("s")
    (link_dir / "l").symlink_to("/etc/hostname")
    with pytest.raises(InputError, match="symlinks"):
        ws.commit(link_dir)


def test_lock_is_exclusive_and_names_holder(tmp_path: Path) -> None:
    ws = Workspace(tmp_path / "ws", "alice")
    other = Workspace(tmp_path / "ws", "bob")
    with ws.lock():
        with pytest.raises(WorkspaceLocked, match=f"PID {os.getpid()}"):
            ws.lock().acquire()
        with other.lock():
            pass
    with ws.lock():
        pass


def test_odd_file_names_round_trip_through_the_manifest(tmp_path: Path) -> None:
    ws = Workspace(tmp_path / "ws", "alice")
    ws.ensure()
    folder = ws.new_temp_dir("odd")
    for name in ("tab\there", "new\nline", "ünï cödé", os.fsdecode(b"raw\xffbyte")):
        (folder / name).write_bytes(os.fsencode(name))
    digest = ws.commit(folder)
    assert ws.verify_object(digest) == []
    assert len(ws.manifest(digest)) == 4


def test_stat_cache_skips_undecodable_names(tmp_path: Path) -> None:
    root = tmp_path / "cap"
    root.mkdir()
    odd = root / os.fsdecode(b"raw\xffbyte")
    odd.write_bytes(b"x")
    old = time.time() - 60
    os.utime(odd, (old, old))
    cache = StatCache(tmp_path / "cache.sqlite")
    first = hash_tree(root, stat_cache=cache, allow_symlinks=True)[0]
    cache.flush()
    assert hash_tree(root, stat_cache=StatCache(tmp_path / "cache.sqlite"), allow_symlinks=True)[0] == first


def test_gc_drops_cache_files_unused_for_keep_days(tmp_path: Path) -> None:
    ws = Workspace(tmp_path / "ws", "alice")
    ws.ensure()
    stale = ws.cache_dir / "capture" / "items" / "mod.fn" / "ab" / "abc.npz"
    fresh = ws.cache_dir / "capture" / "items" / "mod.fn" / "cd" / "cde.npz"
    ckpt = ws.cache_dir / "train" / "key1" / "ours.pt"
    for path in (stale, fresh, ckpt):
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(b"x" * 1000)
    ten_days_ago = time.time() - 10 * 86400
    os.utime(stale, (ten_days_ago, ten_days_ago))
    os.utime(ckpt, (ten_days_ago, ten_days_ago))
    two_days_ago = time.time() - 2 * 86400
    os.utime(fresh, (two_days_ago, two_days_ago))
    with ws.lock():
        report = ws.gc(keep_days=7)
    assert report["cache_files_removed"] == 2 and report["cache_bytes_freed"] == 2000
    assert fresh.is_file() and not stale.exists() and not ckpt.exists()
    assert not stale.parent.exists() and not ckpt.parent.exists()  # emptied folders go
    assert (ws.cache_dir / "train").is_dir() and (ws.cache_dir / "capture").is_dir()  # per-stage folders stay


def test_item_cache_hit_marks_the_entry_used(tmp_path: Path) -> None:
    from pipeline.executors import LocalExecutor
    from pipeline.itemcache import ItemCache

    ws = Workspace(tmp_path / "ws", "alice")
    ws.ensure()
    cache = ItemCache(ws.cache_dir / "s" / "items")
    with LocalExecutor(workers=1) as pool:
        assert cache.map(pool, abs, [-3], str) == [3]
        (entry,) = list((ws.cache_dir / "s" / "items").rglob("*.npz"))
        ten_days_ago = time.time() - 10 * 86400
        os.utime(entry, (ten_days_ago, ten_days_ago))
        assert cache.map(pool, abs, [-3], str) == [3] and cache.hits == 1
    # The modification time, not only the access time (a noatime mount never updates that).
    assert entry.stat().st_mtime > time.time() - 60
    with ws.lock():
        assert ws.gc(keep_days=7)["cache_files_removed"] == 0
    assert entry.is_file()


def test_content_key_leaves_out_the_runner_metrics_only(tmp_path: Path) -> None:
    ws = Workspace(tmp_path / "ws", "alice")
    ws.ensure()

    def commit(metrics: str | None, data: str = "y") -> str:
        folder = ws.new_temp_dir("t")
        _tree(folder)
        (folder / "y.txt").write_text(data)
        if metrics is not None:
            (folder / "metrics.json").write_text(metrics)
        return ws.commit(folder)

    plain = commit(None)
    assert ws.content_key(plain) == plain
    first, second = commit('{"seconds": 1.0}'), commit('{"seconds": 2.0}')
    assert first != second and ws.content_key(first) == ws.content_key(second) != first
    assert ws.content_key(commit('{"seconds": 1.0}', data="z")) != ws.content_key(first)
    assert ws.content_key("0" * 64) == "0" * 64  # no manifest: the digest itself


def test_content_key_leaves_out_the_stages_run_records(tmp_path: Path) -> None:
    ws = Workspace(tmp_path / "ws", "alice")
    ws.ensure()

    def commit(curve: str, data: str = "y") -> str:
        folder = ws.new_temp_dir("t")
        _tree(folder)
        (folder / "y.txt").write_text(data)
        (folder / "tb").mkdir()
        (folder / "tb" / f"events.{curve}").write_text(curve)
        (folder / "curve.json").write_text(curve)
        return ws.commit(folder)

    records = ("curve.json", "tb/*")
    first, second = commit("1.0"), commit("2.0")
    assert ws.content_key(first) != ws.content_key(second)  # the records are data unless declared
    assert ws.content_key(first, records) == ws.content_key(second, records)
    assert ws.content_key(commit("1.0", data="z"), records) != ws.content_key(first, records)
    assert ws.content_key(first, ("curve.json",)) != ws.content_key(second, ("curve.json",))  # tb/ still differs
    assert is_run_record("metrics.json") and is_run_record("tb/a/b", ("tb/*",)) and not is_run_record("y.txt", records)
