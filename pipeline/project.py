"""Finding the project root: the folder that holds ``configs/pipeline.yaml``.

The environment variable ``PIPELINE_PROJECT_ROOT`` wins (tests point it at a toy project);
otherwise the current directory and its parents are searched.
"""

from __future__ import annotations

import os
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pipeline.errors import ConfigError

PIPELINE_FILE = Path("configs") / "pipeline.yaml"
ENV_PROJECT_ROOT = "PIPELINE_PROJECT_ROOT"


def find_project_root(start: Path | None = None) -> Path:
    """The project root: ``$PIPELINE_PROJECT_ROOT``, else the nearest ancestor of ``start``
    (default: the current directory) holding ``configs/pipeline.yaml``."""
    env = os.environ.get(ENV_PROJECT_ROOT)
    if env:
        root = Path(env).expanduser().resolve()
        if not (root / PIPELINE_FILE).is_file():
            raise ConfigError(f"{ENV_PROJECT_ROOT}={env}: no {PIPELINE_FILE} there; "
                              f"point it at the folder that holds configs/pipeline.yaml")
        return root
    here = (start or Path.cwd()).resolve()
    for folder in (here, *here.parents):
        if (folder / PIPELINE_FILE).is_file():
            return folder
    raise ConfigError(f"no {PIPELINE_FILE} in {here} or any parent folder; run from inside the "
                      f"project or set {ENV_PROJECT_ROOT}")


def ensure_importable(root: Path) -> None:
    """Put the project root first on ``sys.path`` so stage modules import from it."""
    text = str(root)
    if text in sys.path:
        sys.path.remove(text)
    sys.path.insert(0, text)


@dataclass(frozen=True)
class ResolvedParams:
    """A stage's effective params as the action key sees them.

    ``canonical``: the JSON form of the validated params (only declared keys); ``external``:
    the stage's external input paths as it declares them; ``value``: the validated params
    object when the stage module was imported in this process (None when both came from the
    declaration cache; ``Project.params_value`` imports and validates).
    """

    canonical: dict[str, Any]
    external: tuple[str, ...]
    value: Any = None


class Project:
    """A loaded project: root, ``configs/pipeline.yaml``, stage declarations, the DAG.

    With a ``cache_dir`` (the CLI passes ``<workspace root>/.pipeline-cache``), declarations and
    validated params come from the declaration cache when the files behind them are unchanged,
    so stage modules (and torch) are imported only for stages that actually run or changed.
    """

    def __init__(self, root: Path, *, cache_dir: Path | None = None) -> None:
        from pipeline.config import StageRegistry, import_stage, load_pipeline_config
        from pipeline.dag import Dag
        from pipeline.declcache import DeclCache, StageDecl, project_source_files

        self.root = root
        ensure_importable(root)
        self.config = load_pipeline_config(root)
        self.cache = DeclCache.for_project(cache_dir, root) if cache_dir is not None else None
        self._imported: dict[str, Any] = {}
        decls: dict[str, StageDecl] = {}
        broken: dict[str, str] = {}
        for name, module in self.config.stage_modules.items():
            decl = self.cache.decl(name, module) if self.cache is not None else None
            if decl is None:
                loaded = import_stage(name, module)
                if isinstance(loaded, str):
                    broken[name] = loaded
                    continue
                self._imported[name] = loaded
                decl = StageDecl.from_stage(loaded, module)
                if self.cache is not None:
                    self.cache.put_decl(decl, project_source_files(root))
            decls[name] = decl
        self.registry = StageRegistry(stages=decls, modules=dict(self.config.stage_modules), broken=broken)
        self.stages = decls
        self.dag = Dag.build(decls.values(), unloaded=broken)

    @classmethod
    def discover(cls, start: Path | None = None, *, cache_dir: Path | None = None) -> "Project":
        """Load the project found by ``find_project_root``."""
        return cls(find_project_root(start), cache_dir=cache_dir)

    def module_of(self, stage: str) -> str:
        """The module name of a stage, from ``configs/pipeline.yaml``."""
        return self.config.stage_modules[stage]

    def stage(self, name: str):
        """The real ``Stage`` object (imports its module if the declaration came from the cache)."""
        from pipeline.config import import_stage

        if name not in self._imported:
            loaded = import_stage(name, self.module_of(name))
            if isinstance(loaded, str):
                raise ConfigError(loaded)
            self._imported[name] = loaded
        return self._imported[name]

    def code_version(self, name: str):
        """The stage's ``pipeline.codedigest.CodeVersion``: its package and every project file it
        imports or declares, transitively, each with its digest."""
        from pipeline.codedigest import stage_code_version

        return stage_code_version(self.stages[name], self.module_of(name), self.root, self.cache)

    def code_digest(self, name: str) -> str:
        """The stage's code digest (``code_version(name).digest``)."""
        return self.code_version(name).digest

    def subject_config(self, subject: str, *, preset: str | None = None, sets: list[str] = ()):
        """The layered config of ``subject`` (``pipeline.config.SubjectConfig``)."""
        from pipeline.config import load_subject_config

        return load_subject_config(self.root, subject, self.registry.names, preset=preset, sets=list(sets))

    def resolve_params(self, name: str, subject_config, *, need_value: bool = False) -> ResolvedParams:
        """Effective params of stage ``name``, from the declaration cache when possible."""
        from pipeline.config import canonical_params, merge_layers, raw_params_key, validate_params

        decl = self.stages[name]
        merged = merge_layers(name, decl.has_rig, subject_config)
        raw_key = raw_params_key(merged[0])
        if not need_value and name not in self._imported and self.cache is not None:
            hit = self.cache.params(name, raw_key)
            if hit is not None:
                return ResolvedParams(hit["canonical"], tuple(hit["external"]))
        stage = self.stage(name)
        value = validate_params(stage, subject_config, merged)
        external: tuple[str, ...] = ()
        if stage.external_inputs is not None:
            external = tuple(str(p) for p in (stage.external_inputs(value) or ()))
        canonical = canonical_params(value)
        if self.cache is not None:
            self.cache.put_params(name, raw_key, canonical, list(external))
        return ResolvedParams(canonical, external, value)

    def params(self, subject_config, names: list[str] | None = None) -> dict[str, ResolvedParams]:
        """Resolved params of the loaded stages among ``names`` (default: all loaded);
        every bad value of every stage is reported in one ``ConfigError``."""
        result, problems = {}, []
        for name in names if names is not None else self.dag.order:
            if name not in self.stages:
                continue
            try:
                result[name] = self.resolve_params(name, subject_config)
            except ConfigError as err:
                problems.append(str(err))
        if problems:
            raise ConfigError("; ".join(problems))
        return result

    def save_cache(self) -> None:
        """Persist the declaration cache (if one is used and it changed)."""
        if self.cache is not None:
            self.cache.save()
