"""``pipeline hw``: talk to the LED controller from a shell.

    pipeline hw ping --port /dev/ttyUSB0
    pipeline hw upload --port /dev/ttyUSB0 --sequence sequence.json [--arm]
    pipeline hw status --port /dev/ttyUSB0
    pipeline hw log --port /dev/ttyUSB0
    pipeline hw emulate [--bars 32] [--seconds 0]
    pipeline hw export-capture -S alice --out /data/alice-export [--rig my_rig.yaml]

``emulate`` starts an emulated controller on a pty and prints its port, so the other
commands (or any serial terminal) can be tried without a rig. ``export-capture`` writes a
virtual-studio capture in the layout a real capture is imported from (``stages.capture.export``).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from hardware.led import ControllerError, LedController, LedEmulator
from hardware.led.protocol import light_token
from pipeline.errors import PipelineError


def _add_port_args(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--port", required=True, help="serial device or pyserial URL, e.g. /dev/ttyUSB0")
    parser.add_argument("--timeout", type=float, default=0.5, help="seconds to wait for each reply")
    parser.add_argument("--retries", type=int, default=2, help="resends after a timeout or corrupt reply")


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="pipeline hw", description="LED-bar controller tools.")
    commands = parser.add_subparsers(dest="command", required=True)
    ping = commands.add_parser("ping", help="check the controller answers; print its firmware")
    _add_port_args(ping)
    ping.add_argument("--count", type=int, default=3, help="pings to send")
    upload = commands.add_parser("upload", help="upload a sequence, read it back, verify its checksum")
    _add_port_args(upload)
    upload.add_argument("--sequence", required=True, type=Path, help="sequence.json of the sequence stage")
    upload.add_argument("--arm", action="store_true", help="arm the program after verifying it")
    status = commands.add_parser("status", help="print the controller's state")
    _add_port_args(status)
    log = commands.add_parser("log", help="print the controller's pulse log as JSON lines")
    _add_port_args(log)
    emulate = commands.add_parser("emulate", help="serve an emulated controller on a pty and print its port")
    emulate.add_argument("--bars", type=int, default=32, help="LED bars on the emulated board")
    emulate.add_argument("--seconds", type=float, default=0.0, help="stop after this long (0: until Ctrl-C)")
    _add_export_args(commands)
    return parser


_EXPORT_HELP = """\
Write a virtual-studio capture, with its calibration takes and scans, in the layout a real
capture is imported from (stages/capture/README.md). It runs the subject's `sequence` and
`capture` stages as `pipeline run -S SUBJECT --until capture` would (fresh ones are reused,
so an existing capture costs nothing; --preset and --set apply as there), then writes the
capture output: cameras/<cam>/000000.exr... (each camera's images in arrival order, float
EXR) with timestamps.json, controller_log.json, capture.json, rig.yaml (the rig it was
filmed with), scans/ and calib/. Files are hard-linked from the workspace (copied across
file systems); the ground truth stays behind.

--rig films with another rig file (the form of configs/rig.yaml; keys it lacks come from
the subject's rig): the subject's workspace then holds that capture until its next plain
`pipeline run`. A subject that always uses another rig names it in its file (rig: PATH).

Check the result with `pipeline check-capture DIR`; import it with
`pipeline run -S NAME --set capture.source=DIR`."""


def _add_export_args(commands: argparse._SubParsersAction) -> None:
    export = commands.add_parser("export-capture", help="write a virtual-studio capture in the import layout",
                                 description=_EXPORT_HELP, formatter_class=argparse.RawDescriptionHelpFormatter)
    export.add_argument("-S", "--subject", required=True, help="subject name (configs/subjects/<S>.yaml)")
    export.add_argument("--out", required=True, type=Path, help="folder to write (new or empty)")
    export.add_argument("--rig", type=Path, default=None, help="rig YAML to film with instead of configs/rig.yaml")
    export.add_argument("--preset", default=None, help="preset to start from instead of the subject's own")
    export.add_argument("--set", dest="sets", action="append", default=[], metavar="STAGE.KEY=VALUE",
                        help="override a param of sequence or capture (value parsed as YAML); repeatable")
    export.add_argument("--workers", type=int, default=None, help="worker processes for rendering (default: all cores)")
    export.add_argument("--workspace-root", default=None,
                        help="folder holding the workspaces (default: $PIPELINE_WORKSPACES or <project>/workspaces)")


def _load_sequence(path: Path) -> tuple[list, int, str | None]:
    try:
        sequence = json.loads(path.read_text())
        pattern, cycles = sequence["pattern"], int(sequence["cycles"])
    except FileNotFoundError as err:
        raise ValueError(f"{path}: no such file; pass the sequence stage's sequence.json") from err
    except (json.JSONDecodeError, KeyError, TypeError, ValueError) as err:
        raise ValueError(f"{path}: not a sequence file (needs 'pattern' and 'cycles'): {err}") from err
    for light in pattern:
        light_token(light)  # raises ValueError naming the bad light
    return pattern, cycles, sequence.get("program_crc32")


def _ping(args: argparse.Namespace) -> int:
    with LedController(args.port, args.timeout, args.retries) as controller:
        info = controller.version()
        times_ms = [controller.ping() * 1e3 for _ in range(max(1, args.count))]
    print(f"{args.port}: {info.firmware} {info.version}, protocol {info.protocol}, {info.bars} bars; "
          f"round trip {min(times_ms):.2f}-{max(times_ms):.2f} ms")
    return 0


def _upload(args: argparse.Namespace) -> int:
    pattern, cycles, expected_crc = _load_sequence(args.sequence)
    with LedController(args.port, args.timeout, args.retries) as controller:
        crc = controller.upload(pattern, cycles)
        controller.verify_program(pattern, cycles)
        if expected_crc is not None and expected_crc != crc:
            print(f"error: {args.sequence} says program_crc32 {expected_crc}, the controller holds {crc}; "
                  f"re-run the sequence stage", file=sys.stderr)
            return 1
        if args.arm:
            controller.arm(crc)
    print(f"{args.port}: uploaded {len(pattern)} steps x {cycles} cycles, read back and verified, "
          f"crc32 {crc}{', armed' if args.arm else ''}")
    return 0


def _status(args: argparse.Namespace) -> int:
    with LedController(args.port, args.timeout, args.retries) as controller:
        status = controller.status()
    print(json.dumps(status.__dict__))
    return 0


def _log(args: argparse.Namespace) -> int:
    with LedController(args.port, args.timeout, args.retries) as controller:
        for entry in controller.read_log():
            print(json.dumps(entry.to_json()))
    return 0


def _emulate(args: argparse.Namespace) -> int:
    with LedEmulator(n_bars=args.bars) as emulator:
        print(emulator.port, flush=True)
        print(f"emulated LED controller ({args.bars} bars) on {emulator.port}; Ctrl-C to stop",
              file=sys.stderr, flush=True)
        deadline = time.monotonic() + args.seconds if args.seconds > 0 else None
        try:
            while deadline is None or time.monotonic() < deadline:
                time.sleep(0.1)
        except KeyboardInterrupt:
            pass
    return 0


def _rig_sets(path: Path) -> list[str]:
    """``--set`` expressions that give the sequence and capture stages the rig in ``path``."""
    from pipeline.yamlio import read_yaml_mapping

    if not path.is_file():
        raise ValueError(f"--rig {path}: no such file; give a rig YAML in the form of configs/rig.yaml")
    rig = json.dumps(read_yaml_mapping(path, str(path)))  # JSON is YAML: --set parses it back
    return [f"sequence.rig={rig}", f"capture.rig={rig}"]


def _export_capture(args: argparse.Namespace) -> int:
    from pipeline.config import check_subject_name
    from pipeline.project import Project, find_project_root
    from pipeline.runner import RunOptions, Runner
    from pipeline.workspace import Workspace, workspace_root
    from stages.capture.export import check_destination, export_capture

    check_destination(args.out)  # before filming, not after
    root = find_project_root()
    ws_root = workspace_root(root, args.workspace_root)
    project = Project(root, cache_dir=ws_root / ".pipeline-cache")
    ws = Workspace(ws_root, check_subject_name(args.subject))
    sets = [*args.sets, *(_rig_sets(args.rig) if args.rig else [])]
    options = RunOptions(until="capture", workers=args.workers, preset=args.preset, sets=sets,
                         workspace_root=args.workspace_root)
    runner = Runner(project, ws, options)
    try:
        outcomes = runner.run()
    finally:
        project.save_cache()
    ref = ws.read_ref("capture")
    rig = runner.params["capture"].canonical["rig"]  # what the capture was filmed with
    summary = export_capture(ws.object_path(ref.outputs["out"]), args.out, rig=rig)
    ran = ", ".join(o.stage for o in outcomes if o.outcome == "ran") or "none (the capture was fresh)"
    print(f"{summary.folder}: {summary.cameras} cameras, {summary.images} images, {summary.log_entries} "
          f"controller log entries, {summary.calibration_files} calibration files (stages run: {ran})")
    return 0


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``pipeline hw``; returns the exit code (0 ok, 1 device error, 2 usage)."""
    try:
        args = _parser().parse_args(argv)
    except SystemExit as exit_:  # argparse exits on --help and on bad usage; return its code
        return int(exit_.code or 0)
    handlers = {"ping": _ping, "upload": _upload, "status": _status, "log": _log, "emulate": _emulate,
                "export-capture": _export_capture}
    try:
        return handlers[args.command](args)
    except PipelineError as err:  # export-capture: a bad subject, config or capture
        print(f"error: {err}", file=sys.stderr)
        return err.exit_code
    except ControllerError as err:
        print(f"error: {err}", file=sys.stderr)
        return 1
    except ValueError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
