"""Which stages are fresh or stale, and why; also the plan behind ``run --dry-run``.

A stage is fresh when its current action key (code, params, input objects, external inputs)
equals the one its ref was produced by, its output objects are present (and intact under
``--verify``), and every upstream stage is fresh.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from pipeline.errors import InputError
from pipeline.plan import describe_changes, find_action, input_digests_from_refs, key_material, outputs_problem
from pipeline.project import Project
from pipeline.project import ResolvedParams
from pipeline.workspace import Workspace

FRESH, STALE, NEVER_RUN, UNLOADABLE = "fresh", "stale", "never-run", "unloadable"


@dataclass
class StageStatus:
    """A stage's state (fresh, stale, never-run, unloadable), the reasons, and keys."""

    stage: str
    state: str
    reasons: list[str] = field(default_factory=list)
    key: str | None = None
    ref_action: str | None = None
    cached: bool = False  # an action for the current key exists with its objects: a run reuses it

    def to_json(self) -> dict:
        """JSON form for ``status --json``."""
        return {"stage": self.stage, "state": self.state, "reasons": self.reasons, "key": self.key,
                "ref_action": self.ref_action, "cached": self.cached}


def assess(project: Project, ws: Workspace, params: dict[str, ResolvedParams], names: list[str], *,
           verify: bool = False, pending: dict[str, str] | None = None,
           forced: set[str] = frozenset()) -> list[StageStatus]:
    """Assess ``names`` (in topological order).

    ``pending`` maps stages that will be (re)built before these ones to why (dry-run: the
    selected stages that would run); it is extended as stale stages are found.
    """
    refs = ws.refs()
    pending = dict(pending or {})
    results = []
    for name in names:
        stage = project.stages.get(name)
        ref = refs.get(name)
        if stage is None:
            results.append(StageStatus(name, UNLOADABLE, [project.registry.broken.get(name, "not loaded")]))
            pending[name] = "unloadable"
            continue
        reasons: list[str] = []
        ups = [up for up in project.dag.upstream[name] if up in pending]
        for up in ups:
            reasons.append(f"upstream '{up}' is {pending[up]}")
        status = StageStatus(name, STALE, reasons, ref_action=ref.action if ref else None)
        digests, missing = input_digests_from_refs(stage, refs)
        if missing and not ups:
            reasons.append("no output yet for input " + ", ".join(missing))
        if not missing:
            try:
                material = key_material(project, ws, name, params[name], digests)
            except InputError as err:
                reasons.append(str(err))
                material = None
            if material is not None:
                status.key = material.key
                found = find_action(ws, material)
                status.cached = found is not None and outputs_problem(ws, found[1].get("outputs", {})) is None
                if ref is not None:
                    if ref.action in (material.key, *material.earlier_keys):
                        problem = outputs_problem(ws, ref.outputs, verify=verify)
                        if problem:
                            reasons.append(problem)
                            status.cached = False
                    else:
                        reasons.extend(describe_changes(ws.read_action(ref.action), material))
        elif ref is not None and verify:
            problem = outputs_problem(ws, ref.outputs, verify=True)
            if problem:
                reasons.append(problem)
        if name in forced:
            reasons.append("forced")
        if ref is None:
            status.state = NEVER_RUN
            reasons[:] = ["never run"] + [r for r in reasons if "unloadable" in r]
        elif not reasons:
            status.state = FRESH
        if status.state != FRESH:
            pending[name] = "never run" if status.state == NEVER_RUN else "stale"
        results.append(status)
    return results


def format_status(statuses: list[StageStatus]) -> str:
    """One line per stage: ``name  state  reasons``."""
    width = max((len(s.stage) for s in statuses), default=5)
    lines = []
    for s in statuses:
        why = "; ".join(s.reasons)
        if s.state == "stale" and s.cached and not any("forced" == r for r in s.reasons):
            why += " (a cached result matches; `pipeline run` will reuse it)"
        lines.append(f"{s.stage:<{width}}  {s.state:<10}  {why}".rstrip())
    return "\n".join(lines)
