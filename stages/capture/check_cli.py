"""``pipeline check-capture DIR``: is a capture folder ready to import? One line per problem.

    pipeline check-capture /data/shoot-0412            # exit 0: it imports with nothing dropped
    pipeline check-capture /data/shoot-0412 --allow-gaps

Exit codes: 0 the folder imports (``--allow-gaps``: possibly with frames dropped), 1 it has
problems (listed on stdout, one per line, each naming the file and what to do), 2 bad usage.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from stages.capture.check import check_images, scan_folder


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="pipeline check-capture",
        description="Check a real capture folder against the import layout (stages/capture/README.md) before "
                    "anything runs: capture.json, the controller log and its gaps, the camera folders and their "
                    "image counts, every EXR (readable, float, one size), time stamps, links out of the folder.")
    parser.add_argument("folder", type=Path, metavar="DIR", help="the capture folder")
    parser.add_argument("--allow-gaps", action="store_true",
                        help="accept what the importer takes with frames set aside as dropped (a camera short of "
                             "images, triggers missing from the controller log); still listed")
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the exit code."""
    try:
        args = _parser().parse_args(argv)
    except SystemExit as exit_:  # argparse exits on --help and on bad usage
        return int(exit_.code or 0)
    scan = scan_folder(args.folder)
    check_images(scan)
    for problem in scan.problems:
        print(problem.line())
    failing = scan.blocking if args.allow_gaps else scan.problems
    root = scan.folder.root
    if failing:
        print(f"{root}: {len(failing)} problem(s); the folder is not ready to import", file=sys.stderr)
        return 1
    images = sum(len(v) for v in scan.images.values())
    dropped = " (with frames dropped, see above)" if scan.problems else ""
    print(f"{root}: imports{dropped}: {len(scan.images)} cameras, {images} images, "
          f"{len(scan.entries or [])} controller log entries at {scan.info['fps']:g} fps")
    return 0


if __name__ == "__main__":
    sys.exit(main())
