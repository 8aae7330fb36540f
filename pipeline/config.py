"""Configuration: the stage list, presets, subjects, the rig and ``--set`` overrides.

Effective params of a stage = params class defaults <- ``configs/rig.yaml``, or the rig file
the subject names with ``rig: <path>`` (as the ``rig`` field, for stages that declare one) <- ``configs/presets/<preset>.yaml`` <- 
``configs/subjects/<subject>.yaml`` <- ``--set stage.key=value``; validated into the
stage's frozen params class. A bad value raises ``ConfigError`` naming the file, the key
path and what is allowed.
"""

from __future__ import annotations

import importlib
import json
import re
import traceback
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

import pydantic

from pipeline.errors import ConfigError
from pipeline.stage import Stage, StageParams
from pipeline.yamlio import load_yaml_text, read_yaml_mapping

SUBJECT_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")
STAGE_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")


@dataclass(frozen=True)
class ExecutorConfig:
    """Which executor fans per-item work out, and with how many workers (None: all cores)."""

    kind: str = "local"
    workers: int | None = None


@dataclass(frozen=True)
class PipelineConfig:
    """``configs/pipeline.yaml``: stage name -> module, extra CLI commands, executor."""

    root: Path
    stage_modules: dict[str, str]
    commands: dict[str, str]
    executor: ExecutorConfig

    @property
    def path(self) -> Path:
        """The file this configuration was read from."""
        return self.root / "configs" / "pipeline.yaml"


def load_pipeline_config(root: Path) -> PipelineConfig:
    """Read and check ``configs/pipeline.yaml`` under the project ``root``."""
    display = "configs/pipeline.yaml"
    data = read_yaml_mapping(root / "configs" / "pipeline.yaml", display)
    unknown = set(data) - {"stages", "commands", "executor"}
    if unknown:
        raise ConfigError(f"{display}: unknown top-level keys {sorted(unknown)}; "
                          f"allowed: stages, commands, executor")
    stages = data.get("stages") or {}
    if not isinstance(stages, dict) or not stages:
        raise ConfigError(f"{display}: 'stages' must be a non-empty mapping of name -> module")
    for name, module in stages.items():
        if not isinstance(name, str) or not STAGE_NAME.match(name):
            raise ConfigError(f"{display}: stages.{name}: a stage name must be an identifier "
                              f"(letters, digits, underscore)")
        if not isinstance(module, str) or not module:
            raise ConfigError(f"{display}: stages.{name}: expected a module name such as "
                              f"'stages.{name}.stage', got {module!r}")
    commands = data.get("commands") or {}
    if not isinstance(commands, dict):
        raise ConfigError(f"{display}: 'commands' must be a mapping of name -> 'module:function'")
    for name, target in commands.items():
        if not isinstance(target, str) or target.count(":") != 1:
            raise ConfigError(f"{display}: commands.{name}: expected 'module:function', got {target!r}")
    raw_exec = data.get("executor") or {}
    if not isinstance(raw_exec, dict) or set(raw_exec) - {"kind", "workers"}:
        raise ConfigError(f"{display}: 'executor' allows only 'kind' and 'workers'")
    workers = raw_exec.get("workers")
    if workers is not None and (not isinstance(workers, int) or workers < 1):
        raise ConfigError(f"{display}: executor.workers must be a positive integer, got {workers!r}")
    executor = ExecutorConfig(kind=str(raw_exec.get("kind", "local")), workers=workers)
    return PipelineConfig(root=root, stage_modules=dict(stages), commands=dict(commands),
                          executor=executor)


@dataclass
class StageRegistry:
    """The stages of ``configs/pipeline.yaml`` that imported, and why the others did not.

    Attributes:
        stages: name -> Stage, in the order of the file.
        modules: name -> module name (every entry, loaded or not).
        broken: name -> one line saying why that entry could not be loaded.
    """

    stages: dict[str, Stage]
    modules: dict[str, str]
    broken: dict[str, str] = field(default_factory=dict)

    @property
    def names(self) -> list[str]:
        """Every stage named in ``configs/pipeline.yaml``."""
        return list(self.modules)

    def require(self, names: list[str] | set[str]) -> None:
        """Raise ``ConfigError`` if any of ``names`` could not be loaded."""
        bad = [n for n in self.modules if n in names and n in self.broken]
        if bad:
            lines = "; ".join(f"{n}: {self.broken[n]}" for n in bad)
            raise ConfigError(
                f"cannot load stage(s) needed here: {lines}. Fix the module(s), remove the "
                f"entries from configs/pipeline.yaml, or select fewer stages (--until/--only)")


def import_stage(name: str, module_name: str) -> Stage | str:
    """Import one stage module; its ``STAGE``, or one line saying why it cannot be used."""
    where = f"configs/pipeline.yaml stages.{name} ({module_name})"
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError as err:
        if err.name and module_name.startswith(err.name):
            return f"{where}: module not found"
        return f"{where}: import failed: {type(err).__name__}: {err}"
    except Exception as err:  # a broken stage module must not hide the others
        last = traceback.extract_tb(err.__traceback__)[-1]
        return f"{where}: import failed: {type(err).__name__}: {err} ({last.filename}:{last.lineno})"
    stage = getattr(module, "STAGE", None)
    if not isinstance(stage, Stage):
        return f"{where}: the module has no module-level STAGE = Stage(...)"
    if stage.name != name:
        return f"{where}: the module declares stage '{stage.name}', not '{name}'"
    if not (isinstance(stage.params, type) and issubclass(stage.params, StageParams)):
        return f"{where}: STAGE.params must be a StageParams subclass"
    return stage


def load_stages(config: PipelineConfig) -> StageRegistry:
    """Import every stage module; entries that fail are recorded in ``broken``, not raised.

    A module that imports but has no ``STAGE`` or declares another name is also broken;
    the runner refuses to run a broken stage (``StageRegistry.require``).
    """
    stages: dict[str, Stage] = {}
    broken: dict[str, str] = {}
    for name, module_name in config.stage_modules.items():
        loaded = import_stage(name, module_name)
        if isinstance(loaded, str):
            broken[name] = loaded
        else:
            stages[name] = loaded
    return StageRegistry(stages=stages, modules=dict(config.stage_modules), broken=broken)


# ----------------------------------------------------------------------------- layering


@dataclass(frozen=True)
class Layer:
    """One source of params: a label (file name or ``--set ...``) and its stage sections."""

    label: str
    sections: dict[str, dict[str, Any]]


@dataclass(frozen=True)
class SubjectConfig:
    """The layered configuration of one subject (preset, subject file, ``--set``) and the rig."""

    subject: str
    preset: str
    layers: tuple[Layer, ...]
    rig: dict[str, Any] | None
    rig_label: str = "configs/rig.yaml"  # the file ``rig`` came from, as error messages name it


def check_subject_name(subject: str) -> str:
    """Refuse subject names that could escape the workspace root or confuse the shell."""
    if not SUBJECT_NAME.match(subject or ""):
        raise ConfigError(f"subject name {subject!r}: use letters, digits, '_', '-', '.' "
                          f"(not starting with '.' or '-')")
    return subject


def parse_set(expr: str, known_stages: list[str]) -> tuple[str, list[str], Any]:
    """Parse ``stage.key.sub=value`` (value YAML-parsed) into (stage, key path, value)."""
    if "=" not in expr:
        raise ConfigError(f"--set {expr}: expected stage.key=value")
    lhs, rhs = expr.split("=", 1)
    parts = lhs.strip().split(".")
    if len(parts) < 2 or not all(parts):
        raise ConfigError(f"--set {expr}: expected stage.key=value (e.g. track.iterations=50)")
    stage = parts[0]
    if stage not in known_stages:
        raise ConfigError(f"--set {expr}: unknown stage '{stage}'; stages: {', '.join(known_stages)}")
    try:
        value = load_yaml_text(rhs, f"--set {expr}") if rhs.strip() else ""
    except ConfigError:
        value = rhs
    return stage, parts[1:], value


def _check_sections(data: dict, label: str, known_stages: list[str], skip: set[str]) -> dict:
    sections: dict[str, dict] = {}
    for key, value in data.items():
        if key in skip:
            continue
        if key not in known_stages:
            raise ConfigError(f"{label}: section '{key}' is not a stage in configs/pipeline.yaml; "
                              f"stages: {', '.join(known_stages)}")
        if value is None:
            value = {}
        if not isinstance(value, dict):
            raise ConfigError(f"{label}: section '{key}' must be a mapping of params, got "
                              f"{type(value).__name__}")
        sections[key] = value
    return sections


def load_subject_config(root: Path, subject: str, known_stages: list[str], *,
                        preset: str | None = None, sets: list[str] = ()) -> SubjectConfig:
    """Read ``configs/subjects/<subject>.yaml``, its preset (or ``preset``), the rig and ``--set``."""
    check_subject_name(subject)
    subject_label = f"configs/subjects/{subject}.yaml"
    subject_path = root / subject_label
    if not subject_path.is_file():
        have = sorted(p.stem for p in (root / "configs" / "subjects").glob("*.yaml"))
        raise ConfigError(f"{subject_label}: no such subject file; subjects: {', '.join(have) or 'none'}. "
                          f"Create it (a 'preset:' line plus per-stage sections)")
    subject_data = read_yaml_mapping(subject_path, subject_label)
    preset_name = preset or subject_data.get("preset")
    if not preset_name or not isinstance(preset_name, str):
        raise ConfigError(f"{subject_label}: 'preset' is missing; add e.g. 'preset: tiny' or pass --preset")
    preset_label = f"configs/presets/{preset_name}.yaml"
    preset_path = root / preset_label
    if not preset_path.is_file() or not SUBJECT_NAME.match(preset_name):
        have = sorted(p.stem for p in (root / "configs" / "presets").glob("*.yaml"))
        raise ConfigError(f"{preset_label}: no such preset; presets: {', '.join(have) or 'none'}")
    layers = [
        Layer(preset_label, _check_sections(read_yaml_mapping(preset_path, preset_label),
                                            preset_label, known_stages, set())),
        Layer(subject_label, _check_sections(subject_data, subject_label, known_stages, {"preset", "rig"})),
    ]
    for expr in sets:
        stage, path, value = parse_set(expr, known_stages)
        nested: Any = value
        for key in reversed(path):
            nested = {key: nested}
        layers.append(Layer(f"--set {expr}", {stage: nested}))
    rig_label, rig_path = _rig_file(root, subject_data.get("rig"), subject_label)
    rig = read_yaml_mapping(rig_path, rig_label) if rig_path.is_file() else None
    return SubjectConfig(subject=subject, preset=preset_name, layers=tuple(layers), rig=rig, rig_label=rig_label)


def _rig_file(root: Path, named: Any, subject_label: str) -> tuple[str, Path]:
    """The rig file of a subject: the one its ``rig:`` names (project-relative or absolute), else configs/rig.yaml.

    A subject's own rig replaces configs/rig.yaml as a whole (a studio's rig shares nothing with
    the default one), so a subject with another rig needs no edit to a shared file.
    """
    if named is None:
        return "configs/rig.yaml", root / "configs" / "rig.yaml"
    if not isinstance(named, str) or not named.strip():
        raise ConfigError(f"{subject_label}: 'rig' must be the path of a rig file, e.g. 'rig: configs/rigs/studio_b.yaml'")
    path = Path(named).expanduser()
    path = path if path.is_absolute() else root / path
    if not path.is_file():
        raise ConfigError(f"{subject_label}: rig {named}: no such file ({path}); give a rig YAML in the form of "
                          "configs/rig.yaml, relative to the project folder or absolute")
    return named, path


def _deep_merge(base: dict, update: Mapping, origin: dict, label: str, prefix: tuple) -> dict:
    merged = dict(base)
    for key, value in update.items():
        path = (*prefix, key)
        if isinstance(value, Mapping) and isinstance(merged.get(key), Mapping):
            merged[key] = _deep_merge(dict(merged[key]), value, origin, label, path)
        else:
            merged[key] = value
            _record_origin(value, origin, label, path)
    return merged


def _record_origin(value: Any, origin: dict, label: str, path: tuple) -> None:
    origin[path] = label
    if isinstance(value, Mapping):
        for key, sub in value.items():
            _record_origin(sub, origin, label, (*path, key))


def _allowed_text(stage_params: type[StageParams], err: Mapping[str, Any]) -> str:
    ctx = err.get("ctx") or {}
    kind = err.get("type", "")
    if "expected" in ctx:
        return f"allowed: {ctx['expected']}"
    if kind == "extra_forbidden":
        model: Any = stage_params
        for part in err["loc"][:-1]:
            fields = getattr(model, "model_fields", {})
            if isinstance(part, str) and part in fields:
                model = fields[part].annotation
            else:
                model = None
                break
        fields = getattr(model, "model_fields", None)
        if fields:
            return "allowed keys: " + ", ".join(sorted(fields))
        return "remove this key"
    for bound in ("gt", "ge", "lt", "le"):
        if bound in ctx:
            return f"allowed: {bound} {ctx[bound]}"
    return ""


def merge_layers(name: str, has_rig: bool, subject_config: SubjectConfig) -> tuple[dict, dict]:
    """The raw merged params of stage ``name`` and, per key path, the file that set it."""
    origin: dict[tuple, str] = {}
    merged: dict[str, Any] = {}
    if subject_config.rig is not None and has_rig:
        merged = _deep_merge(merged, {"rig": subject_config.rig}, origin, subject_config.rig_label, ())
    for layer in subject_config.layers:
        section = layer.sections.get(name)
        if section:
            merged = _deep_merge(merged, section, origin, layer.label, ())
    return merged, origin


def raw_params_key(merged: dict) -> str:
    """A digest of a raw merged configuration (for the declaration cache)."""
    from pipeline.hashing import hash_bytes

    return hash_bytes(json.dumps(merged, sort_keys=True, default=repr).encode())


def validate_params(stage: Stage, subject_config: SubjectConfig,
                    merged: tuple[dict, dict] | None = None) -> StageParams:
    """The stage's effective, validated params (see the module docstring for the order)."""
    if merged is None:
        merged = merge_layers(stage.name, "rig" in stage.params.model_fields, subject_config)
    values, origin = merged
    try:
        return stage.params.model_validate(values)
    except pydantic.ValidationError as exc:
        lines = []
        for err in exc.errors(include_url=False):
            loc = tuple(err["loc"])
            label = None
            for cut in range(len(loc), 0, -1):
                if loc[:cut] in origin:
                    label = origin[loc[:cut]]
                    break
            key = ".".join(str(part) for part in (stage.name, *loc))
            if label is None:
                label = (f"configs/presets/{subject_config.preset}.yaml or "
                         f"configs/subjects/{subject_config.subject}.yaml")
            shown = f" = {err['input']!r}" if err["type"] not in ("missing",) else ""
            allowed = _allowed_text(stage.params, err)
            lines.append(f"{label}: {key}{shown}: {err['msg']}" + (f" ({allowed})" if allowed else ""))
        raise ConfigError("; ".join(lines)) from None


def canonical_params(params: StageParams) -> dict[str, Any]:
    """The JSON form of params that counts for staleness (only declared fields exist)."""
    return json.loads(json.dumps(params.model_dump(mode="json"), sort_keys=True))
