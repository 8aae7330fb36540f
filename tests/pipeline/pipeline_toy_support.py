"""The toy project used by the orchestrator tests: a private copy and a CLI runner over it
(in a subprocess, so each invocation imports the copy's stage modules afresh, exactly like a
user's shell)."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
TOY = Path(__file__).resolve().parent / "toy"


@dataclass
class Result:
    returncode: int
    stdout: str
    stderr: str

    @property
    def ran(self) -> set[str]:
        """Stages that actually ran (not reused / fresh)."""
        return {line.split()[1] for line in self.stdout.splitlines() if line.startswith("ran ")}


class ToyProject:
    """A copy of tests/pipeline/toy with its own workspace root."""

    def __init__(self, tmp_path: Path) -> None:
        self.root = tmp_path / "project"
        shutil.copytree(TOY, self.root, ignore=shutil.ignore_patterns("__pycache__"))
        self.workspaces = tmp_path / "workspaces"

    def env(self, **extra: str) -> dict[str, str]:
        env = dict(os.environ)
        env.update(PYTHONPATH=str(REPO), PIPELINE_PROJECT_ROOT=str(self.root),
                   PIPELINE_WORKSPACES=str(self.workspaces), PYTHONDONTWRITEBYTECODE="1")
        env.pop("TOY_HOLD_FILE", None)
        env.update(extra)
        return env

    def command(self, *args: str) -> list[str]:
        return [sys.executable, "-m", "pipeline.cli", *args]

    def cli(self, *args: str, expect: int | None = 0, **env: str) -> Result:
        proc = subprocess.run(self.command(*args), cwd=self.root, env=self.env(**env), capture_output=True,
                              text=True, timeout=120)
        result = Result(proc.returncode, proc.stdout, proc.stderr)
        if expect is not None and proc.returncode != expect:
            raise AssertionError(f"pipeline {' '.join(args)} exited {proc.returncode}, expected {expect}\n"
                                 f"stdout:\n{proc.stdout}\nstderr:\n{proc.stderr}")
        return result

    def popen(self, *args: str, **env: str) -> subprocess.Popen:
        return subprocess.Popen(self.command(*args), cwd=self.root, env=self.env(**env), stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE, text=True, start_new_session=True)

    def ws(self, subject: str = "alice") -> Path:
        return self.workspaces / subject

    def edit(self, relpath: str, old: str, new: str) -> None:
        path = self.root / relpath
        text = path.read_text()
        if old not in text:
            raise AssertionError(f"{old!r} not in {relpath}")
        path.write_text(text.replace(old, new, 1))
