"""The compiled kernels' on-disk cache kept in step with every source file they call.

numba invalidates a cached kernel when its own file changes, not when a function it calls from
another file does (a limitation numba documents): after an edit of ``soft_arm_model/lie.py`` the
cached kernels of ``kernels.py``, ``statics.py`` and the controller's would go on running the old
code, and tests would pass on it. :func:`clear_stale` keeps a digest of every source file of the
project's packages beside the cache; where sources no longer match theirs, it deletes the cached
kernels (``.nbi`` index, ``.nbc`` object code) of every module that reaches a changed source
through its imports, directly or through other modules, and of the changed modules themselves;
they recompile on their next call. The kernels of modules that reach no changed source stay: an
edit of a node's shell or of a command-line tool costs no compilation.

What a module imports is read from its source, erring towards compiling again: every ``import``
statement counts (those inside functions too; relative ones resolved, and ``from p import name``
as importing ``p`` and ``p.name``), and so do the ``__init__`` of its own packages, which run
before it; a package whose ``__init__`` resolves names on first use (a
module-level ``__getattr__``, as :mod:`soft_arm_model`'s) counts as importing every module under
it, and any other module that imports by a name built at run time (``importlib.import_module``,
``__import__``) as importing every module of the project. A cached kernel whose source file cannot
be told is deleted, and so is the whole cache when no digest was recorded. ``test/run``'s pytest
runs and ``soft-arm-warmup`` call it before anything compiles.
"""
from __future__ import annotations

import ast
import hashlib
import json
import os
from pathlib import Path

PACKAGES = ("soft_arm_model", "soft_arm_ros", "soft_arm_control", "soft_arm_drivers",
            "soft_arm_experiments")
DIGEST_FILE = "soft_arm_sources.json"
_CACHE_SUFFIXES = (".nbi", ".nbc")
_RUN_TIME_IMPORTS = ("import_module", "__import__")


def package_roots() -> list[Path]:
    """The directories of the project's packages, where this module's package sits."""
    here = Path(__file__).resolve().parent.parent
    return [here / name for name in PACKAGES if (here / name).is_dir()]


def _sources(roots) -> dict[str, Path]:
    """Every ``.py`` file under ``roots`` by its key, ``<root name>/<path under the root>``."""
    out = {}
    for root in roots:
        root = Path(root)
        for path in sorted(root.rglob("*.py")):
            out[f"{root.name}/{path.relative_to(root).as_posix()}"] = path
    return out


def source_digests(roots) -> dict[str, str]:
    """SHA-256 of the contents of every ``.py`` file under ``roots``, by key (:func:`_sources`)."""
    return {key: hashlib.sha256(path.read_bytes()).hexdigest() for key, path in _sources(roots).items()}


def _module_name(key: str) -> str:
    """The dotted name of the module at ``key``: ``pkg/sub/mod.py`` is ``pkg.sub.mod``,
    ``pkg/sub/__init__.py`` is ``pkg.sub``."""
    parts = key[:-len(".py")].split("/")
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imported_names(tree: ast.Module, name: str, is_package: bool) -> set[str]:
    """The dotted names the module ``name`` (a package's ``__init__`` if ``is_package``) may
    import, each with the packages above it."""
    names = set()
    package = name if is_package else name.rpartition(".")[0]
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[:len(base) - (node.level - 1)]
                base = ".".join(base + ([node.module] if node.module else []))
            else:
                base = node.module or ""
            names.add(base)
            names.update(f"{base}.{alias.name}" for alias in node.names)
    with_parents = set()
    for dotted in names:
        parts = dotted.split(".")
        with_parents.update(".".join(parts[:k]) for k in range(1, len(parts) + 1))
    return with_parents


def _imports_at_run_time(tree: ast.Module) -> bool:
    """Whether the module calls ``importlib.import_module`` or ``__import__``."""
    for node in ast.walk(tree):
        if isinstance(node, ast.Call):
            f = node.func
            called = f.attr if isinstance(f, ast.Attribute) else f.id if isinstance(f, ast.Name) else None
            if called in _RUN_TIME_IMPORTS:
                return True
    return False


def _resolves_lazily(tree: ast.Module) -> bool:
    """Whether the module defines a module-level ``__getattr__`` (PEP 562)."""
    return any(isinstance(node, ast.FunctionDef) and node.name == "__getattr__" for node in tree.body)


def dependencies(roots, removed=()) -> dict[str, set[str]]:
    """The project modules each module under ``roots`` imports directly, by key (module docstring:
    what counts), its packages' ``__init__`` among them (they run before it); ``removed``: the keys
    of modules no longer there, that imports may still name."""
    sources = _sources(roots)
    known = set(sources) | set(removed)
    by_name = {_module_name(key): key for key in known}
    out = {}
    for key, path in sources.items():
        tree = ast.parse(path.read_bytes(), filename=str(path))
        is_package = key.endswith("/__init__.py")
        name = _module_name(key)
        if is_package and _resolves_lazily(tree):
            folder = key[:-len("__init__.py")]
            deps = {k for k in known if k.startswith(folder)}
        elif _imports_at_run_time(tree):
            deps = set(known)
        else:
            deps = set()
        parts = name.split(".")
        names = _imported_names(tree, name, is_package) | {".".join(parts[:k]) for k in range(1, len(parts))}
        deps.update(by_name[n] for n in names if n in by_name)
        deps.discard(key)
        out[key] = deps
    return out


def affected(changed, graph: dict[str, set[str]]) -> set[str]:
    """The modules of ``graph`` (:func:`dependencies`) that reach one of ``changed`` (keys) through
    their imports, and ``changed`` themselves."""
    importers = {}
    for key, deps in graph.items():
        for dep in deps:
            importers.setdefault(dep, set()).add(key)
    reached, frontier = set(changed), list(changed)
    while frontier:
        for importer in importers.get(frontier.pop(), ()):
            if importer not in reached:
                reached.add(importer)
                frontier.append(importer)
    return reached


def _cached_kernels(roots, cache_dir: Path | None) -> dict[Path, str | None]:
    """Every cached kernel file with the key of its source module (None: not told). numba names a
    module's kernels ``<module file stem>.<function>-...`` in its directory's ``__pycache__``, or
    with ``NUMBA_CACHE_DIR`` in ``<directory name>_<SHA-1 of its absolute path>`` there."""
    sources = _sources(roots)
    folders = {}                                   # cache folder -> (source folder, its key prefix)
    for key, path in sources.items():
        folder = path.parent
        prefix = key[:len(key) - len(path.name)]
        if cache_dir is None:
            folders[folder / "__pycache__"] = (folder, prefix)
        else:
            absolute = os.path.dirname(os.path.abspath(path))
            hashed = hashlib.sha1(absolute.encode()).hexdigest()
            folders[cache_dir / f"{os.path.basename(absolute)}_{hashed}"] = (folder, prefix)
    if cache_dir is not None:
        candidates = cache_dir.rglob("*") if cache_dir.is_dir() else ()
    else:
        candidates = (p for root in roots for p in Path(root).rglob("__pycache__/*"))
    out = {}
    for path in candidates:
        if path.suffix not in _CACHE_SUFFIXES or not path.is_file():
            continue
        folder = folders.get(path.parent)
        key = None if folder is None else folder[1] + path.name.split(".", 1)[0] + ".py"
        out[path] = key if key in sources else None
    return out


def _recorded(stamp: Path) -> dict | None:
    """The digests recorded at ``stamp``, None where there are none (no file, or not of this kind)."""
    try:
        recorded = json.loads(stamp.read_text())
    except (OSError, ValueError):
        return None
    return recorded if isinstance(recorded, dict) else None


def clear_stale(roots=None, cache_dir: str | os.PathLike | None = None) -> int:
    """Delete the cached kernels of ``roots`` (default: the project's packages) that sources
    changed since the digests were last recorded may have made stale (module docstring), all of
    them when none were recorded; record the current digests. The cache is ``cache_dir``, else
    ``NUMBA_CACHE_DIR`` if set, else the packages' ``__pycache__`` directories (numba's default).
    Returns the number of files deleted."""
    roots = package_roots() if roots is None else [Path(r) for r in roots]
    if cache_dir is None and os.environ.get("NUMBA_CACHE_DIR"):
        cache_dir = os.environ["NUMBA_CACHE_DIR"]
    cache = Path(cache_dir) if cache_dir is not None else None
    stamp = (cache if cache is not None else roots[0] / "__pycache__") / DIGEST_FILE
    current = source_digests(roots)
    recorded = _recorded(stamp)
    if recorded == current:
        return 0
    stale = None
    if recorded is not None:
        changed = {k for k in current.keys() | recorded.keys() if current.get(k) != recorded.get(k)}
        stale = affected(changed, dependencies(roots, recorded.keys() - current.keys()))
    removed = 0
    for path, source in _cached_kernels(roots, cache).items():
        if stale is not None and source is not None and source not in stale:
            continue
        try:
            path.unlink()
            removed += 1
        except FileNotFoundError:
            pass
    stamp.parent.mkdir(parents=True, exist_ok=True)
    stamp.write_text(json.dumps(current, indent=0, sort_keys=True) + "\n")
    return removed
