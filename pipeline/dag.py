"""The stage graph: a pure model built from stage declarations and validated when built.

Unknown inputs, cycles (the cycle is named), duplicate names and ground truth fed to a
product stage raise ``ConfigError``. Inputs are stage names, or ``<stage>.<extra>`` for a
declared extra output; ``<stage>.truth`` may feed only stages with ``may_read_truth``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable

from pipeline.errors import ConfigError
from pipeline.stage import Stage

TRUTH = "truth"


def split_input(name: str) -> tuple[str, str | None]:
    """``"capture.truth"`` -> ("capture", "truth"); ``"capture"`` -> ("capture", None)."""
    if "." in name:
        stage, extra = name.split(".", 1)
        return stage, extra
    return name, None


@dataclass(frozen=True)
class Dag:
    """Stages, their upstream stage names and a topological order (file order among equals).

    ``unloaded`` names stages listed in ``configs/pipeline.yaml`` whose module did not load:
    other stages may name them as inputs, but selecting one raises (StageRegistry.require).
    """

    stages: dict[str, Stage]
    upstream: dict[str, tuple[str, ...]]
    order: tuple[str, ...]
    unloaded: tuple[str, ...] = ()

    @classmethod
    def build(cls, stages: Iterable[Stage], unloaded: Iterable[str] = ()) -> "Dag":
        """Validate the declarations and build the graph."""
        by_name: dict[str, Stage] = {}
        listed: list[str] = []
        for stage in stages:
            if stage.name in by_name:
                raise ConfigError(f"stage '{stage.name}' is declared twice; stage names must be unique")
            by_name[stage.name] = stage
            listed.append(stage.name)
        unloaded = tuple(n for n in unloaded if n not in by_name)
        known = set(by_name) | set(unloaded)
        upstream: dict[str, tuple[str, ...]] = {}
        for stage in by_name.values():
            ups: list[str] = []
            for inp in stage.inputs:
                base, extra = split_input(inp)
                if base not in known:
                    raise ConfigError(f"stage '{stage.name}': unknown input '{inp}'; known stages: "
                                      f"{', '.join(sorted(known))}")
                if base == stage.name:
                    raise ConfigError(f"stage '{stage.name}' takes its own output '{inp}' as input "
                                      f"(cycle {stage.name} -> {stage.name})")
                if extra is not None and base in by_name and extra not in by_name[base].extra_outputs:
                    raise ConfigError(f"stage '{stage.name}': input '{inp}': stage '{base}' declares "
                                      f"no extra output '{extra}' (it has: "
                                      f"{', '.join(by_name[base].extra_outputs) or 'none'})")
                if extra == TRUTH and not stage.may_read_truth:
                    raise ConfigError(f"stage '{stage.name}' takes ground truth '{inp}' but is not an "
                                      f"evaluation stage; only stages named '*_eval' (or declared with "
                                      f"reads_truth=True) may read ground truth")
                if base not in ups:
                    ups.append(base)
            upstream[stage.name] = tuple(ups)
            if stage.evaluates is not None and stage.evaluates not in known:
                raise ConfigError(f"stage '{stage.name}' evaluates unknown stage '{stage.evaluates}'")
        for name in unloaded:
            upstream[name] = ()
        order = _topological_order([*listed, *unloaded], upstream)
        return cls(stages=by_name, upstream=upstream, order=tuple(order), unloaded=unloaded)

    @property
    def names(self) -> list[str]:
        """Stage names in run order."""
        return list(self.order)

    def downstream(self) -> dict[str, list[str]]:
        """Stage name -> the stages that take its output directly."""
        down: dict[str, list[str]] = {n: [] for n in self.order}
        for name in self.order:
            for up in self.upstream[name]:
                down[up].append(name)
        return down

    def ancestors(self, name: str) -> set[str]:
        """Every stage ``name`` depends on, transitively (excluding itself)."""
        seen: set[str] = set()
        stack = list(self.upstream[name])
        while stack:
            up = stack.pop()
            if up not in seen:
                seen.add(up)
                stack.extend(self.upstream[up])
        return seen

    def descendants(self, name: str) -> set[str]:
        """Every stage that depends on ``name``, transitively (excluding itself)."""
        down = self.downstream()
        seen: set[str] = set()
        stack = list(down[name])
        while stack:
            d = stack.pop()
            if d not in seen:
                seen.add(d)
                stack.extend(down[d])
        return seen

    def evaluator_of(self, name: str) -> str | None:
        """The evaluation stage whose ``evaluates`` names ``name`` (first in order), if any."""
        for other in self.order:
            stage = self.stages.get(other)
            if stage is not None and stage.evaluates == name:
                return other
        return None

    def _check_names(self, names: Iterable[str], option: str) -> None:
        for name in names:
            if name not in self.upstream:
                raise ConfigError(f"{option} {name}: unknown stage; stages: {', '.join(self.order)}")

    def select(self, *, until: str | None = None, from_: str | None = None,
               only: Iterable[str] | None = None) -> list[str]:
        """The stages a run covers, in topological order.

        No option: every stage. ``until``: it and its ancestors. ``from_``: it and its
        descendants. Both: the stages between them. ``only``: exactly those stages.
        """
        if only:
            only = list(only)
            self._check_names(only, "--only")
            if until or from_:
                raise ConfigError("--only cannot be combined with --until/--from")
            return [n for n in self.order if n in set(only)]
        chosen = set(self.order)
        if until:
            self._check_names([until], "--until")
            chosen &= self.ancestors(until) | {until}
        if from_:
            self._check_names([from_], "--from")
            chosen &= self.descendants(from_) | {from_}
        if until and from_ and not chosen:
            raise ConfigError(f"--from {from_} --until {until}: '{until}' does not depend on '{from_}'")
        return [n for n in self.order if n in chosen]

    def to_text(self, broken: dict[str, str] | None = None) -> str:
        """One line per stage in run order: ``name <- inputs``."""
        lines = []
        for name in self.order:
            stage = self.stages.get(name)
            if stage is None:
                why = (broken or {}).get(name, "not loaded")
                lines.append(f"{name}  [unloadable: {why}]")
                continue
            ins = ", ".join(stage.inputs) or "-"
            note = f"  (evaluates {stage.evaluates})" if stage.evaluates else ""
            extra = f"  (+ {', '.join(f'{name}.{x}' for x in stage.extra_outputs)})" if stage.extra_outputs else ""
            lines.append(f"{name} <- {ins}{extra}{note}")
        return "\n".join(lines)

    def to_dot(self) -> str:
        """Graphviz ``dot`` text; truth edges dashed, unloadable stages grey."""
        lines = ["digraph pipeline {", "  rankdir=LR;", "  node [shape=box];"]
        for name in self.order:
            style = ' [style=filled, fillcolor="#dddddd"]' if name not in self.stages else ""
            lines.append(f'  "{name}"{style};')
        for name in self.order:
            stage = self.stages.get(name)
            for inp in stage.inputs if stage else ():
                base, extra = split_input(inp)
                attrs = f' [style=dashed, label="{extra}"]' if extra else ""
                lines.append(f'  "{base}" -> "{name}"{attrs};')
        lines.append("}")
        return "\n".join(lines)


def _topological_order(names: list[str], upstream: dict[str, tuple[str, ...]]) -> list[str]:
    """Depth-first order keeping file order among independent stages; names a cycle if any."""
    state: dict[str, int] = {}
    order: list[str] = []
    for root in names:
        if state.get(root) == 2:
            continue
        path: list[str] = []
        stack: list[tuple[str, int]] = [(root, 0)]
        while stack:
            node, idx = stack.pop()
            if idx == 0:
                if state.get(node) == 2:
                    continue
                if state.get(node) == 1:
                    cycle = path[path.index(node):] + [node]
                    raise ConfigError(f"the stage graph has a cycle: {' -> '.join(cycle)}")
                state[node] = 1
                path.append(node)
            ups = upstream[node]
            if idx < len(ups):
                stack.append((node, idx + 1))
                up = ups[idx]
                if state.get(up) == 1:
                    cycle = path[path.index(up):] + [up]
                    raise ConfigError(f"the stage graph has a cycle: {' -> '.join(reversed(cycle))}")
                if state.get(up) != 2:
                    stack.append((up, 0))
            else:
                state[node] = 2
                path.pop()
                order.append(node)
    return order
