"""The code digest of a stage: its own package plus the project modules it declares.

Each Python file is normalised through ``ast`` (docstrings dropped; comments and layout never
reach the tree), so comment-only and whitespace-only edits leave the digest unchanged while any
change to what the code does changes it. Files are found without importing anything (so a
status check need not import torch); digests are cached per process and, through the
declaration cache, across processes by file stat.
"""

from __future__ import annotations

import ast
import importlib.util
import os
import sys
from pathlib import Path
from typing import Protocol

from pipeline.errors import ConfigError
from pipeline.hashing import hash_bytes

_FILE_CACHE: dict[tuple[str, int, int], str] = {}
_STAGE_CACHE: dict[tuple[str, str], str] = {}


class _Declared(Protocol):
    name: str
    code: tuple[str, ...]


class _DigestStore(Protocol):
    def file_digest(self, path: str) -> str | None: ...

    def put_file_digest(self, path: str, size: int, mtime_ns: int, digest: str) -> None: ...


def _strip_docstrings(tree: ast.AST) -> ast.AST:
    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)):
            body = node.body
            if body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant) \
                    and isinstance(body[0].value.value, str):
                node.body = body[1:] or [ast.Pass()]
    return tree


def normalised_source_digest(path: Path | str, store: _DigestStore | None = None) -> str:
    """Digest of a Python file's meaning: its AST without docstrings (raw bytes if unparsable)."""
    st = os.stat(path)
    key = (str(path), st.st_size, st.st_mtime_ns)
    cached = _FILE_CACHE.get(key)
    if cached is None and store is not None:
        cached = store.file_digest(str(path))
    if cached is not None:
        _FILE_CACHE[key] = cached
        return cached
    raw = Path(path).read_bytes()
    try:
        tree = _strip_docstrings(ast.parse(raw, filename=str(path)))
        digest = hash_bytes(ast.dump(tree, annotate_fields=False, include_attributes=False).encode())
    except (SyntaxError, ValueError):
        digest = hash_bytes(raw)
    _FILE_CACHE[key] = digest
    if store is not None:
        store.put_file_digest(str(path), st.st_size, st.st_mtime_ns, digest)
    return digest


def _python_files(folder: Path) -> list[Path]:
    found = []
    for current, dirs, files in os.walk(folder):
        dirs[:] = sorted(d for d in dirs if d != "__pycache__" and not d.startswith("."))
        found.extend(Path(current) / f for f in files if f.endswith(".py"))
    return sorted(found)


def locate_module(dotted: str, root: Path | None = None) -> tuple[Path, bool] | None:
    """(path, is_package) of a module's source without importing it: the project root first,
    then ``sys.path``; falls back to ``importlib.util.find_spec`` for anything else."""
    module = sys.modules.get(dotted)
    if module is not None and getattr(module, "__file__", None):
        path = Path(module.__file__)
        return (path.parent, True) if path.name == "__init__.py" else (path, False)
    parts = dotted.split(".")
    bases = ([str(root)] if root is not None else []) + [p for p in sys.path if p]
    for base in bases:
        folder = Path(base, *parts)
        if (folder / "__init__.py").is_file():
            return folder, True
        if folder.with_suffix(".py").is_file():
            return folder.with_suffix(".py"), False
    try:
        spec = importlib.util.find_spec(dotted)
    except (ImportError, ValueError):
        return None
    if spec is None:
        return None
    if spec.submodule_search_locations:
        return Path(list(spec.submodule_search_locations)[0]), True
    if spec.origin and spec.origin.endswith(".py"):
        return Path(spec.origin), False
    return None


def module_files(dotted: str, root: Path | None = None) -> list[Path]:
    """The source files of a module (one file) or a package (every ``.py`` below it)."""
    found = locate_module(dotted, root)
    if found is None:
        raise ConfigError(f"code module '{dotted}' declared in Stage.code cannot be found; fix Stage.code")
    path, is_package = found
    return _python_files(path) if is_package else [path]


def stage_source_files(stage: _Declared, module_name: str, root: Path | None = None) -> list[Path]:
    """The stage's own package (``stages/<pkg>/**/*.py``; just the module file for a top-level
    module) plus every module of ``Stage.code``; sorted, no duplicates."""
    found = locate_module(module_name, root)
    if found is None:
        raise ConfigError(f"stage '{stage.name}': module {module_name} cannot be found")
    path, is_package = found
    if is_package:
        own = _python_files(path)
    elif module_name.count(".") >= 2:
        own = _python_files(path.parent)  # stages.<pkg>.stage: the whole stages/<pkg> package
    else:
        own = [path]
    files = {p.resolve() for p in own}
    for dotted in stage.code:
        files.update(p.resolve() for p in module_files(dotted, root))
    return sorted(files)


def stage_code_digest(stage: _Declared, module_name: str, root: Path, store: _DigestStore | None = None) -> str:
    """Digest over (path relative to the project root, normalised source digest) of every file."""
    cache_key = (stage.name, module_name)
    cached = _STAGE_CACHE.get(cache_key)
    if cached is not None:
        return cached
    lines = []
    for path in stage_source_files(stage, module_name, root):
        try:
            rel = path.relative_to(root).as_posix()
        except ValueError:
            rel = path.as_posix()
        lines.append(f"{rel}\t{normalised_source_digest(path, store)}\n")
    digest = hash_bytes("".join(lines).encode())
    _STAGE_CACHE[cache_key] = digest
    return digest
