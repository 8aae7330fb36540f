"""Comment, whitespace and docstring edits leave the code digest alone; code edits change it."""

from __future__ import annotations

from pathlib import Path

from pipeline.codedigest import normalised_source_digest

SOURCE = '''"""Module doc."""
import math


def area(radius_m):
    """Area of a disc."""
    return math.pi * radius_m ** 2
'''


def _digest(tmp_path: Path, name: str, text: str) -> str:
    path = tmp_path / name
    path.write_text(text)
    return normalised_source_digest(path)


def test_normalisation(tmp_path: Path) -> None:
    base = _digest(tmp_path, "a.py", SOURCE)
    cosmetic = SOURCE.replace('"""Area of a disc."""', '"""Area of a disc, in m^2."""  # why: docs')
    cosmetic = cosmetic.replace("import math\n", "import math  # stdlib\n\n\n")
    cosmetic = cosmetic.replace("math.pi * radius_m ** 2", "math.pi * radius_m**2   # pi r^2")
    assert _digest(tmp_path, "b.py", cosmetic) == base
    assert _digest(tmp_path, "c.py", SOURCE.replace("** 2", "** 3")) != base
    assert _digest(tmp_path, "d.py", SOURCE.replace("radius_m ** 2", "radius_m * radius_m")) != base
    assert _digest(tmp_path, "e.py", SOURCE + "x = 'a string statement'\n") != base
