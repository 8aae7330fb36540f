"""End-to-end behaviour of ``pipeline run`` over the toy project (real stages, subprocesses)."""

from __future__ import annotations

import json
import os
import signal
import time
from pathlib import Path

from pipeline_toy_support import ToyProject

ALL = {"source", "source_eval", "double", "total", "side"}


def _objects(ws: Path) -> set[str]:
    return {p.name for p in (ws / "objects").iterdir() if p.is_dir()}


def test_second_run_does_nothing(toy: ToyProject) -> None:
    assert toy.cli("run", "-S", "alice").ran == ALL
    before = _objects(toy.ws())
    again = toy.cli("run", "-S", "alice")
    assert again.ran == set()
    assert _objects(toy.ws()) == before
    status = toy.cli("status", "-S", "alice").stdout
    assert all(" fresh" in line for line in status.splitlines()), status


def test_param_edit_reruns_stage_and_downstream_only(toy: ToyProject) -> None:
    toy.cli("run", "-S", "alice")
    toy.edit("configs/presets/tiny.yaml", "factor: 3", "factor: 4")
    status = toy.cli("status", "-S", "alice").stdout
    assert "params changed: factor: 3 -> 4" in status
    assert "upstream 'double' is stale" in status
    plan = toy.cli("run", "-S", "alice", "--dry-run")
    assert plan.ran == set() and "run    double" in plan.stdout and "skip   side" in plan.stdout
    assert toy.cli("run", "-S", "alice", "--only", "double").ran == {"double"}
    total_line = next(line for line in toy.cli("status", "-S", "alice").stdout.splitlines()
                      if line.startswith("total "))
    assert "stale" in total_line and "input changed: double" in total_line
    assert toy.cli("run", "-S", "alice").ran == {"total"}
    # --set on top of the preset: same rule.
    assert toy.cli("run", "-S", "alice", "--set", "total.offset=2.5").ran == {"total"}
    # Back to an earlier configuration: the cached action is reused, nothing runs.
    back = toy.cli("run", "-S", "alice")
    assert back.ran == set() and "reused total" in back.stdout


def test_comment_only_edit_reruns_nothing_code_edit_does(toy: ToyProject) -> None:
    toy.cli("run", "-S", "alice")
    toy.edit("toy_stages/double/stage.py", "def run(ctx: StageContext) -> None:\n",
             "def run(ctx: StageContext) -> None:\n    \"\"\"A new docstring.\"\"\"\n    # a new comment\n\n")
    toy.edit("toy_lib/arith.py", "    value, factor, mode = item", "    value, factor, mode = item  # unpack")
    assert toy.cli("run", "-S", "alice").ran == set()
    # A code change in a declared module that leaves the output identical: double reruns,
    # its output digest is unchanged, so total is not rerun (early cutoff).
    toy.edit("toy_lib/arith.py", "return value * factor if", "return factor * value if")
    assert "code changed" in toy.cli("status", "-S", "alice").stdout
    assert toy.cli("run", "-S", "alice").ran == {"double"}
    # A change of behaviour reaches downstream.
    toy.edit("toy_stages/total/stage.py", "total = sum(numbers) + ctx.params.offset",
             "total = sum(numbers) + ctx.params.offset + 1")
    assert toy.cli("run", "-S", "alice").ran == {"total"}


def test_rerun_with_identical_data_stops_there_whatever_its_timings(toy: ToyProject) -> None:
    """A forced source reruns with the same numbers but another ``source_seconds`` and another
    timing in its run record ``log/run.txt``: its object digest changes, its data do not. Stages
    keyed on data stay fresh; ``side``, which reads the source's metrics, reruns."""
    toy.cli("run", "-S", "alice")
    before = json.loads((toy.ws() / "refs" / "source.json").read_text())["outputs"]["out"]
    forced = toy.cli("run", "-S", "alice", "--force", "source")
    after = json.loads((toy.ws() / "refs" / "source.json").read_text())["outputs"]["out"]
    assert after != before, "the timing should have changed the source object"
    assert forced.ran == {"source", "side"}
    assert toy.cli("run", "-S", "alice").ran == set()
    status = toy.cli("status", "-S", "alice").stdout
    assert all(" fresh" in line for line in status.splitlines()), status
    # New data still reach every stage below.
    assert toy.cli("run", "-S", "alice", "--set", "source.seed=7").ran == ALL


def test_actions_recorded_before_content_keys_are_still_found(toy: ToyProject) -> None:
    """A workspace written when actions were keyed on full input digests stays fresh after the
    upgrade: nothing reruns, and the refs move to the new keys."""
    from pipeline.hashing import hash_bytes

    toy.cli("run", "-S", "alice")
    ws = toy.ws()
    for stage in ("double", "total", "source_eval"):
        ref_file = ws / "refs" / f"{stage}.json"
        ref = json.loads(ref_file.read_text())
        record = json.loads((ws / "actions" / f"{ref['action']}.json").read_text())
        body = {k: record[k] for k in ("stage", "code", "params", "inputs", "external")}
        legacy = hash_bytes(json.dumps(body, sort_keys=True, separators=(",", ":")).encode())
        assert legacy != ref["action"], f"{stage}: an input with metrics should key differently"
        (ws / "actions" / f"{ref['action']}.json").unlink()
        record.pop("input_keys")
        (ws / "actions" / f"{legacy}.json").write_text(json.dumps({**record, "key": legacy}))
        ref_file.write_text(json.dumps({**ref, "action": legacy}))
    status = toy.cli("status", "-S", "alice").stdout
    assert all(" fresh" in line for line in status.splitlines()), status
    assert toy.cli("run", "-S", "alice").ran == set()
    for stage in ("double", "total"):
        ref = json.loads((ws / "refs" / f"{stage}.json").read_text())
        assert (ws / "actions" / f"{ref['action']}.json").is_file()
        assert json.loads((ws / "actions" / f"{ref['action']}.json").read_text())["key"] == ref["action"]


def test_actions_keyed_on_content_with_run_records_are_still_found(toy: ToyProject) -> None:
    """A workspace written when content keys still held the producing stage's run records stays
    fresh after the upgrade: nothing reruns, and the refs move to the new keys."""
    from pipeline.hashing import hash_bytes
    from pipeline.workspace import Workspace

    toy.cli("run", "-S", "alice")
    ws_dir = toy.ws()
    ws = Workspace(ws_dir.parent, "alice")
    for stage in ("double", "source_eval"):
        ref_file = ws_dir / "refs" / f"{stage}.json"
        ref = json.loads(ref_file.read_text())
        record = json.loads((ws_dir / "actions" / f"{ref['action']}.json").read_text())
        with_records = {inp: ws.content_key(digest) for inp, digest in record["inputs"].items()}
        body = {k: record[k] for k in ("stage", "code", "params", "external")}
        old_key = hash_bytes(json.dumps({**body, "inputs": with_records}, sort_keys=True,
                                        separators=(",", ":")).encode())
        if stage == "double":  # its input holds log/run.txt: the old key differs
            assert old_key != ref["action"]
        (ws_dir / "actions" / f"{ref['action']}.json").unlink()
        (ws_dir / "actions" / f"{old_key}.json").write_text(json.dumps({**record, "key": old_key,
                                                                        "input_keys": with_records}))
        ref_file.write_text(json.dumps({**ref, "action": old_key}))
    status = toy.cli("status", "-S", "alice").stdout
    assert all(" fresh" in line for line in status.splitlines()), status
    assert toy.cli("run", "-S", "alice").ran == set()
    ref = json.loads((ws_dir / "refs" / "double.json").read_text())
    assert json.loads((ws_dir / "actions" / f"{ref['action']}.json").read_text())["key"] == ref["action"]


def test_selection_options_select_exactly(toy: ToyProject) -> None:
    assert toy.cli("run", "-S", "alice", "--until", "double").ran == {"source", "double"}
    assert toy.cli("run", "-S", "alice", "--from", "double").ran == {"total"}
    assert toy.cli("run", "-S", "alice", "--only", "side", "source_eval").ran == {"side", "source_eval"}
    assert toy.cli("run", "-S", "alice").ran == set()
    assert toy.cli("run", "-S", "alice", "--only", "double", "--force").ran == {"double"}
    assert toy.cli("run", "-S", "alice", "--from", "double", "--force").ran == {"double", "total"}
    assert toy.cli("run", "-S", "alice", "--force", "side").ran == {"side"}
    assert toy.cli("run", "-S", "alice", "--force").ran == ALL
    # An input outside the selection without an output: a clear error, exit 1.
    missing = toy.cli("run", "-S", "bob", "--only", "total", expect=1)
    assert "needs 'double'" in missing.stderr and "--until double" in missing.stderr
    bad = toy.cli("run", "-S", "alice", "--only", "nope", expect=2)
    assert "unknown stage" in bad.stderr


def test_sigkill_mid_write_leaves_nothing_and_is_redone(toy: ToyProject, tmp_path: Path) -> None:
    hold = tmp_path / "hold"
    proc = toy.popen("run", "-S", "alice", TOY_HOLD_FILE=str(hold))
    started = Path(str(hold) + ".started")
    deadline = time.monotonic() + 30
    while not started.exists():
        assert proc.poll() is None, proc.communicate()
        assert time.monotonic() < deadline, "double never started"
        time.sleep(0.05)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    ws = toy.ws()
    assert not (ws / "refs" / "double.json").exists()
    assert (ws / "refs" / "source.json").exists()
    for obj in _objects(ws):
        assert not (ws / "objects" / obj / "partial.bin").exists()
    assert any((ws / "tmp").iterdir()), "the killed run's temp folder should still be there"
    again = toy.cli("run", "-S", "alice")
    assert again.ran == {"double", "total", "side"}
    assert not any((ws / "tmp").iterdir())
    # SIGTERM (a batch scheduler stopping the job): the run unwinds and removes its temp output.
    started.unlink()
    proc = toy.popen("run", "-S", "alice", "--force", "double", TOY_HOLD_FILE=str(hold))
    while not started.exists():
        assert proc.poll() is None, proc.communicate()
        time.sleep(0.05)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err
    assert not any((ws / "tmp").iterdir())


def test_second_run_on_same_subject_fails_at_once_other_subject_proceeds(toy: ToyProject, tmp_path: Path) -> None:
    hold = tmp_path / "hold"
    first = toy.popen("run", "-S", "alice", TOY_HOLD_FILE=str(hold))
    try:
        started = Path(str(hold) + ".started")
        deadline = time.monotonic() + 30
        while not started.exists():
            assert first.poll() is None, first.communicate()
            assert time.monotonic() < deadline
            time.sleep(0.05)
        t0 = time.monotonic()
        second = toy.cli("run", "-S", "alice", expect=1)
        assert time.monotonic() - t0 < 10
        assert "in use by another pipeline run" in second.stderr
        assert f"PID {first.pid}" in second.stderr
        assert toy.cli("run", "-S", "bob").ran == ALL
    finally:
        hold.write_text("go")
        out, err = first.communicate(timeout=60)
    assert first.returncode == 0, err


def test_flipped_byte_found_by_verify_and_rebuilt(toy: ToyProject) -> None:
    toy.cli("run", "-S", "alice")
    ws = toy.ws()
    ref = json.loads((ws / "refs" / "double.json").read_text())
    target = ws / "objects" / ref["outputs"]["out"] / "numbers.json"
    os.chmod(target, 0o644)
    original = target.read_bytes()
    data = bytearray(original)
    data[1] ^= 0x01
    target.write_bytes(bytes(data))
    assert "corrupt" not in toy.cli("status", "-S", "alice").stdout  # cheap status does not re-hash
    verify = toy.cli("status", "-S", "alice", "--verify").stdout
    double_line = next(line for line in verify.splitlines() if line.startswith("double "))
    assert "corrupt" in double_line and "numbers.json: content changed" in double_line
    rebuilt = toy.cli("run", "-S", "alice")
    assert rebuilt.ran == {"double"}  # same bytes again: downstream stays fresh
    assert target.read_bytes() == original
    final = toy.cli("status", "-S", "alice", "--verify").stdout
    assert all(" fresh" in line for line in final.splitlines()), final


def test_bad_config_value_names_file_key_and_allowed_values(toy: ToyProject) -> None:
    (toy.root / "configs/subjects/carol.yaml").write_text("preset: tiny\ndouble:\n  mode: pow\n")
    bad = toy.cli("run", "-S", "carol", expect=2)
    assert "configs/subjects/carol.yaml" in bad.stderr and "double.mode" in bad.stderr
    assert "'mul'" in bad.stderr and "'add'" in bad.stderr
    assert "Traceback" not in bad.stderr and len(bad.stderr.strip().splitlines()) == 1
    setbad = toy.cli("run", "-S", "alice", "--set", "source.count=0", expect=2)
    assert "--set source.count=0" in setbad.stderr and "source.count" in setbad.stderr and "ge 1" in setbad.stderr
    (toy.root / "configs/presets/typo.yaml").write_text("double:\n  factr: 2\n")
    typo = toy.cli("run", "-S", "alice", "--preset", "typo", expect=2)
    assert "configs/presets/typo.yaml" in typo.stderr and "double.factr" in typo.stderr
    assert "allowed keys: factor, mode" in typo.stderr
    (toy.root / "configs/presets/stray.yaml").write_text("tracking:\n  x: 1\n")
    stray = toy.cli("status", "-S", "alice", "--preset", "stray", expect=2)
    assert "section 'tracking' is not a stage" in stray.stderr
    assert "no such preset" in toy.cli("run", "-S", "alice", "--preset", "nope", expect=2).stderr
    assert toy.cli("run", "-S", "alice", "--bogus", expect=2).returncode == 2


def test_imported_folder_stat_cache_and_symlink_escape(toy: ToyProject, tmp_path: Path) -> None:
    capture = tmp_path / "capture"
    capture.mkdir()
    for i in range(5):
        (capture / f"{i}.txt").write_text(f"{i}\n")
    old = time.time() - 60  # older than the stat cache's racy window
    for f in capture.iterdir():
        os.utime(f, (old, old))
    imp = f"source.import_dir={capture}"
    assert toy.cli("run", "-S", "alice", "--set", imp).ran == ALL
    for f in capture.iterdir():  # touched, same bytes: no rerun
        os.utime(f, None)
    assert toy.cli("run", "-S", "alice", "--set", imp).ran == set()
    (capture / "3.txt").write_text("30\n")
    changed = toy.cli("status", "-S", "alice", "--set", imp).stdout
    assert f"external input changed: {capture}" in changed
    assert "source" in toy.cli("run", "-S", "alice", "--set", imp).ran
    outside = tmp_path / "outside.txt"
    outside.write_text("7\n")
    (capture / "evil.txt").symlink_to(outside)
    escaped = toy.cli("run", "-S", "alice", "--set", imp, expect=1)
    assert "outside its folder" in escaped.stderr and "evil.txt" in escaped.stderr


def test_show_log_gc_dag_and_extra_command(toy: ToyProject) -> None:
    toy.cli("run", "-S", "alice")
    merged = json.loads(toy.cli("show", "-S", "alice", "source", "--json").stdout)
    assert merged.pop("source_seconds") > 0
    assert merged == {"numbers": 4, "rig_bars": 4, "sum_abs_err": 0}
    full = json.loads(toy.cli("show", "-S", "alice", "source", "--json", "--full").stdout)
    assert full["provenance"]["params"]["rig"] == {"name": "toyrig", "bars": 4}
    assert Path(full["path"]).is_dir() and full["evaluation"]["stage"] == "source_eval"
    text = toy.cli("show", "-S", "alice", "double").stdout
    assert "max_value" in text and "input    source" in text
    assert "doubled 4 numbers" in toy.cli("log", "-S", "alice", "double").stdout
    toy.cli("run", "-S", "alice", "--set", "double.factor=7")
    toy.cli("run", "-S", "alice")
    before = _objects(toy.ws())
    gc = toy.cli("gc", "-S", "alice", "--keep-days", "0").stdout
    after = _objects(toy.ws())
    assert len(before - after) == 2 and "removed 2 object(s)" in gc  # double and total of factor=7
    assert toy.cli("run", "-S", "alice").ran == set()
    dot = toy.cli("dag", "--format", "dot").stdout
    assert '"source" -> "source_eval" [style=dashed, label="truth"]' in dot
    assert "double <- source" in toy.cli("dag").stdout
    assert toy.cli("hello", "world").stdout.strip() == "hello world"
    assert toy.cli("hello", "--fail", expect=3).returncode == 3


def test_stage_failure_keeps_refs_and_prints_resume_command(toy: ToyProject) -> None:
    toy.cli("run", "-S", "alice")
    ref_before = (toy.ws() / "refs" / "total.json").read_text()
    toy.edit("toy_stages/total/stage.py", "total = sum(numbers)", "total = sum(numbers) / 0.0 + sum(numbers)")
    failed = toy.cli("run", "-S", "alice", "--preset", "other", expect=1)
    assert "stage 'total' failed: ZeroDivisionError" in failed.stderr
    assert "pipeline run -S alice --from total --preset other" in failed.stderr
    assert "Traceback" not in failed.stderr
    assert "ZeroDivisionError" in toy.cli("log", "-S", "alice", "total").stdout.split("Traceback")[-1]
    assert (toy.ws() / "refs" / "total.json").read_text() == ref_before
    assert not any((toy.ws() / "tmp").iterdir())


def test_missing_stage_module_is_an_error_only_when_needed(toy: ToyProject) -> None:
    cfg = toy.root / "configs/pipeline.yaml"
    cfg.write_text(cfg.read_text().replace("  side: toy_stages.side.stage\n",
                                           "  side: toy_stages.side.stage\n  later: toy_stages.later.stage\n"))
    assert "later  [unloadable" in toy.cli("dag").stdout
    assert toy.cli("run", "-S", "alice", "--until", "total").ran == {"source", "double", "total"}
    full = toy.cli("run", "-S", "alice", expect=2)
    assert "later: configs/pipeline.yaml stages.later (toy_stages.later.stage): module not found" in full.stderr
    cfg.write_text(cfg.read_text().replace("toy_stages.later.stage", "toy_stages.side.stage"))
    renamed = toy.cli("run", "-S", "alice", expect=2)
    assert "declares stage 'side', not 'later'" in renamed.stderr


def test_workers_process_pool(toy: ToyProject) -> None:
    toy.cli("run", "-S", "alice", "--until", "double", "--workers", "2")
    numbers = json.loads(toy.cli("show", "-S", "alice", "double", "--json").stdout)
    assert numbers["max_value"] > 0
    # The result does not depend on the worker count: a serial rerun reuses nothing new.
    assert toy.cli("run", "-S", "alice", "--until", "double", "--workers", "1").ran == set()
    bad = toy.cli("run", "-S", "alice", "--executor", "nope", expect=2)
    assert "executor 'nope': unknown; available: local, ray" in bad.stderr


def test_declaration_cache_spares_imports(toy: ToyProject, tmp_path: Path) -> None:
    imports = tmp_path / "imports.txt"
    toy.cli("run", "-S", "alice", TOY_IMPORT_LOG=str(imports))
    assert set(imports.read_text().split()) == {"toy_stages.double.stage", "toy_stages.side.stage"}
    imports.unlink()
    toy.cli("status", "-S", "alice", TOY_IMPORT_LOG=str(imports))
    assert toy.cli("run", "-S", "alice", TOY_IMPORT_LOG=str(imports)).ran == set()
    assert not imports.exists()
    # A new configuration of double: only double is imported (to validate and run it).
    assert toy.cli("run", "-S", "alice", "--set", "double.factor=9", TOY_IMPORT_LOG=str(imports)).ran == {
        "double", "total"}
    assert imports.read_text().split() == ["toy_stages.double.stage"]
    # A damaged cache file is ignored, not fatal.
    for cache in (toy.workspaces / ".pipeline-cache").glob("*.json"):
        cache.write_text("{not json")
    assert toy.cli("run", "-S", "alice", "--set", "double.factor=9").ran == set()
