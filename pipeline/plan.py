"""Action keys and change explanations, shared by the runner, ``status`` and ``--dry-run``.

A stage's action key is BLAKE3 over the canonical JSON of: its name, its code digest, its
canonical params, the content keys of its input objects and the digests of its external inputs.
An input's content key is the digest of its data without the runner's ``metrics.json`` and
the producing stage's run records (``Workspace.content_key``, ``Stage.run_records``), so an
upstream rerun that reproduces the same files with other timings leaves the stages below it
fresh; a stage that reads its inputs' metrics (``Stage.reads_metrics``) is keyed on their full
digests. Actions recorded by earlier versions (keyed on full digests, or on content keys that
still held the run records) are still found (``KeyMaterial.earlier_keys``).
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pipeline.codedigest import changed_files
from pipeline.dag import split_input
from pipeline.errors import ConfigError, InputError
from pipeline.hashing import hash_bytes, hash_path
from pipeline.declcache import StageDecl
from pipeline.project import Project, ResolvedParams
from pipeline.workspace import Ref, Workspace

OUT = "out"


def output_name(input_name: str) -> tuple[str, str]:
    """Input ``capture.truth`` -> (``capture``, ``truth``); ``capture`` -> (``capture``, ``out``)."""
    base, extra = split_input(input_name)
    return base, extra or OUT


def external_paths(params: ResolvedParams) -> list[Path]:
    """The stage's declared external inputs as absolute paths (relative ones: from the cwd)."""
    return [Path(os.path.abspath(Path(raw).expanduser())) for raw in params.external]


def external_digests(name: str, params: ResolvedParams, ws: Workspace) -> dict[str, str]:
    """path -> content digest of each external input (the stat cache spares unchanged files)."""
    digests = {}
    paths = external_paths(params)
    if not paths:
        return digests
    cache = ws.stat_cache()
    try:
        for path in paths:
            if not path.exists():
                raise InputError(f"stage '{name}': external input {path} does not exist; fix the "
                                 f"path in the config (e.g. --set {name}.<key>=...)")
            digests[str(path)] = hash_path(path, stat_cache=cache)
    finally:
        cache.flush()
    return digests


@dataclass(frozen=True)
class KeyMaterial:
    """Everything an action key is computed from.

    ``inputs`` are the input objects' digests (where the stage reads them; provenance),
    ``input_keys`` what the key hashes for them: their content keys, or the same digests for a
    stage that reads its inputs' metrics. ``earlier_input_keys``: what earlier versions hashed
    for the same inputs where it differs (content keys that kept the run records).
    """

    stage: str
    code: str
    params: dict[str, Any]
    inputs: dict[str, str]
    external: dict[str, str]
    input_keys: dict[str, str] | None = None
    earlier_input_keys: tuple[dict[str, str], ...] = ()
    code_files: dict[str, str] | None = None

    def to_json(self) -> dict[str, Any]:
        """The JSON form recorded in the action file (``code_files``: the digest of each file
        behind ``code``, so a later change can be named; not part of the key)."""
        record = {"stage": self.stage, "code": self.code, "params": self.params,
                  "inputs": self.inputs, "input_keys": self.keyed_inputs, "external": self.external}
        if self.code_files is not None:
            record["code_files"] = self.code_files
        return record

    @property
    def keyed_inputs(self) -> dict[str, str]:
        """What the key hashes for the inputs."""
        return self.inputs if self.input_keys is None else self.input_keys

    def _hash(self, inputs: dict[str, str]) -> str:
        body = {"stage": self.stage, "code": self.code, "params": self.params, "inputs": inputs,
                "external": self.external}
        return hash_bytes(json.dumps(body, sort_keys=True, separators=(",", ":")).encode())

    @property
    def key(self) -> str:
        """The action key: BLAKE3 of the canonical JSON of the stage, code, params, keyed inputs, externals."""
        return self._hash(self.keyed_inputs)

    @property
    def legacy_key(self) -> str:
        """The key of the same action before inputs were keyed by content (their full digests)."""
        return self._hash(self.inputs)

    @property
    def earlier_keys(self) -> tuple[str, ...]:
        """Keys earlier versions recorded the same action under (other than ``key``), newest first."""
        keys = [self._hash(inputs) for inputs in self.earlier_input_keys] + [self.legacy_key]
        return tuple(k for k in dict.fromkeys(keys) if k != self.key)


def key_material(project: Project, ws: Workspace, name: str, params: ResolvedParams,
                 input_digests: dict[str, str]) -> KeyMaterial:
    """Compute the key material of stage ``name`` for given input digests."""
    keys, earlier = None, ()
    if not project.stages[name].reads_metrics:
        keys = {inp: ws.content_key(digest, project.stages[output_name(inp)[0]].run_records)
                for inp, digest in input_digests.items()}
        with_records = {inp: ws.content_key(digest) for inp, digest in input_digests.items()}
        earlier = (with_records,) if with_records != keys else ()
    code = project.code_version(name)
    return KeyMaterial(stage=name, code=code.digest, params=params.canonical,
                       inputs=dict(input_digests), external=external_digests(name, params, ws), input_keys=keys,
                       earlier_input_keys=earlier, code_files=dict(code.files))


def find_action(ws: Workspace, material: KeyMaterial) -> tuple[str, dict] | None:
    """The recorded action for ``material`` and the key it is stored under, or None.

    Looks under ``material.key``, then under the keys earlier versions used for it
    (``KeyMaterial.earlier_keys``: on identical input objects, it is the same work).
    """
    for key in (material.key, *material.earlier_keys):
        action = ws.read_action(key)
        if action is not None:
            return key, action
    return None


def input_digests_from_refs(stage: StageDecl, refs: dict[str, Ref]) -> tuple[dict[str, str], list[str]]:
    """Digests of the stage's inputs from the given refs, and the inputs that have none."""
    digests, missing = {}, []
    for inp in stage.inputs:
        base, out = output_name(inp)
        ref = refs.get(base)
        if ref is None or out not in ref.outputs:
            missing.append(inp)
        else:
            digests[inp] = ref.outputs[out]
    return digests, missing


def _flatten(value: Any, prefix: str = "") -> dict[str, Any]:
    if isinstance(value, dict):
        flat: dict[str, Any] = {}
        for key, sub in value.items():
            flat.update(_flatten(sub, f"{prefix}.{key}" if prefix else str(key)))
        return flat
    return {prefix: value}


def changed_params(old: dict[str, Any], new: dict[str, Any]) -> list[str]:
    """Dotted keys whose values differ, with ``old -> new``."""
    old_flat, new_flat = _flatten(old), _flatten(new)
    lines = []
    for key in sorted(set(old_flat) | set(new_flat)):
        if old_flat.get(key, "<unset>") != new_flat.get(key, "<unset>"):
            lines.append(f"{key}: {json.dumps(old_flat.get(key, '<unset>'))} -> "
                         f"{json.dumps(new_flat.get(key, '<unset>'))}")
    return lines


# How many changed files a status line names before it says "and N more".
_NAMED_FILES = 6


def describe_code_change(old_files: dict[str, str] | None, new_files: dict[str, str]) -> str:
    """``code changed: scene/colour.py, ...``: the files whose digest differs from the last run's."""
    if old_files is None:
        # Records from before the import-closure digest cannot tell which files the run used:
        # the stage reruns once rather than trusting files its old digest did not cover.
        return "code changed: last run recorded before digests covered the whole import closure (reruns once)"
    changed = changed_files(old_files, new_files)
    if not changed:
        return "code changed"
    named = ", ".join(changed[:_NAMED_FILES])
    more = f" and {len(changed) - _NAMED_FILES} more" if len(changed) > _NAMED_FILES else ""
    return f"code changed: {named}{more}"


def describe_changes(old: dict[str, Any] | None, new: KeyMaterial) -> list[str]:
    """Why ``new`` differs from the recorded action ``old`` (code, params keys, inputs, external)."""
    if old is None:
        return ["the action record of the last run is missing"]
    reasons = []
    if old.get("code") != new.code:
        reasons.append(describe_code_change(old.get("code_files"), new.code_files or {}))
    params = changed_params(old.get("params", {}), new.params)
    if params:
        reasons.append("params changed: " + "; ".join(params))
    # Compare what the keys hashed; a record from before content keys has full digests only.
    old_inputs, new_inputs = ((old["input_keys"], new.keyed_inputs) if "input_keys" in old
                              else (old.get("inputs", {}), new.inputs))
    changed_inputs = sorted(k for k in set(old_inputs) | set(new_inputs) if old_inputs.get(k) != new_inputs.get(k))
    if changed_inputs:
        reasons.append("input changed: " + ", ".join(changed_inputs))
    old_ext = old.get("external", {})
    changed_ext = sorted(k for k in set(old_ext) | set(new.external) if old_ext.get(k) != new.external.get(k))
    if changed_ext:
        reasons.append("external input changed: " + ", ".join(changed_ext))
    if not reasons:
        reasons.append("action key changed")
    return reasons


def outputs_problem(ws: Workspace, outputs: dict[str, str], *, verify: bool = False) -> str | None:
    """Why a set of output objects cannot be used (missing, corrupt), or None if fine.

    With ``verify`` every object is re-hashed; damaged ones are marked corrupt so the next run
    treats them as missing and rebuilds them.
    """
    for out, digest in sorted(outputs.items()):
        label = "output" if out == OUT else f"extra output '{out}'"
        if ws.is_corrupt(digest):
            return f"{label} object {digest[:12]} is corrupt (found by --verify); it will be rebuilt"
        if not ws.has_object(digest):
            return f"{label} object {digest[:12]} is missing"
        if verify:
            problems = ws.verify_object(digest)
            if problems:
                ws.mark_corrupt(digest, problems)
                shown = "; ".join(problems[:5]) + (f"; ... {len(problems) - 5} more" if len(problems) > 5 else "")
                return f"{label} object {digest[:12]} is corrupt ({shown}); it will be rebuilt"
    return None


def check_known(project: Project, names: list[str]) -> None:
    """Raise if any name is not a stage."""
    for name in names:
        if name not in project.dag.upstream:
            raise ConfigError(f"unknown stage '{name}'; stages: {', '.join(project.dag.order)}")
