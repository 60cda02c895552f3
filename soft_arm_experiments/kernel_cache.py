"""The compiled kernels' on-disk cache kept in step with every source file they call.

numba invalidates a cached kernel when its own file changes, not when a function it calls from
another file does (a limitation numba documents): after an edit of ``soft_arm_model/lie.py`` the
cached kernels of ``kernels.py``, ``statics.py`` and the controller's would go on running the old
code, and tests would pass on it. :func:`clear_stale` keeps one digest of every source file of the
project's packages beside the cache; when the sources no longer match it, every cached kernel
(``.nbi`` index, ``.nbc`` object code) is deleted and recompiles on its next call. ``test/run``'s
pytest run and ``soft-arm-warmup`` call it before anything compiles.
"""
from __future__ import annotations

import hashlib
import os
from pathlib import Path

PACKAGES = ("soft_arm_model", "soft_arm_ros", "soft_arm_control", "soft_arm_drivers",
            "soft_arm_experiments")
DIGEST_FILE = "soft_arm_sources.sha256"
_CACHE_SUFFIXES = (".nbi", ".nbc")


def package_roots() -> list[Path]:
    """The directories of the project's packages, where this module's package sits."""
    here = Path(__file__).resolve().parent.parent
    return [here / name for name in PACKAGES if (here / name).is_dir()]


def sources_digest(roots) -> str:
    """SHA-256 of every ``.py`` file under ``roots`` (paths relative to their root, and contents)."""
    digest = hashlib.sha256()
    for root in roots:
        root = Path(root)
        for path in sorted(root.rglob("*.py")):
            digest.update(f"{root.name}/{path.relative_to(root).as_posix()}\0".encode())
            digest.update(path.read_bytes())
            digest.update(b"\0")
    return digest.hexdigest()


def _cached_kernels(roots, cache_dir: Path | None):
    if cache_dir is not None:
        candidates = cache_dir.rglob("*") if cache_dir.is_dir() else ()
    else:
        candidates = (p for root in roots for p in Path(root).rglob("__pycache__/*"))
    return [p for p in candidates if p.suffix in _CACHE_SUFFIXES and p.is_file()]


def clear_stale(roots=None, cache_dir: str | os.PathLike | None = None) -> int:
    """Delete every cached kernel of ``roots`` (default: the project's packages) unless the digest
    of their sources equals the one recorded when the cache was last cleared; record the current
    one. The cache is ``cache_dir``, else ``NUMBA_CACHE_DIR`` if set, else the packages'
    ``__pycache__`` directories (numba's default). Returns the number of files deleted."""
    roots = package_roots() if roots is None else [Path(r) for r in roots]
    if cache_dir is None and os.environ.get("NUMBA_CACHE_DIR"):
        cache_dir = os.environ["NUMBA_CACHE_DIR"]
    cache = Path(cache_dir) if cache_dir is not None else None
    stamp = (cache if cache is not None else roots[0] / "__pycache__") / DIGEST_FILE
    current = sources_digest(roots)
    if stamp.is_file() and stamp.read_text().strip() == current:
        return 0
    removed = 0
    for path in _cached_kernels(roots, cache):
        try:
            path.unlink()
            removed += 1
        except FileNotFoundError:
            pass
    stamp.parent.mkdir(parents=True, exist_ok=True)
    stamp.write_text(current + "\n")
    return removed
