"""``pipeline report -S SUBJECT``: bring the report up to date and print where it is.

Runs ``pipeline run -S SUBJECT --until report`` (so only stale stages rerun), then prints
the path of ``report.html``.
"""

from __future__ import annotations

import argparse
from typing import Sequence


def main(argv: Sequence[str]) -> int:
    """Entry point wired in configs/pipeline.yaml ``commands: report``."""
    parser = argparse.ArgumentParser(prog="pipeline report", description=__doc__.splitlines()[0])
    parser.add_argument("-S", "--subject", required=True, help="subject name (configs/subjects/<S>.yaml)")
    parser.add_argument("--workspace-root", default=None, help="folder holding the workspaces")
    parser.add_argument("--preset", default=None, help="preset to start from instead of the subject's own")
    parser.add_argument("--set", dest="sets", action="append", default=[], metavar="STAGE.KEY=VALUE",
                        help="override a param (value parsed as YAML); repeatable")
    args = parser.parse_args(list(argv))
    from pipeline.cli import main as pipeline_main

    common = ["-S", args.subject] + (["--workspace-root", args.workspace_root] if args.workspace_root else [])
    run_args = ["run", *common, "--until", "report"] + (["--preset", args.preset] if args.preset else [])
    for item in args.sets:
        run_args += ["--set", item]
    code = pipeline_main(run_args)
    if code != 0:
        return code
    from pipeline.project import find_project_root
    from pipeline.workspace import Workspace, workspace_root
    from stages.report.output import ReportOutput

    ws = Workspace(workspace_root(find_project_root(), args.workspace_root), args.subject)
    ref = ws.read_ref("report")
    print(f"report: {ReportOutput(ws.object_path(ref.outputs['out'])).html_path}")
    return 0
