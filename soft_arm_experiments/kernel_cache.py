"""The compiled kernels' on-disk cache kept in step with every source file they call.

numba invalidates a cached kernel when its own file changes, not when a function it calls from
another file does (a limitation numba documents): after an edit of ``soft_arm_model/lie.py`` the
cached kernels of ``kernels.py``, ``statics.py`` and the controller's would go on running the old
code, and tests would pass on it. :func:`clear_stale` keeps a digest of every source file of the
project's packages beside the cache; where sources no longer match theirs, it deletes the cached
kernels (``.nbi`` index, ``.nbc`` object code) of every module that reaches a changed source
through its imports, directly or through other modules, and of the changed modules themselves;
they recompile on their next call. A kernel file older than a source its module reaches goes too:
the digests say what changed since the last check, the times what a kernel may have been compiled
on in between (an edit put back after a process compiled on it). The kernels of modules that
reach no changed source stay: an edit of a node's shell or of a command-line tool costs no
compilation.

What a module imports is read from its source, erring towards compiling again: every ``import``
statement counts (those inside functions too; relative ones resolved, and ``from p import name``
as importing ``p`` and ``p.name``), and so do the ``__init__`` of its own packages, which run
before it; a package whose ``__init__`` resolves names on first use (a module-level
``__getattr__``, as :mod:`soft_arm_model`'s) or a module that imports a relative name given at run
time counts as importing every module under its package, and a module that imports any other name
given at run time (``importlib.import_module``, ``__import__``), or whose source does not parse,
as importing every module of the project. A cached kernel whose source file cannot be told is
deleted, and so is the whole cache when no digest was recorded. ``test/run``'s pytest runs and
``soft-arm-warmup`` call it before anything compiles.
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
_IMPORT_FIELDS = {"names", "within", "by_name"}          # of a module's imports (module_imports)


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


def _module_name(key: str) -> str:
    """The dotted name of the module at ``key``: ``pkg/sub/mod.py`` is ``pkg.sub.mod``,
    ``pkg/sub/__init__.py`` is ``pkg.sub``."""
    parts = key[:-len(".py")].split("/")
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def module_imports(path, key: str) -> dict:
    """What the module at ``path`` (its key ``key``) imports, read from its source: ``names``, the
    dotted names its ``import`` statements may import (those inside functions too, relative ones
    resolved, each with the packages above it), ``within`` (it may import any module of its own
    package: a package ``__init__`` with a module-level ``__getattr__``, or a module calling
    ``importlib.import_module`` on a relative name) and ``by_name`` (it may import any module: it
    calls ``import_module`` on another name or ``__import__``, or its source cannot be read)."""
    try:
        tree = ast.parse(Path(path).read_bytes(), filename=str(path))
    except (SyntaxError, ValueError, OSError):
        return {"names": [], "within": False, "by_name": True}
    is_package = key.endswith("/__init__.py")
    name = _module_name(key)
    package = name if is_package else name.rpartition(".")[0]
    names, within, by_name = set(), False, False
    aliases = _import_aliases(tree)
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
        elif isinstance(node, ast.Call) and _calls_an_import(node, aliases):
            relative = node.args and _starts_with_a_dot(node.args[0])
            within |= bool(relative)
            by_name |= not relative
    with_parents = set()
    for dotted in names:
        parts = dotted.split(".")
        with_parents.update(".".join(parts[:k]) for k in range(1, len(parts) + 1))
    within |= is_package and any(isinstance(node, ast.FunctionDef) and node.name == "__getattr__"
                                 for node in tree.body)
    return {"names": sorted(with_parents), "within": within, "by_name": by_name}


def _import_aliases(tree: ast.Module) -> set[str]:
    """The names that call an import in the module: ``__import__``, ``import_module`` and what
    ``from importlib import import_module as ...`` binds."""
    aliases = {"import_module", "__import__"}
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module == "importlib":
            aliases.update(a.asname or a.name for a in node.names if a.name == "import_module")
    return aliases


def _calls_an_import(call: ast.Call, aliases: set[str]) -> bool:
    """Whether ``call`` is ``importlib.import_module``, ``__import__`` or one of ``aliases``."""
    f = call.func
    if isinstance(f, ast.Attribute):
        return f.attr in _RUN_TIME_IMPORTS
    return isinstance(f, ast.Name) and f.id in aliases


def _starts_with_a_dot(arg: ast.expr) -> bool:
    """Whether the module name ``arg`` is a relative one: a string, or an f-string whose text
    starts with a dot."""
    if isinstance(arg, ast.JoinedStr) and arg.values:
        arg = arg.values[0]
    return isinstance(arg, ast.Constant) and isinstance(arg.value, str) and arg.value.startswith(".")


def import_graph(imports: dict, removed=()) -> dict[str, set[str]]:
    """The project modules each module imports directly, by key, from their :func:`module_imports`
    (``imports``, by key); its packages' ``__init__`` count (they run before it). ``removed``: the
    keys of modules no longer there, that imports may still name."""
    known = set(imports) | set(removed)
    by_name = {_module_name(key): key for key in known}
    out = {}
    for key, info in imports.items():
        deps = set(known) if info["by_name"] else set()
        if info["within"]:
            folder = key.rpartition("/")[0] + "/"
            deps.update(k for k in known if k.startswith(folder))
        parts = _module_name(key).split(".")
        names = set(info["names"]) | {".".join(parts[:k]) for k in range(1, len(parts))}
        deps.update(by_name[n] for n in names if n in by_name)
        deps.discard(key)
        out[key] = deps
    return out


def dependencies(roots, removed=()) -> dict[str, set[str]]:
    """:func:`import_graph` of every module under ``roots``, each read from its source."""
    return import_graph({key: module_imports(path, key) for key, path in _sources(roots).items()}, removed)


def affected(changed, graph: dict[str, set[str]]) -> set[str]:
    """The modules of ``graph`` (:func:`dependencies`) that reach one of ``changed`` (keys) through
    their imports, and ``changed`` themselves."""
    importers = {}
    for key, deps in graph.items():
        for dep in deps:
            importers.setdefault(dep, set()).add(key)
    return _reached(changed, importers)


def _reached(starts, edges: dict[str, set[str]]) -> set[str]:
    """``starts`` and every key that ``edges`` (key -> keys) lead to from them."""
    reached, frontier = set(starts), list(starts)
    while frontier:
        for key in edges.get(frontier.pop(), ()):
            if key not in reached:
                reached.add(key)
                frontier.append(key)
    return reached


def _cached_kernels(roots, sources: dict[str, Path], cache_dir: Path | None) -> dict[Path, str | None]:
    """Every cached kernel file with the key of its source module (None: not told). numba names a
    module's kernels ``<module file stem>.<function>-...`` in its directory's ``__pycache__``, or
    with ``NUMBA_CACHE_DIR`` in ``<directory name>_<SHA-1 of its absolute path>`` there (``sources``:
    :func:`_sources` of ``roots``)."""
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
    """What ``stamp`` records (``sources``: the digests by key; ``imports``: each source's
    :func:`module_imports`), None where it records nothing of this kind."""
    try:
        recorded = json.loads(stamp.read_text())
    except (OSError, ValueError):
        return None
    ok = isinstance(recorded, dict) and isinstance(recorded.get("sources"), dict) \
        and isinstance(recorded.get("imports"), dict)
    return recorded if ok else None


def clear_stale(roots=None, cache_dir: str | os.PathLike | None = None) -> int:
    """Delete the cached kernels of ``roots`` (default: the project's packages) that may run code
    older than their sources, and record the sources' digests. A kernel file goes when its module
    reaches a source whose digest changed since the last record (module docstring), or a source
    written after the kernel file was (an edit put back, or one a process compiled on without
    this check; a touched file counts too), or when its source cannot be told; every one goes when
    nothing was recorded. The cache is ``cache_dir``, else ``NUMBA_CACHE_DIR`` if set, else the
    packages' ``__pycache__`` directories (numba's default). Returns the number of files deleted."""
    roots = package_roots() if roots is None else [Path(r) for r in roots]
    if cache_dir is None and os.environ.get("NUMBA_CACHE_DIR"):
        cache_dir = os.environ["NUMBA_CACHE_DIR"]
    cache = Path(cache_dir) if cache_dir is not None else None
    stamp = (cache if cache is not None else roots[0] / "__pycache__") / DIGEST_FILE
    sources = _sources(roots)
    current = {key: hashlib.sha256(path.read_bytes()).hexdigest() for key, path in sources.items()}
    recorded = _recorded(stamp)
    known = recorded["imports"] if recorded is not None else {}
    unchanged = recorded is not None and recorded["sources"] == current
    imports = {key: known[key] if recorded is not None and recorded["sources"].get(key) == digest
               and isinstance(known.get(key), dict) and known[key].keys() == _IMPORT_FIELDS
               else module_imports(sources[key], key) for key, digest in current.items()}
    stale = None
    if recorded is not None:
        removed = recorded["sources"].keys() - current.keys()
        graph = import_graph(imports, removed)
        changed = {k for k in current.keys() | recorded["sources"].keys()
                   if current.get(k) != recorded["sources"].get(k)}
        stale = affected(changed, graph)
    written = {key: path.stat().st_mtime_ns for key, path in sources.items()}
    newest = {}
    removed_files = 0
    for path, source in _cached_kernels(roots, sources, cache).items():
        if stale is not None and source is not None and source not in stale:
            if source not in newest:
                newest[source] = max(written[k] for k in _reached({source}, graph) if k in written)
            try:
                if path.stat().st_mtime_ns >= newest[source]:
                    continue
            except FileNotFoundError:
                continue
        try:
            path.unlink()
            removed_files += 1
        except FileNotFoundError:
            pass
    if not unchanged:
        stamp.parent.mkdir(parents=True, exist_ok=True)
        partial = stamp.with_name(f"{stamp.name}.{os.getpid()}")
        partial.write_text(json.dumps({"sources": current, "imports": imports}, sort_keys=True) + "\n")
        os.replace(partial, stamp)            # a reader sees the old record or the new, never half
    return removed_files
