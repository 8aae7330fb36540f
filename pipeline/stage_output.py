"""The base of every stage's typed output folder (``stages/<name>/output.py``).

Each stage that produces files owns one module that reads and writes its output folder
(``CaptureOutput(path).manifest()``, ``StabilizeOutput(path).cameras_head()``): it alone
spells the folder's file names, and a missing or malformed file gets one clear error from
it, naming the stage, the file and what to rerun::

    capture output /ws/objects/ab12/manifest.json is missing or unreadable: [Errno 2] ...;
    rerun the capture stage (pipeline run --only capture --force)

This module only holds what all of them share; it knows no stage.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Callable, ClassVar, Iterable, TypeVar

import numpy as np

from pipeline.errors import InputError

T = TypeVar("T")


class StageOutput:
    """One output folder of one stage: ``stage``'s main output, or its extra output ``output``.

    Subclasses set ``stage`` (the stage that writes the folder) and, for an extra output,
    ``output`` (``"truth"``), and add typed read and write methods built on ``read_json``,
    ``read_npz``, ``load`` and ``write_json``.
    """

    stage: ClassVar[str] = ""
    output: ClassVar[str] = ""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)

    def __repr__(self) -> str:
        return f"{type(self).__name__}({str(self.path)!r})"

    @property
    def label(self) -> str:
        """How errors name the folder: ``capture output``, ``capture truth``."""
        return f"{self.stage} {self.output or 'output'}"

    def rerun_hint(self) -> str:
        """What to do about a bad file in this folder."""
        return f"rerun the {self.stage} stage (pipeline run --only {self.stage} --force)"

    def error(self, path: str | Path, problem: object, state: str = "is missing or unreadable") -> InputError:
        """The one error for a bad file: ``<stage> output <file> <state>: <problem>; rerun ...``."""
        return InputError(f"{self.label} {path} {state}: {problem}; {self.rerun_hint()}")

    def malformed(self, path: str | Path, problem: object) -> InputError:
        """The error for a file that reads but does not hold what it should."""
        return self.error(path, problem, state="is malformed")

    def file(self, *parts: str) -> Path:
        """The path of ``parts`` inside the folder (nothing checked)."""
        return self.path.joinpath(*parts)

    def load(self, path: Path, reader: Callable[[Path], T]) -> T:
        """``reader(path)``; a missing or unreadable file (``OSError``/``ValueError``) becomes ``error``."""
        try:
            return reader(path)
        except (OSError, ValueError, KeyError, TypeError, EOFError) as err:
            raise self.error(path, err) from err

    def read_json(self, *parts: str, keys: Iterable[str] = (), kind: type = dict) -> Any:
        """The parsed JSON file ``parts``; it must be a ``kind`` (``dict`` holding ``keys``, ``list``)."""
        path = self.file(*parts)
        data = self.load(path, lambda p: json.loads(p.read_text()))
        if not isinstance(data, kind):
            raise self.malformed(path, f"expected a JSON {'object' if kind is dict else kind.__name__}, "
                                       f"found {type(data).__name__}")
        missing = [k for k in keys if k not in data]
        if missing:
            raise self.malformed(path, f"no {', '.join(repr(k) for k in missing)} key")
        return data

    def read_npz(self, *parts: str, keys: Iterable[str] = ()) -> dict[str, np.ndarray]:
        """Every array of the ``.npz`` file ``parts``; it must hold ``keys``."""
        path = self.file(*parts)

        def read(p: Path) -> dict[str, np.ndarray]:
            with np.load(p, allow_pickle=False) as npz:
                return {k: npz[k] for k in npz.files}

        arrays = self.load(path, read)
        missing = [k for k in keys if k not in arrays]
        if missing:
            raise self.malformed(path, f"no array {', '.join(repr(k) for k in missing)}")
        return arrays

    def write_json(self, data: Any, *parts: str, **dumps: Any) -> Path:
        """Write ``json.dumps(data, **dumps)`` (no trailing newline) to ``parts``; returns the path."""
        path = self.file(*parts)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(data, **dumps))
        return path
