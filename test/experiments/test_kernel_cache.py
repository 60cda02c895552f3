"""The kernel cache is cleared when any source changed, and only then."""
from soft_arm_experiments.kernel_cache import DIGEST_FILE, clear_stale, package_roots, sources_digest


def _tree(tmp_path):
    """Two packages, each with a source file and a cached kernel beside it."""
    roots = []
    for name in ("pkg_a", "pkg_b"):
        root = tmp_path / name
        (root / "__pycache__").mkdir(parents=True)
        (root / "mod.py").write_text(f"X = '{name}'\n")
        (root / "__pycache__" / "mod.f-10.py311.nbi").write_bytes(b"index")
        (root / "__pycache__" / "mod.f-10.py311.1.nbc").write_bytes(b"code")
        (root / "__pycache__" / "mod.cpython-311.pyc").write_bytes(b"bytecode")
        roots.append(root)
    return roots


def _cached(roots):
    return sorted(p.name for r in roots for p in (r / "__pycache__").iterdir()
                  if p.suffix in (".nbi", ".nbc"))


def test_a_cache_of_unknown_sources_is_cleared_then_kept_until_any_file_changes(tmp_path):
    roots = _tree(tmp_path)
    assert clear_stale(roots) == 4                       # no digest yet: provenance unknown
    assert _cached(roots) == [] and (roots[0] / "__pycache__" / "mod.cpython-311.pyc").exists()
    for r in roots:                                      # the kernels compile again
        (r / "__pycache__" / "mod.f-10.py311.nbi").write_bytes(b"index")
    assert clear_stale(roots) == 0 and len(_cached(roots)) == 2
    (roots[1] / "mod.py").write_text("X = 'edited'\n")   # an edit in the other package ...
    assert clear_stale(roots) == 2 and _cached(roots) == []   # ... clears both packages' kernels
    (roots[1] / "new.py").write_text("Y = 1\n")          # a new file counts too
    assert sources_digest(roots) != (roots[0] / "__pycache__" / DIGEST_FILE).read_text().strip()


def test_numba_cache_dir_is_where_the_kernels_and_the_digest_are(tmp_path, monkeypatch):
    roots = _tree(tmp_path)
    cache = tmp_path / "numba-cache"
    (cache / "x" / "y").mkdir(parents=True)
    (cache / "x" / "y" / "mod.f-10.py311.nbi").write_bytes(b"index")
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(cache))
    assert clear_stale(roots) == 1                       # the cache dir's, not __pycache__'s
    assert len(_cached(roots)) == 4 and (cache / DIGEST_FILE).is_file()
    assert clear_stale(roots) == 0


def test_the_project_packages_are_the_roots():
    names = [r.name for r in package_roots()]
    assert names[0] == "soft_arm_model" and "soft_arm_control" in names and "soft_arm_drivers" in names
