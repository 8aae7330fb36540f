"""Runs the selected stages in order, reusing every result whose action key is unchanged.

For each stage: compute the action key from its code, params, input objects and external
inputs; if an action with that key exists and its objects are intact (and the stage is not
forced), point the ref at it; otherwise run the stage into a fresh temp folder, commit the
outputs as objects, record the action, then move the ref. A failure leaves objects and refs
untouched and names the command that resumes the run. Early cutoff comes for free: a rerun
that produces identical bytes gives the same digest, so downstream keys do not change.
"""

from __future__ import annotations

import json
import logging
import os
import platform
import resource
import shlex
import socket
import sys
import time
from dataclasses import dataclass, field
from importlib import metadata
from typing import Any

from pipeline.errors import InputError, PipelineError, StageFailed
from pipeline.executors import check_executor_kind, make_executor
from pipeline.metrics import clean_metrics
from pipeline.plan import OUT, find_action, input_digests_from_refs, key_material, outputs_problem
from pipeline.progress import progress_factory
from pipeline.project import Project
from pipeline.stage import StageContext
from pipeline.status import assess
from pipeline.workspace import Ref, Workspace, remove_tree

log = logging.getLogger("pipeline.runner")


@dataclass
class RunOptions:
    """What ``pipeline run`` was asked to do.

    ``force``: None when ``--force`` was not given; an empty list for a bare ``--force``
    (force every selected stage); else the stages to force.
    """

    until: str | None = None
    from_: str | None = None
    only: list[str] | None = None
    force: list[str] | None = None
    dry_run: bool = False
    workers: int | None = None
    executor: str | None = None
    preset: str | None = None
    sets: list[str] = field(default_factory=list)
    workspace_root: str | None = None


@dataclass
class StageOutcome:
    """What happened to one stage: ``ran``, ``reused`` (cached action), ``fresh`` or a dry-run plan."""

    stage: str
    outcome: str
    detail: str = ""
    seconds: float = 0.0


def _versions() -> dict[str, str]:
    found = {"python": platform.python_version()}
    for package in ("torch", "numpy", "pydantic", "blake3"):
        try:
            found[package] = metadata.version(package)
        except metadata.PackageNotFoundError:
            pass
    return found


class Runner:
    """Runs a selection of stages for one subject."""

    def __init__(self, project: Project, ws: Workspace, options: RunOptions) -> None:
        self.project = project
        self.ws = ws
        self.options = options
        self.subject_config = project.subject_config(ws.subject, preset=options.preset, sets=options.sets)
        self.selected = project.dag.select(until=options.until, from_=options.from_, only=options.only)
        project.registry.require(set(self.selected))
        if options.force is None:
            self.forced: set[str] = set()
        elif not options.force:
            self.forced = set(self.selected)
        else:
            for name in options.force:
                if name not in project.dag.upstream:
                    raise_config(f"--force {name}: unknown stage; stages: {', '.join(project.dag.order)}")
                if name not in self.selected:
                    raise_config(f"--force {name}: '{name}' is not among the selected stages "
                                 f"({', '.join(self.selected)})")
            self.forced = set(options.force)
        check_executor_kind(options.executor or project.config.executor.kind)
        self.params = project.params(self.subject_config, self.selected)
        self.outcomes: list[StageOutcome] = []

    # -- the resume command ---------------------------------------------------------------

    def resume_command(self, failed: str) -> str:
        """The command that reruns from the failed stage with the same configuration."""
        args = ["pipeline", "run", "-S", self.ws.subject]
        if self.options.only:
            rest = self.selected[self.selected.index(failed):]
            args += ["--only", *rest]
        else:
            args += ["--from", failed]
            if self.options.until:
                args += ["--until", self.options.until]
        if self.options.preset:
            args += ["--preset", self.options.preset]
        for expr in self.options.sets:
            args += ["--set", expr]
        if self.options.workers:
            args += ["--workers", str(self.options.workers)]
        if self.options.executor:
            args += ["--executor", self.options.executor]
        if self.options.workspace_root:
            args += ["--workspace-root", self.options.workspace_root]
        return shlex.join(args)

    # -- dry run --------------------------------------------------------------------------

    def plan(self) -> list[StageOutcome]:
        """What a run would do and why, without running or locking anything."""
        pending: dict[str, str] = {}
        outcomes = []
        for status in assess(self.project, self.ws, self.params, self.selected, forced=self.forced):
            name = status.stage
            upstream_pending = [u for u in self.project.dag.upstream[name] if u in pending]
            if name in self.forced:
                outcomes.append(StageOutcome(name, "run", "forced"))
            elif status.state == "fresh":
                outcomes.append(StageOutcome(name, "skip", "fresh"))
                continue
            elif status.cached and not upstream_pending:
                outcomes.append(StageOutcome(name, "reuse", "a cached result matches: " + "; ".join(status.reasons)))
                continue
            else:
                why = "; ".join(r.replace("is stale", "will be rebuilt").replace("is never run", "will be built")
                                for r in status.reasons)
                if upstream_pending and status.state != "never-run":
                    why += " (skipped if the rebuilt inputs come out identical)"
                outcomes.append(StageOutcome(name, "run", why))
            pending[name] = "rebuilt"
        return outcomes

    # -- the run --------------------------------------------------------------------------

    def run(self) -> list[StageOutcome]:
        """Run the selection under the workspace lock; returns what happened per stage."""
        if self.options.dry_run:
            return self.plan()
        self.ws.ensure()
        with self.ws.lock():
            leftovers = self.ws.clean_tmp()
            if leftovers:
                log.info("removed %d unfinished output(s) of an interrupted run", len(leftovers))
            refs = self.ws.refs()
            for name in self.selected:
                self.outcomes.append(self._run_one(name, refs))
        return self.outcomes

    def _inputs_for(self, name: str, refs: dict[str, Ref]) -> dict[str, str]:
        stage = self.project.stages[name]
        digests, missing = input_digests_from_refs(stage, refs)
        for inp in missing:
            base = inp.split(".", 1)[0]
            raise PipelineError(f"stage '{name}' needs '{inp}', which has no output for subject "
                                f"'{self.ws.subject}' yet; run `pipeline run -S {self.ws.subject} "
                                f"--until {base}` first")
        for inp, digest in digests.items():
            problem = outputs_problem(self.ws, {OUT: digest})
            if problem:
                base = inp.split(".", 1)[0]
                raise PipelineError(f"stage '{name}' needs '{inp}', whose {problem.split(' object')[0]} "
                                    f"object {digest[:12]} is missing or corrupt; rebuild it with "
                                    f"`pipeline run -S {self.ws.subject} --only {base}`")
        return digests

    def _run_one(self, name: str, refs: dict[str, Ref]) -> StageOutcome:
        params = self.params[name]
        try:
            digests = self._inputs_for(name, refs)
            material = key_material(self.project, self.ws, name, params, digests)
        except InputError as err:
            raise StageFailed(f"stage '{name}' cannot start: {err}. Fix it, then resume with: "
                              f"{self.resume_command(name)}") from err
        key = material.key
        found = None if name in self.forced else find_action(self.ws, material)
        if found is not None:
            found_key, action = found
            problem = outputs_problem(self.ws, action.get("outputs", {}))
            if problem is None:
                if found_key != key:
                    # Recorded under an earlier version's key: file it under the current key too.
                    self.ws.write_action(key, {**action, "key": key, "input_keys": material.keyed_inputs})
                ref = refs.get(name)
                if ref is not None and ref.action in (key, found_key) and ref.outputs == action["outputs"]:
                    if ref.action != key:
                        refs[name] = self._write_ref(name, key, action["outputs"])
                    log.debug("%s: fresh", name)
                    return StageOutcome(name, "fresh")
                refs[name] = self._write_ref(name, key, action["outputs"])
                log.info("%s: reused the cached result of an earlier run (%s)", name,
                         action.get("timings", {}).get("started", "?"))
                return StageOutcome(name, "reused")
            log.warning("%s: %s; rebuilding", name, problem)
        return self._execute(name, material, refs)

    def _write_ref(self, name: str, key: str, outputs: dict[str, str]) -> Ref:
        ref = Ref(name, key, dict(outputs), time.strftime("%Y-%m-%dT%H:%M:%S%z"))
        self.ws.write_ref(ref)
        return ref

    def _execute(self, name: str, material, refs: dict[str, Ref]) -> StageOutcome:
        key = material.key
        stage = self.project.stage(name)
        params = self.project.resolve_params(name, self.subject_config, need_value=True).value
        temp = self.ws.new_temp_dir(name)
        out = temp / OUT
        out.mkdir()
        extras = {extra: temp / extra for extra in stage.extra_outputs}
        for folder in extras.values():
            folder.mkdir()
        log_path = self.ws.new_log_path(name, key)
        handler = logging.FileHandler(log_path, encoding="utf-8")
        handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
        root_logger = logging.getLogger()
        root_logger.addHandler(handler)
        old_level = root_logger.level
        if root_logger.level > logging.INFO or root_logger.level == logging.NOTSET:
            root_logger.setLevel(logging.INFO)
        stage_log = logging.getLogger(f"stage.{name}")
        cache_dir = self.ws.cache_dir / name
        cache_dir.mkdir(parents=True, exist_ok=True)
        metrics: dict[str, Any] = {}
        factory = progress_factory(name, stage_log)
        workers = self.options.workers or self.project.config.executor.workers
        started = time.strftime("%Y-%m-%dT%H:%M:%S%z")
        wall0 = time.perf_counter()
        usage0 = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
        inputs = {}
        for inp, digest in material.inputs.items():
            inputs[inp] = self.ws.object_path(digest)
        stage_log.info("running %s for subject %s (action %s)", name, self.ws.subject, key[:12])
        try:
            try:
                kind = self.options.executor or self.project.config.executor.kind
                with make_executor(kind, workers, factory) as executor:
                    ctx = StageContext(stage=name, subject=self.ws.subject, params=params, inputs=inputs,
                                       out=out, extra_outputs=extras, log=stage_log, metrics=metrics,
                                       cache_dir=cache_dir, shared_cache_dir=self.ws.shared_cache_dir,
                                       executor=executor, progress_factory=factory)
                    stage.run(ctx)
                clean = clean_metrics(name, metrics)
                metrics_file = out / "metrics.json"
                if metrics_file.is_file():
                    written = json.loads(metrics_file.read_text(encoding="utf-8"))
                    clean = {**written, **clean}
                metrics_file.write_text(json.dumps(clean, indent=1, sort_keys=True) + "\n", encoding="utf-8")
                outputs = {OUT: self.ws.commit(out)}
                for extra, folder in extras.items():
                    outputs[extra] = self.ws.commit(folder)
            except Exception as err:
                # The traceback goes to the log file only; the console gets one line (--debug: all).
                trace_log = logging.getLogger(f"pipeline.trace.{name}")
                trace_log.propagate = False
                trace_log.addHandler(handler)
                try:
                    trace_log.error("stage %s failed", name, exc_info=True)
                finally:
                    trace_log.removeHandler(handler)
                raise StageFailed(
                    f"stage '{name}' failed: {type(err).__name__}: {err} (log: {log_path}). "
                    f"Fix it, then resume with: {self.resume_command(name)}") from err
            finally:
                remove_tree(temp)
            wall = time.perf_counter() - wall0
            usage1 = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
            cpu = sum(u1.ru_utime + u1.ru_stime - u0.ru_utime - u0.ru_stime for u0, u1 in zip(usage0, usage1))
            record = {
                **material.to_json(), "key": key, "outputs": outputs, "metrics": clean,
                "timings": {"started": started, "seconds": round(wall, 4), "cpu_seconds": round(cpu, 4)},
                "versions": _versions(), "host": socket.gethostname(), "pid": os.getpid(),
                "command": shlex.join(["pipeline", *sys.argv[1:]]), "log": str(log_path),
                "subject": self.ws.subject,
            }
            self.ws.write_action(key, record)
            refs[name] = self._write_ref(name, key, outputs)
            stage_log.info("%s done in %.2f s -> %s", name, wall, outputs[OUT][:12])
            return StageOutcome(name, "ran", seconds=wall)
        finally:
            root_logger.removeHandler(handler)
            root_logger.setLevel(old_level)
            handler.close()


def raise_config(message: str) -> None:
    """Raise ``ConfigError`` (bad command-line usage, exit code 2)."""
    from pipeline.errors import ConfigError

    raise ConfigError(message)
