"""Stage output contracts: only a stage's own package spells the names of the files it writes.

Every stage that produces files owns ``stages/<package>/output.py``, which declares the names
of its files and folders in ``CONTRACT_NAMES`` and reads and writes them
(``CaptureOutput(path).manifest()``). Any other production module (``avatar``, ``scene``,
``hardware``, ``pipeline``, ``benchmarks``, another stage's package) goes through that module;
this test fails when one of them spells such a name itself.

What counts as spelling a name, in a string literal (docstrings and prose, i.e. strings with
white space such as log messages and help texts, do not count):

- a file name (``manifest.json``): the literal is it, or holds it as a path component
  (``"scans/scans.npz"``, an f-string part ``"/manifest.json"``);
- a folder name (``frames``): the literal holds it as a path component of a path string
  (``"calib/mirror"``), or is joined as a path (``capture / "frames"``, ``Path("frames")``,
  ``.joinpath("frames")``). A bare ``"frames"`` elsewhere is a JSON key, a progress unit, ...

A name declared by several stages (``cameras.json``: calibrate, track, the capture's truth)
may be spelled in any of their packages.
"""

from __future__ import annotations

import ast
import importlib
import json
import re
from pathlib import Path

import pytest
import yaml

from pipeline.errors import InputError

ROOT = Path(__file__).resolve().parents[1]
PRODUCTION = ("avatar", "scene", "hardware", "pipeline", "stages", "benchmarks")

#: The stage packages whose outputs are typed (``stages/<package>/output.py``).
COVERED = ("sequence", "capture", "calibrate", "lightcal", "track", "stabilize", "matte", "train", "relight",
           "evaluate", "report")

#: Modules allowed to spell another package's contract name, and why.
EXCEPTIONS: dict[tuple[str, str], str] = {
    ("hardware/studio/calibration_takes.py", "capture"):
        "the virtual studio shoots the capture's calibration takes (calib/...) in the capture's layout, and "
        "writes calibration-only captures with their truth for tests and benches",
    ("hardware/studio/envmap_truth.py", "studio.json"):
        "subject_from_truth reads the capture truth's studio record; every hardware/studio source keys the matte "
        "model cache (stages.matte.stage.training_code_files), so editing it would retrain the matting model and "
        "change matte/model.json",
    ("benchmarks/bench_studio.py", "studio.json"): "its own results file, bench-results/studio.json",
    ("benchmarks/bench_sequence.py", "sequence.json"): "its own results file, bench-results/sequence.json",
    ("benchmarks/bench_capacity.py", "capacity.json"): "its own results file, bench-results/capacity.json",
    ("stages/report/capacity.py", "capacity.json"): "reads bench-results/capacity.json (the capacity bench)",
}


def _stage_packages() -> list[str]:
    """Stage packages named in ``configs/pipeline.yaml`` (``stages.capture.stage`` -> ``capture``)."""
    config = yaml.safe_load((ROOT / "configs" / "pipeline.yaml").read_text())
    packages = []
    for module in config["stages"].values():
        parts = module.split(".")
        if parts[0] == "stages" and parts[1] not in packages:
            packages.append(parts[1])
    return packages


def _contracts() -> dict[str, set[str]]:
    """Contract name -> the stage packages that declare it."""
    owners: dict[str, set[str]] = {}
    for package in _stage_packages():
        if not (ROOT / "stages" / package / "output.py").is_file():
            continue
        module = importlib.import_module(f"stages.{package}.output")
        names = getattr(module, "CONTRACT_NAMES", None)
        assert names, f"stages/{package}/output.py declares no CONTRACT_NAMES"
        for name in names:
            assert isinstance(name, str) and name and "/" not in name, f"stages/{package}: bad contract name {name!r}"
            owners.setdefault(name, set()).add(package)
    return owners


def _package_of(relpath: str) -> str:
    parts = relpath.split("/")
    return parts[1] if parts[0] == "stages" and len(parts) > 2 else parts[0]


def _docstrings(tree: ast.AST) -> set[int]:
    ids = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)) and node.body:
            first = node.body[0]
            if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant):
                ids.add(id(first.value))
    return ids


def _path_context(tree: ast.AST) -> set[int]:
    """Ids of string constants joined as a path: ``x / "a"``, ``Path("a")``, ``p.joinpath("a")``."""
    ids = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.BinOp) and isinstance(node.op, ast.Div):
            ids.update(id(side) for side in (node.left, node.right) if isinstance(side, ast.Constant))
        elif isinstance(node, ast.Call):
            func = node.func
            name = func.id if isinstance(func, ast.Name) else func.attr if isinstance(func, ast.Attribute) else ""
            if name in ("Path", "PurePath", "joinpath"):
                ids.update(id(arg) for arg in node.args if isinstance(arg, ast.Constant))
    return ids


def spelled_names(source: str, names: set[str]) -> list[tuple[int, str]]:
    """(line, name) of every contract name in ``names`` that ``source`` spells (rules: module docstring)."""
    tree = ast.parse(source)
    skip, joined = _docstrings(tree), _path_context(tree)
    found = []
    for node in ast.walk(tree):
        if not (isinstance(node, ast.Constant) and isinstance(node.value, str)) or id(node) in skip:
            continue
        text = node.value
        if not text or re.search(r"\s", text):
            continue  # prose: messages, help texts, descriptions
        components = set(re.split(r"[/\\]", text))
        for name in names & components:
            is_file = "." in name
            if is_file or id(node) in joined or ("/" in text or "\\" in text):
                found.append((node.lineno, name))
    return found


def _production_files() -> list[Path]:
    return sorted(p for top in PRODUCTION for p in (ROOT / top).rglob("*.py") if "__pycache__" not in p.parts)


def test_every_covered_stage_owns_an_output_module():
    packages = _stage_packages()
    for package in COVERED:
        assert package in packages, f"{package} is not a stage package of configs/pipeline.yaml"
        assert (ROOT / "stages" / package / "output.py").is_file(), f"stages/{package}/output.py is missing"


def test_no_module_spells_another_stages_output_file_names():
    owners = _contracts()
    assert set(COVERED) <= {p for ps in owners.values() for p in ps}
    problems = []
    for path in _production_files():
        relpath = path.relative_to(ROOT).as_posix()
        package = _package_of(relpath)
        foreign = {name for name, pkgs in owners.items() if package not in pkgs}
        for line, name in spelled_names(path.read_text(encoding="utf-8"), foreign):
            stages = sorted(owners[name])
            if (relpath, name) in EXCEPTIONS or any((relpath, s) in EXCEPTIONS for s in stages):
                continue
            problems.append(f"{relpath}:{line}: spells {name!r}, a file of stage {'/'.join(stages)}; "
                            f"use stages/{stages[0]}/output.py instead")
    assert not problems, "\n".join(problems)


def test_output_modules_import_only_their_stage_scene_and_pipeline():
    # So that any module can read any stage's output without an import cycle.
    for package in _stage_packages():
        path = ROOT / "stages" / package / "output.py"
        if not path.is_file():
            continue
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            names = ([a.name for a in node.names] if isinstance(node, ast.Import) else
                     [node.module or ""] if isinstance(node, ast.ImportFrom) else [])
            for name in names:
                top = name.split(".")[0]
                if top in PRODUCTION:
                    assert top in ("scene", "pipeline") or name.startswith(f"stages.{package}."), \
                        f"stages/{package}/output.py imports {name}"


def test_the_scan_sees_the_spellings_it_must():
    names = {"manifest.json", "frames", "scans.npz"}
    source = '''
"""Docstring naming manifest.json and frames/ is fine."""
def f(capture, k):
    """So is this: frames/<cam>/<k>.exr."""
    a = capture / "manifest.json"
    b = capture / "frames" / "cam00" / f"{k:06d}.exr"
    c = "scans/scans.npz"
    d = {"frames": 3}["frames"]
    e = progress(10, "frames")
    log.info("read manifest.json from %s", capture)
    return Path("frames"), capture.joinpath("frames"), f"{capture}/manifest.json"
'''
    assert sorted(spelled_names(source, names)) == [
        (5, "manifest.json"), (6, "frames"), (7, "scans.npz"), (11, "frames"), (11, "frames"),
        (11, "manifest.json")]


def test_the_contract_names_are_the_files_the_stages_write():
    from stages.capture.output import CONTRACT_NAMES as capture
    from stages.stabilize.output import CONTRACT_NAMES as stabilize

    assert {"manifest.json", "frames", "scans.npz", "controller_log.json", "calib"} <= set(capture)
    assert "cameras_head.json" in stabilize


# --- the errors of the output modules -------------------------------------------------------------

def test_a_missing_capture_manifest_names_the_stage_the_file_and_the_rerun(tmp_path):
    from stages.capture.output import CaptureOutput

    with pytest.raises(InputError) as err:
        CaptureOutput(tmp_path).manifest()
    message = str(err.value)
    assert message.startswith(f"capture output {tmp_path / 'manifest.json'} is missing or unreadable: ")
    assert message.endswith("; rerun the capture stage (pipeline run --only capture --force)")


def test_a_malformed_capture_manifest_gets_the_same_clear_error(tmp_path):
    from stages.capture.output import CaptureOutput

    (tmp_path / "manifest.json").write_text('{"cameras": ["cam00"], "frames": [')
    with pytest.raises(InputError, match=r"capture output .*manifest.json is missing or unreadable: .*"
                                         r"rerun the capture stage \(pipeline run --only capture --force\)"):
        CaptureOutput(tmp_path).manifest()
    (tmp_path / "manifest.json").write_text(json.dumps({"cameras": ["cam00"]}))
    with pytest.raises(InputError, match=r"capture output .*manifest.json is malformed: no 'frames' key; "
                                         r"rerun the capture stage"):
        CaptureOutput(tmp_path).manifest(keys=("cameras", "frames"))
    (tmp_path / "manifest.json").write_text("[1, 2]")
    with pytest.raises(InputError, match="manifest.json is malformed: expected a JSON object"):
        CaptureOutput(tmp_path).manifest()


def test_a_missing_or_broken_capture_frame_names_camera_frame_and_rerun(tmp_path):
    from stages.capture.output import CaptureOutput

    capture = CaptureOutput(tmp_path)
    with pytest.raises(InputError) as err:
        capture.frame("cam03", 12)
    assert str(err.value).startswith(f"capture output {tmp_path / 'frames' / 'cam03' / '000012.exr'} "
                                     "is missing or unreadable: ")
    assert "rerun the capture stage (pipeline run --only capture --force)" in str(err.value)
    capture.frames_dir("cam03").mkdir(parents=True)
    capture.frame_path("cam03", 12).write_bytes(b"not an EXR")
    with pytest.raises(InputError, match=r"capture output .*cam03/000012.exr is missing or unreadable"):
        capture.frame("cam03", 12)


def test_capture_truth_errors_name_the_truth(tmp_path):
    from stages.capture.output import CaptureTruth

    with pytest.raises(InputError, match=r"^capture truth .*studio.json is missing or unreadable: .*"
                                         r"rerun the capture stage"):
        CaptureTruth(tmp_path).studio()
    np_path = tmp_path / "frames.npz"
    np_path.write_bytes(b"PK broken")
    with pytest.raises(InputError, match=r"^capture truth .*frames.npz is missing or unreadable"):
        CaptureTruth(tmp_path).frames()


def test_a_missing_or_malformed_stabilize_file_names_the_stage_and_the_rerun(tmp_path):
    from stages.stabilize.output import StabilizeOutput

    out = StabilizeOutput(tmp_path)
    with pytest.raises(InputError) as err:
        out.cameras_head()
    assert str(err.value).startswith(f"stabilize output {tmp_path / 'cameras_head.json'} is missing or unreadable")
    assert str(err.value).endswith("; rerun the stabilize stage (pipeline run --only stabilize --force)")
    out.cameras_head_path.write_text('{"space": "head", "frames": {"0": [{"name": "cam00"')
    with pytest.raises(InputError, match=r"stabilize output .*cameras_head.json is missing or unreadable: .*"
                                         r"rerun the stabilize stage"):
        out.cameras_head()
    out.cameras_head_path.write_text(json.dumps({"space": "head"}))
    with pytest.raises(InputError, match=r"cameras_head.json is missing or unreadable: .*'frames'"):
        out.cameras_head()


def test_stabilize_output_round_trip(tmp_path):
    import numpy as np

    from scene.camera import Camera, Rigid
    from stages.stabilize.output import StabilizeOutput

    cam = Camera(name="cam00", width=8, height=6, fx=10.0, fy=10.0, cx=4.0, cy=3.0, dist=(0.0,) * 5,
                 pose=Rigid(np.eye(3), np.array([0.0, 0.0, 1.0])))
    out = StabilizeOutput(tmp_path)
    out.write_cameras_head([0, 4], np.stack([np.eye(3)] * 2), np.zeros((2, 3)), [cam])
    back = out.cameras_head_by_name()
    assert sorted(back) == [0, 4] and back[4]["cam00"].cam_from_head.t.tolist() == [0.0, 0.0, 1.0]


def test_other_stages_errors_say_which_stage_to_rerun(tmp_path):
    from stages.calibrate.output import CalibrateOutput
    from stages.lightcal.output import LightcalOutput
    from stages.matte.output import MatteOutput
    from stages.sequence.output import SequenceOutput
    from stages.track.output import TrackOutput
    from stages.train.output import TrainOutput

    for read, stage in ((CalibrateOutput(tmp_path).cameras, "calibrate"), (LightcalOutput(tmp_path).bars, "lightcal"),
                        (lambda: MatteOutput(tmp_path).matte("cam00", 3), "matte"),
                        (SequenceOutput(tmp_path).sequence, "sequence"), (TrackOutput(tmp_path).tracking, "track"),
                        (TrainOutput(tmp_path).splits, "train")):
        with pytest.raises(InputError, match=rf"^{stage} output .* is missing or unreadable: .*; rerun the {stage} "
                                             rf"stage \(pipeline run --only {stage} --force\)$"):
            read()
