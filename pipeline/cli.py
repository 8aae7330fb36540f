"""The ``pipeline`` command: a thin argparse layer over the library.

Exit codes: 0 ok, 1 a stage failed (or another pipeline error), 2 bad usage or config.
A ``PipelineError`` prints one clear line on stderr (a traceback only with ``--debug``).
Extra subcommands (``hw``, ``report``, ...) come from ``commands:`` in
``configs/pipeline.yaml`` and are imported only when called.
"""

from __future__ import annotations

import argparse
import importlib
import json
import logging
import signal
import sys
import traceback
from pathlib import Path
from typing import Any, Callable, Sequence

from pipeline.errors import ConfigError, PipelineError

BUILTIN = ("run", "status", "show", "dag", "gc", "log")
log = logging.getLogger("pipeline.cli")


def _common(parser: argparse.ArgumentParser, *, subject: bool = True) -> None:
    if subject:
        parser.add_argument("-S", "--subject", required=True, help="subject name (configs/subjects/<S>.yaml)")
    parser.add_argument("--workspace-root", default=None,
                        help="folder holding the workspaces (default: $PIPELINE_WORKSPACES or <project>/workspaces)")
    parser.add_argument("--project-root", default=None,
                        help="project folder (default: $PIPELINE_PROJECT_ROOT or the nearest parent "
                             "holding configs/pipeline.yaml)")
    parser.add_argument("--debug", action="store_true", help="show tracebacks and debug logs")


def _config_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--preset", default=None, help="preset to start from instead of the subject's own")
    parser.add_argument("--set", dest="sets", action="append", default=[], metavar="STAGE.KEY=VALUE",
                        help="override a param (value parsed as YAML); repeatable")


def build_parser(extra_commands: dict[str, str] | None = None) -> argparse.ArgumentParser:
    """The argument parser of every built-in subcommand."""
    parser = argparse.ArgumentParser(
        prog="pipeline", description="Capture-to-relight pipeline: run stages, inspect workspaces.",
        epilog=("extra commands: " + ", ".join(sorted(extra_commands))) if extra_commands else None)
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    run = sub.add_parser("run", help="run the stages that are stale (all, or a selection)")
    _common(run)
    _config_options(run)
    run.add_argument("--until", metavar="STAGE", help="run STAGE and everything it depends on")
    run.add_argument("--from", dest="from_", metavar="STAGE", help="run STAGE and everything downstream of it")
    run.add_argument("--only", nargs="+", metavar="STAGE", help="run exactly these stages")
    run.add_argument("--force", nargs="*", metavar="STAGE",
                     help="rerun these stages even if fresh (no names: every selected stage)")
    run.add_argument("--dry-run", action="store_true", help="print what would run and why; run nothing")
    run.add_argument("--workers", type=int, default=None, help="worker processes for per-item work (default: all cores)")
    run.add_argument("--executor", default=None, metavar="KIND",
                     help="where per-item work runs: local (process pool, default) or ray")

    status = sub.add_parser("status", help="fresh / stale / never-run per stage, with the reason")
    _common(status)
    _config_options(status)
    status.add_argument("--verify", action="store_true",
                        help="re-hash every current object; corrupt ones are marked and rebuilt by the next run")
    status.add_argument("--json", action="store_true", help="machine-readable output")

    show = sub.add_parser("show", help="a stage's output folder, metrics (with its evaluation's) and provenance")
    _common(show)
    show.add_argument("stage")
    show.add_argument("--json", action="store_true",
                      help="print the merged metrics as one flat JSON object")
    show.add_argument("--full", action="store_true", help="with --json: also path and provenance")

    dag = sub.add_parser("dag", help="print the stage graph")
    _common(dag, subject=False)
    dag.add_argument("--format", choices=("text", "dot"), default="text")

    gc = sub.add_parser("gc", help="delete objects that no ref and no recent action reaches, and stage-cache "
                                    "files unused for --keep-days")
    _common(gc)
    gc.add_argument("--keep-days", type=float, default=7.0,
                    help="keep outputs of actions younger than this many days, and cache files used "
                         "within them (default 7)")

    logcmd = sub.add_parser("log", help="print the latest log of a stage")
    _common(logcmd)
    logcmd.add_argument("stage")
    return parser


def _setup_logging(debug: bool) -> None:
    from pipeline.progress import ConsoleHandler

    handler = ConsoleHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("%(asctime)s %(name)s: %(message)s", datefmt="%H:%M:%S"))
    root = logging.getLogger()
    for old in list(root.handlers):
        root.removeHandler(old)
    root.addHandler(handler)
    root.setLevel(logging.DEBUG if debug else logging.INFO)


_LOADED: list = []


def _project(args: argparse.Namespace):
    from pipeline.project import Project, find_project_root
    from pipeline.workspace import workspace_root

    root = Path(args.project_root).resolve() if args.project_root else find_project_root()
    if args.project_root and not (root / "configs" / "pipeline.yaml").is_file():
        raise ConfigError(f"--project-root {args.project_root}: no configs/pipeline.yaml there")
    project = Project(root, cache_dir=workspace_root(root, args.workspace_root) / ".pipeline-cache")
    _LOADED.append(project)
    return project


def _workspace(args: argparse.Namespace, project):
    from pipeline.config import check_subject_name
    from pipeline.workspace import Workspace, workspace_root

    return Workspace(workspace_root(project.root, args.workspace_root), check_subject_name(args.subject))


def cmd_run(args: argparse.Namespace) -> int:
    """``pipeline run``: run the selected stages that are stale."""
    from pipeline.runner import RunOptions, Runner

    if args.workers is not None and args.workers < 1:
        raise ConfigError(f"--workers {args.workers}: must be at least 1")
    project = _project(args)
    ws = _workspace(args, project)
    options = RunOptions(until=args.until, from_=args.from_, only=args.only, force=args.force,
                         dry_run=args.dry_run, workers=args.workers, executor=args.executor,
                         preset=args.preset,
                         sets=list(args.sets), workspace_root=args.workspace_root)
    runner = Runner(project, ws, options)

    def _terminate(signum: int, frame: object) -> None:
        # A batch scheduler's SIGTERM: unwind like Ctrl-C so temp outputs are removed.
        raise KeyboardInterrupt(f"signal {signum}")

    previous = signal.signal(signal.SIGTERM, _terminate)
    try:
        outcomes = runner.run()
    finally:
        signal.signal(signal.SIGTERM, previous)
    width = max((len(o.stage) for o in outcomes), default=5)
    for o in outcomes:
        if args.dry_run:
            print(f"{o.outcome:<6} {o.stage:<{width}}  {o.detail}".rstrip())
        else:
            took = f"  {o.seconds:.2f} s" if o.outcome == "ran" else ""
            print(f"{o.outcome:<6} {o.stage}{took}")
    if not args.dry_run:
        ran = sum(o.outcome == "ran" for o in outcomes)
        print(f"subject {ws.subject}: {ran} stage(s) ran, {len(outcomes) - ran} up to date ({ws.path})")
    return 0


def cmd_status(args: argparse.Namespace) -> int:
    """``pipeline status``: fresh / stale / never-run per stage, with reasons."""
    from pipeline.status import assess, format_status

    project = _project(args)
    ws = _workspace(args, project)
    subject_config = project.subject_config(ws.subject, preset=args.preset, sets=args.sets)
    params = project.params(subject_config)
    statuses = assess(project, ws, params, list(project.dag.order), verify=args.verify)
    if args.json:
        print(json.dumps([s.to_json() for s in statuses], indent=1))
    else:
        print(format_status(statuses))
    return 0


def _metrics_of(ws, digest: str) -> dict[str, Any]:
    path = ws.object_path(digest) / "metrics.json"
    return json.loads(path.read_text(encoding="utf-8")) if path.is_file() else {}


def cmd_show(args: argparse.Namespace) -> int:
    """``pipeline show``: output folder, merged metrics and provenance of a stage."""
    project = _project(args)
    ws = _workspace(args, project)
    name = args.stage
    if name not in project.dag.upstream:
        raise ConfigError(f"unknown stage '{name}'; stages: {', '.join(project.dag.order)}")
    ref = ws.read_ref(name)
    if ref is None:
        raise PipelineError(f"stage '{name}' has no output for subject '{ws.subject}' yet; run "
                            f"`pipeline run -S {ws.subject} --until {name}`")
    action = ws.read_action(ref.action) or {}
    metrics = _metrics_of(ws, ref.outputs["out"])
    evaluator = project.dag.evaluator_of(name)
    eval_info = None
    if evaluator:
        eval_ref = ws.read_ref(evaluator)
        if eval_ref is not None:
            eval_metrics = _metrics_of(ws, eval_ref.outputs["out"])
            for key, value in eval_metrics.items():
                metrics[key if key not in metrics else f"{evaluator}.{key}"] = value
            eval_info = {"stage": evaluator, "action": eval_ref.action,
                         "path": str(ws.object_path(eval_ref.outputs["out"]))}
    info = {
        "stage": name, "subject": ws.subject, "path": str(ws.object_path(ref.outputs["out"])),
        "outputs": {k: str(ws.object_path(v)) for k, v in ref.outputs.items()},
        "metrics": metrics, "evaluation": eval_info,
        "provenance": {k: action.get(k) for k in ("key", "code", "params", "inputs", "external", "timings",
                                                   "versions", "host", "command", "log")},
    }
    if args.json:
        print(json.dumps(info if args.full else metrics, indent=1, sort_keys=True))
        return 0
    print(f"stage    {name}   subject {ws.subject}")
    for out, path in info["outputs"].items():
        print(f"{out:<8} {path}")
    if evaluator:
        print(f"eval     {evaluator}: " + (eval_info["path"] if eval_info else "not run yet"))
    print("metrics:")
    for key in sorted(metrics):
        print(f"  {key} = {metrics[key]}")
    prov = info["provenance"]
    print("provenance:")
    print(f"  action   {ref.action}")
    print(f"  code     {prov.get('code')}")
    for inp, digest in (prov.get("inputs") or {}).items():
        print(f"  input    {inp} = {digest[:16]}  {ws.object_path(digest)}")
    for path, digest in (prov.get("external") or {}).items():
        print(f"  external {path} = {digest[:16]}")
    print("  params   " + json.dumps(prov.get("params"), sort_keys=True))
    timings = prov.get("timings") or {}
    print(f"  ran      {timings.get('started')} for {timings.get('seconds')} s "
          f"(cpu {timings.get('cpu_seconds')} s) on {prov.get('host')}")
    print("  versions " + ", ".join(f"{k} {v}" for k, v in (prov.get("versions") or {}).items()))
    print(f"  command  {prov.get('command')}")
    print(f"  log      {prov.get('log')}")
    return 0


def cmd_dag(args: argparse.Namespace) -> int:
    """``pipeline dag``: the stage graph as text or Graphviz dot."""
    project = _project(args)
    print(project.dag.to_dot() if args.format == "dot" else project.dag.to_text(project.registry.broken))
    return 0


def cmd_gc(args: argparse.Namespace) -> int:
    """``pipeline gc``: delete unreachable objects (under the lock)."""
    project = _project(args)
    ws = _workspace(args, project)
    if not ws.path.is_dir():
        raise PipelineError(f"no workspace for subject '{ws.subject}' at {ws.path}")
    with ws.lock():
        report = ws.gc(keep_days=args.keep_days)
    print(f"removed {report['objects_removed']} object(s), {report['bytes_freed'] / 1e6:.1f} MB, "
          f"{report['actions_removed']} old action record(s); kept {report['objects_kept']} object(s); "
          f"cache: removed {report['cache_files_removed']} file(s) unused for {args.keep_days:g} day(s), "
          f"{report['cache_bytes_freed'] / 1e6:.1f} MB")
    return 0


def cmd_log(args: argparse.Namespace) -> int:
    """``pipeline log``: print the latest log of a stage."""
    project = _project(args)
    ws = _workspace(args, project)
    if args.stage not in project.dag.upstream:
        raise ConfigError(f"unknown stage '{args.stage}'; stages: {', '.join(project.dag.order)}")
    path = ws.latest_log(args.stage)
    if path is None:
        raise PipelineError(f"no log for stage '{args.stage}' of subject '{ws.subject}' (it has not run)")
    print(f"# {path}")
    sys.stdout.write(path.read_text(encoding="utf-8", errors="replace"))
    return 0


COMMANDS: dict[str, Callable[[argparse.Namespace], int]] = {
    "run": cmd_run, "status": cmd_status, "show": cmd_show, "dag": cmd_dag, "gc": cmd_gc, "log": cmd_log,
}


def _extra_commands() -> dict[str, str]:
    """``commands:`` of configs/pipeline.yaml (empty when no project is found)."""
    from pipeline.config import load_pipeline_config
    from pipeline.project import find_project_root

    try:
        return load_pipeline_config(find_project_root()).commands
    except ConfigError:
        return {}


def _run_extra(name: str, target: str, argv: list[str]) -> int:
    from pipeline.project import ensure_importable, find_project_root

    ensure_importable(find_project_root())
    module_name, func_name = target.split(":")
    try:
        func = getattr(importlib.import_module(module_name), func_name)
    except (ImportError, AttributeError) as err:
        raise ConfigError(f"configs/pipeline.yaml commands.{name} ({target}): cannot import it: {err}") from None
    result = func(argv)
    return int(result or 0)


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``pipeline`` console script; returns the exit code."""
    argv = list(sys.argv[1:] if argv is None else argv)
    debug = "--debug" in argv
    try:
        command = next((a for a in argv if not a.startswith("-")), None)
        if command is not None and command not in BUILTIN and argv and argv[0] == command:
            extra = _extra_commands()
            if command in extra:
                _setup_logging(debug)
                return _run_extra(command, extra[command], argv[1:])
            raise ConfigError(f"unknown command '{command}'; commands: {', '.join([*BUILTIN, *extra])}")
        parser = build_parser(_extra_commands() if not argv or argv[0] in ("-h", "--help") else None)
        args = parser.parse_args(argv)
        _setup_logging(args.debug)
        try:
            return COMMANDS[args.command](args)
        finally:
            for project in _LOADED:
                project.save_cache()
            _LOADED.clear()
    except PipelineError as err:
        if debug:
            traceback.print_exc()
        print(f"pipeline: error: {err}", file=sys.stderr)
        return err.exit_code
    except KeyboardInterrupt:
        print("pipeline: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        # Output piped into `head` and the like: stop quietly.
        sys.stderr.close()
        return 0


if __name__ == "__main__":
    sys.exit(main())
