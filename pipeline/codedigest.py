"""The code digest of a stage: its own package plus every project module it imports, transitively.

What a stage's results depend on is found from the source, without importing anything (so
``pipeline status`` need not import torch):

- **Imports.** Each project file is parsed with ``ast``; every ``import`` and ``from ... import``
  counts, wherever it stands (inside functions too), and so does ``importlib.import_module``
  with a literal name. A dotted import also runs each parent package's ``__init__.py``, so
  those count as well. Following these edges from the stage's own package gives its closure.
- **Files that are not imports.** A module that loads a non-Python file (a C++ source it
  compiles, a weights file, a face model) declares it once, beside the code that loads it, in a
  module-level ``CODE_FILES`` tuple of string literals, paths relative to the module's folder
  (a folder counts with every file below it)::

      CODE_FILES = ("raymarch_fused.cpp",)
      SOURCE = Path(__file__).with_name(CODE_FILES[0])

  Every module that imports it then depends on those files too.
- ``Stage.code`` remains for what neither can show (a module run by name in a subprocess
  outside the stage's package, say).

Each Python file counts by its syntax tree without docstrings (comments and layout never reach
the tree), so comment-only and whitespace-only edits change nothing, while any change to what the
code does changes the digest; other files count by their bytes. A stage's code version keeps the
digest of every file it covers (``CodeVersion.files``), so ``pipeline status`` can name the file
that changed. Per-file scans and digests are cached per process and, through the declaration
cache, across processes by file stat.
"""

from __future__ import annotations

import ast
import importlib.util
import os
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterable, Protocol, Sequence

from pipeline.errors import ConfigError
from pipeline.hashing import hash_bytes, hash_file

# The module-level name under which a module declares the non-Python files it loads.
CODE_FILES_NAME = "CODE_FILES"

_FILE_CACHE: dict[tuple[str, int, int], str] = {}
_SCAN_CACHE: dict[tuple[str, int, int], "FileScan"] = {}
_STAGE_CACHE: dict[tuple[str, str, str], "CodeVersion"] = {}
_RESOLVED: dict[str, dict[str, tuple[Path | None, tuple[Path, ...]]]] = {}
_NEXT: dict[str, dict[tuple[Path, "FileScan"], tuple[Path, ...]]] = {}
_ROOT_FILES: dict[tuple[str, str, tuple[str, ...]], list[Path]] = {}


class _Declared(Protocol):
    name: str
    code: tuple[str, ...]


class _DigestStore(Protocol):
    def file_digest(self, path: str) -> str | None: ...

    def put_file_digest(self, path: str, size: int, mtime_ns: int, digest: str) -> None: ...

    def file_scan(self, path: str) -> tuple[list[str], list[str]] | None: ...

    def put_file_scan(self, path: str, size: int, mtime_ns: int, imports: list[str],
                      code_files: list[str]) -> None: ...


def _strip_docstrings(tree: ast.AST) -> ast.AST:
    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)):
            body = node.body
            if body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant) \
                    and isinstance(body[0].value.value, str):
                node.body = body[1:] or [ast.Pass()]
    return tree


def _python_meaning(path: Path | str) -> str:
    raw = Path(path).read_bytes()
    try:
        tree = _strip_docstrings(ast.parse(raw, filename=str(path)))
        return hash_bytes(ast.dump(tree, annotate_fields=False, include_attributes=False).encode())
    except (SyntaxError, ValueError):
        return hash_bytes(raw)


def _cached_digest(path: Path | str, store: _DigestStore | None, compute: Callable[[Path | str], str]) -> str:
    """``compute(path)``, cached per process and in ``store`` by the file's (path, size, mtime)."""
    st = os.stat(path)
    key = (str(path), st.st_size, st.st_mtime_ns)
    cached = _FILE_CACHE.get(key)
    if cached is None and store is not None:
        cached = store.file_digest(str(path))
    if cached is None:
        cached = compute(path)
        if store is not None:
            store.put_file_digest(str(path), st.st_size, st.st_mtime_ns, cached)
    _FILE_CACHE[key] = cached
    return cached


def normalised_source_digest(path: Path | str, store: _DigestStore | None = None) -> str:
    """Digest of a Python file's meaning: its AST without docstrings (raw bytes if unparsable)."""
    return _cached_digest(path, store, _python_meaning)


def data_file_digest(path: Path | str, store: _DigestStore | None = None) -> str:
    """Digest of a non-Python file's bytes (cached by stat like the source digests)."""
    return _cached_digest(path, store, hash_file)


def _python_files(folder: Path) -> list[Path]:
    found = []
    for current, dirs, files in os.walk(folder):
        dirs[:] = sorted(d for d in dirs if d != "__pycache__" and not d.startswith("."))
        found.extend(Path(current) / f for f in files if f.endswith(".py"))
    return sorted(found)


def locate_module(dotted: str, root: Path | None = None) -> tuple[Path, bool] | None:
    """(path, is_package) of a module's source without importing it: the project root first,
    then ``sys.path``; falls back to ``importlib.util.find_spec`` for anything else."""
    parts = dotted.split(".")
    if root is not None:  # the project's own copy first, whatever this process imported
        folder = Path(root, *parts)
        if (folder / "__init__.py").is_file():
            return folder, True
        if folder.with_suffix(".py").is_file():
            return folder.with_suffix(".py"), False
    module = sys.modules.get(dotted)
    if module is not None and getattr(module, "__file__", None):
        path = Path(module.__file__)
        return (path.parent, True) if path.name == "__init__.py" else (path, False)
    for base in [p for p in sys.path if p]:
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


@dataclass(frozen=True)
class FileScan:
    """What a Python file's syntax tree says it depends on.

    ``imports``: absolute dotted names, one per imported name (``from a import b`` gives
    ``a.b``: a submodule if there is one, else a name in ``a``), wherever the import stands.
    ``code_files``: its ``CODE_FILES`` declaration, paths relative to the file's folder.
    """

    imports: tuple[str, ...]
    code_files: tuple[str, ...]


def _module_name(path: Path, root: Path) -> tuple[str, bool]:
    """(dotted name, is_package) of a project file."""
    rel = path.relative_to(root).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        return ".".join(parts[:-1]), True
    return ".".join(parts), False


def _declared_files(node: ast.stmt, path: Path) -> tuple[str, ...] | None:
    """The literal paths of a module-level ``CODE_FILES = (...)``, None for any other statement."""
    if isinstance(node, ast.Assign):
        targets, value = node.targets, node.value
    elif isinstance(node, ast.AnnAssign) and node.value is not None:
        targets, value = [node.target], node.value
    else:
        return None
    if not any(isinstance(t, ast.Name) and t.id == CODE_FILES_NAME for t in targets):
        return None
    if not isinstance(value, (ast.Tuple, ast.List)) or not all(
            isinstance(e, ast.Constant) and isinstance(e.value, str) for e in value.elts):
        raise ConfigError(f"{path}:{node.lineno}: {CODE_FILES_NAME} must be a tuple of string literals "
                          f"(paths relative to the module's folder), so that it can be read without "
                          f"importing the module")
    return tuple(e.value for e in value.elts)


def scan_source(source: bytes, path: Path, module: str, is_package: bool) -> FileScan:
    """The imports and declared files of one Python file (``module``: its dotted name)."""
    try:
        tree = ast.parse(source, filename=str(path))
    except (SyntaxError, ValueError):
        return FileScan((), ())  # its digest still changes with every edit; it cannot import anything
    package = module if is_package else module.rpartition(".")[0]
    imports: list[str] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            imports.extend(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base_parts = package.split(".") if package else []
                if node.level > 1:
                    base_parts = base_parts[:len(base_parts) - (node.level - 1)]
                base = ".".join(base_parts + ([node.module] if node.module else []))
            else:
                base = node.module or ""
            if not base:
                continue
            # ``from a import b`` names ``a.b``: the submodule if there is one, else ``a`` itself
            # (resolution takes the deepest module that exists); ``a``'s ``__init__`` runs either way.
            for alias in node.names:
                imports.append(base if alias.name == "*" else f"{base}.{alias.name}")
        elif isinstance(node, ast.Call) and node.args and isinstance(node.args[0], ast.Constant) \
                and isinstance(node.args[0].value, str):
            func = node.func
            name = func.attr if isinstance(func, ast.Attribute) else getattr(func, "id", None)
            if name == "import_module":
                imports.append(node.args[0].value)
    declared: tuple[str, ...] = ()
    for node in tree.body:
        found = _declared_files(node, path)
        if found is not None:
            declared = found
    return FileScan(tuple(dict.fromkeys(imports)), declared)


@dataclass(frozen=True)
class CodeVersion:
    """The code a stage (or a cache) depends on: one digest, and each file's (path relative to
    the project root -> digest) so a change can be named."""

    digest: str
    files: dict[str, str]


def changed_files(old: dict[str, str], new: dict[str, str]) -> list[str]:
    """The files whose digest differs between two ``CodeVersion.files`` (added and removed ones too)."""
    lines = []
    for rel in sorted(set(old) | set(new)):
        if rel not in old:
            lines.append(f"{rel} (new)")
        elif rel not in new:
            lines.append(f"{rel} (no longer used)")
        elif old[rel] != new[rel]:
            lines.append(rel)
    return lines


class SourceGraph:
    """The import graph of the project under ``root``, read from source files only.

    A module is a project module when its file lives under ``root`` (``a/b.py`` or
    ``a/b/__init__.py``; folders without ``__init__.py`` are namespace packages); anything else
    (the standard library, torch, ...) is outside the graph.
    """

    def __init__(self, root: Path, store: _DigestStore | None = None) -> None:
        self.root = Path(root).resolve()
        self.store = store
        # Which file a dotted name reaches depends only on which files exist: shared by every
        # graph of this root in the process (``forget_cached_versions`` drops it).
        self._resolved = _RESOLVED.setdefault(str(self.root), {})
        self._next = _NEXT.setdefault(str(self.root), {})

    # -- modules and files ----------------------------------------------------------------

    def _resolve(self, dotted: str) -> tuple[Path | None, tuple[Path, ...]]:
        """(the deepest project file the name reaches, the parent ``__init__.py`` files run on the way)."""
        hit = self._resolved.get(dotted)
        if hit is not None:
            return hit
        parts = dotted.split(".")
        target: str | None = None
        inits: list[str] = []
        folder = str(self.root)
        isfile, isdir, join = os.path.isfile, os.path.isdir, os.path.join
        for i, part in enumerate(parts):
            if not part.isidentifier():
                break
            package = join(folder, part)
            if isfile(join(package, "__init__.py")):
                target = join(package, "__init__.py")
                inits.append(target)
                folder = package
            elif isfile(package + ".py"):
                target = package + ".py"
                break
            elif i < len(parts) - 1 and isdir(package):
                folder = package  # a namespace package: nothing runs, look further down
            else:
                break
        if target is not None and target.endswith("__init__.py"):
            inits = inits[:-1]
        result = (Path(target) if target is not None else None, tuple(Path(p) for p in inits))
        self._resolved[dotted] = result
        return result

    def module_file(self, dotted: str) -> Path | None:
        """The project file of a module (``a/b.py`` or ``a/b/__init__.py``), None outside the project."""
        target, _ = self._resolve(dotted)
        if target is None:
            return None
        name, _ = _module_name(target, self.root)
        return target if name == dotted else None

    def relpath(self, path: Path) -> str:
        """A file's path relative to the project root, ``/``-separated."""
        return path.relative_to(self.root).as_posix()

    def scan(self, path: Path) -> FileScan:
        """The imports and declared files of one project file (cached by stat)."""
        st = os.stat(path)
        key = (str(path), st.st_size, st.st_mtime_ns)
        cached = _SCAN_CACHE.get(key)
        if cached is None and self.store is not None:
            stored = self.store.file_scan(str(path))
            if stored is not None:
                cached = FileScan(tuple(stored[0]), tuple(stored[1]))
        if cached is None:
            module, is_package = _module_name(path, self.root)
            cached = scan_source(path.read_bytes(), path, module, is_package)
            if self.store is not None:
                self.store.put_file_scan(str(path), st.st_size, st.st_mtime_ns, list(cached.imports),
                                         list(cached.code_files))
        _SCAN_CACHE[key] = cached
        return cached

    def imported_files(self, path: Path) -> list[Path]:
        """The project files one file's imports name directly (the deepest module of each; no
        parent packages), for the import graph."""
        found: dict[Path, None] = {}
        for dotted in self.scan(path).imports:
            target, _ = self._resolve(dotted)
            if target is not None and target != path:
                found[target] = None
        return list(found)

    def declared_files(self, path: Path) -> list[Path]:
        """The non-Python files a module declares in ``CODE_FILES`` (folders expanded), checked to exist."""
        files: list[Path] = []
        for rel in self.scan(path).code_files:
            target = (path.parent / rel).resolve()
            if target != self.root and self.root not in target.parents:
                raise ConfigError(f"{path}: {CODE_FILES_NAME} entry '{rel}' is outside the project "
                                  f"{self.root}; declare only files that ship with the project")
            if target.is_dir():
                files.extend(sorted(p for p in target.rglob("*") if p.is_file() and "__pycache__" not in p.parts))
            elif target.is_file():
                files.append(target)
            else:
                raise ConfigError(f"{path}: {CODE_FILES_NAME} entry '{rel}' does not exist ({target}); "
                                  f"fix the declaration or restore the file")
        return files

    def closure(self, roots: Iterable[Path]) -> list[Path]:
        """Every project file reachable from ``roots`` through imports (with the parent packages'
        ``__init__.py``) and the files those modules declare; sorted."""
        todo = [Path(p) if Path(p).is_absolute() else Path(p).resolve() for p in roots]
        seen: set[Path] = set()
        data: set[Path] = set()
        while todo:
            path = todo.pop()
            if path in seen:
                continue
            seen.add(path)
            scan = self.scan(path)
            todo.extend(self._next_files(path, scan))
            if scan.code_files:
                data.update(self.declared_files(path))
        return sorted(seen | data)

    def _next_files(self, path: Path, scan: FileScan) -> tuple[Path, ...]:
        """The files running ``path`` runs next: its parent packages' ``__init__.py`` and, for each
        import, the module's file and its parents' (memoised per scan of the file)."""
        key = (path, scan)
        hit = self._next.get(key)
        if hit is not None:
            return hit
        module, _ = _module_name(path, self.root)
        found: list[Path] = list(self._resolve(module)[1])
        for dotted in scan.imports:
            target, inits = self._resolve(dotted)
            found.extend(inits)
            if target is not None:
                found.append(target)
        result = tuple(dict.fromkeys(found))
        self._next[key] = result
        return result

    def version(self, files: Iterable[Path]) -> CodeVersion:
        """The ``CodeVersion`` of a set of files (Python by normalised syntax tree, others by bytes)."""
        digests = {}
        for path in sorted(files):
            rel = self.relpath(path)
            digests[rel] = (normalised_source_digest(path, self.store) if path.suffix == ".py"
                            else data_file_digest(path, self.store))
        lines = "".join(f"{rel}\t{digest}\n" for rel, digest in digests.items())
        return CodeVersion(hash_bytes(lines.encode()), digests)


def _own_files(module_name: str, root: Path, name: str) -> list[Path]:
    found = locate_module(module_name, root)
    if found is None:
        raise ConfigError(f"stage '{name}': module {module_name} cannot be found")
    path, is_package = found
    if is_package:
        return _python_files(path)
    if module_name.count(".") >= 2:
        return _python_files(path.parent)  # stages.<pkg>.stage: the whole stages/<pkg> package
    return [path]


def stage_source_files(stage: _Declared, module_name: str, root: Path,
                       store: _DigestStore | None = None) -> list[Path]:
    """The files a stage's code digest covers: its own package (``stages/<pkg>/**/*.py``; just the
    module file for a top-level module), every ``Stage.code`` module, and everything they import
    or declare, transitively; sorted, no duplicates."""
    graph = SourceGraph(root, store)
    key = (str(graph.root), module_name, tuple(stage.code))
    roots = _ROOT_FILES.get(key)
    if roots is None:
        roots = [p.resolve() for p in _own_files(module_name, graph.root, stage.name)]
        for dotted in stage.code:
            roots.extend(p.resolve() for p in module_files(dotted, graph.root))
        _ROOT_FILES[key] = roots
    return graph.closure(roots)


def stage_code_version(stage: _Declared, module_name: str, root: Path,
                       store: _DigestStore | None = None) -> CodeVersion:
    """The stage's ``CodeVersion`` over ``stage_source_files`` (cached per process)."""
    cache_key = (str(root), stage.name, module_name)
    cached = _STAGE_CACHE.get(cache_key)
    if cached is not None:
        return cached
    graph = SourceGraph(root, store)
    version = graph.version(stage_source_files(stage, module_name, root, store))
    _STAGE_CACHE[cache_key] = version
    return version


def stage_code_digest(stage: _Declared, module_name: str, root: Path, store: _DigestStore | None = None) -> str:
    """The stage's code digest (``stage_code_version(...).digest``)."""
    return stage_code_version(stage, module_name, root, store).digest


def forget_cached_versions(*, resolutions: bool = True, files: bool = False) -> None:
    """Drop this process's per-stage code versions (files edited while the process runs) and,
    unless ``resolutions`` is False, which file each module name reaches (files added or removed).
    With ``files``, also every file's digest and import scan: the next version is computed as a new
    process would, from the files alone (a cold start, to time against)."""
    _STAGE_CACHE.clear()
    if files:
        _FILE_CACHE.clear()
        _SCAN_CACHE.clear()
    if resolutions:
        _RESOLVED.clear()
        _NEXT.clear()
        _ROOT_FILES.clear()


def _root_of(dotted: str) -> tuple[Path, Path] | None:
    """(project root, module file) of an importable module, from where its file lies."""
    found = locate_module(dotted)
    if found is None:
        return None
    path, is_package = found
    file = path / "__init__.py" if is_package else path
    if not file.is_file():
        return None
    depth = dotted.count(".") + (1 if is_package else 0)
    root = file.resolve().parent
    for _ in range(depth):
        root = root.parent
    return root, file.resolve()


def modules_code_version(modules: Sequence[str]) -> CodeVersion | None:
    """The ``CodeVersion`` of the import closure of some modules (for caches keyed on code: the
    per-item caches, checkpoints, trained models); None when none of them has a source file.

    Each module's project root is where its file lies (``a/b/c.py`` of ``a.b.c`` -> the folder
    holding ``a``); modules from several roots (a test's helper module beside the project's)
    are followed each in its own root.
    """
    roots_by_project: dict[Path, list[Path]] = {}
    for dotted in modules:
        if dotted == "__main__":
            continue
        found = _root_of(dotted)
        if found is None:
            continue
        root, file = found
        files = roots_by_project.setdefault(root, [])
        if file.name == "__init__.py":
            files.extend(p.resolve() for p in _python_files(file.parent))
        else:
            files.append(file)
    if not roots_by_project:
        return None
    versions = []
    for root, files in roots_by_project.items():
        graph = SourceGraph(root)
        versions.append((root, graph.version(graph.closure(files))))
    if len(versions) == 1:
        return versions[0][1]
    digests = {f"{root}:{rel}": digest for root, version in versions for rel, digest in version.files.items()}
    return CodeVersion(hash_bytes("".join(f"{k}\t{v}\n" for k, v in sorted(digests.items())).encode()), digests)
