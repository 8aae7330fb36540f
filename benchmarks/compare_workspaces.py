"""Compare every stage's current outputs in two workspaces of one subject, file by file.

Used to check that a refactor leaves the pipeline's results bit-identical: run the same
subject from an empty workspace before and after the change, then::

    python -m benchmarks.compare_workspaces workspaces-before/ci workspaces-after/ci

For each stage output it prints whether the object digests agree; where they do not, which
files differ and, for JSON files, which keys (``metrics.json`` holds timings and is listed
apart, as it never agrees between two runs). Exit status 0 when every data file agrees.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import sys
from pathlib import Path
from typing import Any


def _refs(workspace: Path) -> dict[str, dict[str, str]]:
    return {path.stem: json.loads(path.read_text())["outputs"] for path in sorted((workspace / "refs").glob("*.json"))}


def _files(folder: Path) -> dict[str, str]:
    digests = {}
    for root, _, names in os.walk(folder):
        for name in names:
            path = Path(root) / name
            digests[path.relative_to(folder).as_posix()] = hashlib.blake2b(path.read_bytes()).hexdigest()
    return digests


def _flat(value: Any, prefix: str = "") -> dict[str, Any]:
    if isinstance(value, dict):
        out: dict[str, Any] = {}
        for key, sub in value.items():
            out.update(_flat(sub, f"{prefix}.{key}" if prefix else str(key)))
        return out
    if isinstance(value, list):
        out = {}
        for i, sub in enumerate(value):
            out.update(_flat(sub, f"{prefix}[{i}]"))
        return out
    return {prefix: value}


def _json_keys(a: Path, b: Path) -> list[str]:
    try:
        fa, fb = _flat(json.loads(a.read_text())), _flat(json.loads(b.read_text()))
    except (OSError, ValueError):
        return []
    return sorted(k for k in set(fa) | set(fb) if fa.get(k) != fb.get(k))


def compare(before: Path, after: Path) -> tuple[list[str], bool]:
    """Report lines and whether every data file (all but ``metrics.json``) agrees."""
    refs_a, refs_b = _refs(before), _refs(after)
    lines, same, clean = [], 0, True
    for stage in sorted(set(refs_a) | set(refs_b)):
        if stage not in refs_a or stage not in refs_b:
            lines.append(f"{stage}: only in {'after' if stage in refs_b else 'before'}")
            clean = False
            continue
        for out in sorted(set(refs_a[stage]) | set(refs_b[stage])):
            da, db = refs_a[stage].get(out), refs_b[stage].get(out)
            if da == db:
                same += 1
                continue
            if da is None or db is None:
                lines.append(f"{stage}.{out}: only in one workspace")
                clean = False
                continue
            folder_a, folder_b = before / "objects" / da, after / "objects" / db
            fa, fb = _files(folder_a), _files(folder_b)
            differ = sorted(k for k in set(fa) | set(fb) if fa.get(k) != fb.get(k))
            data = [k for k in differ if Path(k).name != "metrics.json"]
            if not data:
                lines.append(f"{stage}.{out}: data identical (metrics.json differs: timings)")
                continue
            clean = False
            for rel in data:
                keys = _json_keys(folder_a / rel, folder_b / rel) if rel.endswith(".json") else []
                shown = f" (keys: {', '.join(keys[:6])}{' ...' if len(keys) > 6 else ''})" if keys else ""
                lines.append(f"{stage}.{out}: {rel} differs{shown}")
    lines.append(f"{same} outputs identical object for object")
    return lines, clean


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("before", type=Path, help="workspace of the subject before the change (<root>/<subject>)")
    parser.add_argument("after", type=Path, help="the same subject's workspace after the change")
    args = parser.parse_args(argv)
    lines, clean = compare(args.before, args.after)
    print("\n".join(lines))
    return 0 if clean else 1


if __name__ == "__main__":
    sys.exit(main())
