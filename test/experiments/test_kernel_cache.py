"""The kernel cache: a module's cached kernels are deleted when a source it reaches through its
imports changed, and only then; the project's own imports are read as they are."""
import hashlib
import os

import pytest

from soft_arm_experiments.kernel_cache import (DIGEST_FILE, _sources, affected, clear_stale, dependencies,
                                               package_roots)

# a package of four modules: `low` is imported by `mid` (relatively, inside a function), `mid` by
# `top` (absolutely); `alone` imports nothing of the project; `lazy`'s __init__ resolves names on
# first use; pkg_b's `user` imports pkg_a's `top` by `from pkg_a import top`
MODULES = {
    "pkg_a/__init__.py": "",
    "pkg_a/low.py": "X = 1\n",
    "pkg_a/mid.py": "def f():\n    from .low import X\n    return X\n",
    "pkg_a/top.py": "import pkg_a.mid\n",
    "pkg_a/alone.py": "import numpy\n",
    "pkg_a/lazy/__init__.py": "def __getattr__(name):\n    raise AttributeError(name)\n",
    "pkg_a/lazy/inner.py": "Y = 2\n",
    "pkg_a/lazy_user.py": "from pkg_a.lazy import Y\n",
    "pkg_a/by_name.py": "import importlib\nM = importlib.import_module('pkg_a.low')\n",
    "pkg_b/__init__.py": "",
    "pkg_b/user.py": "from pkg_a import top\n",
}
KERNEL_MODULES = ("pkg_a/low.py", "pkg_a/mid.py", "pkg_a/top.py", "pkg_a/alone.py", "pkg_a/lazy_user.py",
                  "pkg_a/by_name.py", "pkg_b/user.py")


@pytest.fixture(autouse=True)
def _no_numba_cache_dir(monkeypatch):
    """The trees here are the tests' own: a NUMBA_CACHE_DIR of the caller's is not theirs to clear."""
    monkeypatch.delenv("NUMBA_CACHE_DIR", raising=False)


def _tree(tmp_path, cache=None):
    """The packages of MODULES, each module of KERNEL_MODULES with a cached kernel (index and
    object code) where numba puts it: beside it, or in ``cache`` (NUMBA_CACHE_DIR)."""
    for key, text in MODULES.items():
        (tmp_path / key).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / key).write_text(text)
    for key in KERNEL_MODULES:
        _compile(tmp_path, key, cache)
    return [tmp_path / "pkg_a", tmp_path / "pkg_b"]


def _folder(tmp_path, key, cache):
    source = os.path.dirname(os.path.abspath(tmp_path / key))
    if cache is None:
        return tmp_path / os.path.dirname(key) / "__pycache__"
    return cache / f"{os.path.basename(source)}_{hashlib.sha1(source.encode()).hexdigest()}"


def _compile(tmp_path, key, cache=None):
    folder = _folder(tmp_path, key, cache)
    folder.mkdir(parents=True, exist_ok=True)
    stem = os.path.basename(key)[:-3]
    (folder / f"{stem}.f-1.py311.nbi").write_bytes(b"index")
    (folder / f"{stem}.f-1.py311.1.nbc").write_bytes(b"code")


def _cached(tmp_path, cache=None) -> set:
    """The modules of KERNEL_MODULES whose kernels are cached (index and code)."""
    out = set()
    for key in KERNEL_MODULES:
        stem = os.path.basename(key)[:-3]
        files = [_folder(tmp_path, key, cache) / f"{stem}.f-1.py311{s}" for s in (".nbi", ".1.nbc")]
        if all(f.exists() for f in files):
            out.add(key)
    return out


def test_a_cache_of_unknown_sources_is_cleared_whole_then_kept_until_a_source_changes(tmp_path):
    roots = _tree(tmp_path)
    (tmp_path / "pkg_a" / "__pycache__" / "low.cpython-311.pyc").write_bytes(b"bytecode")
    assert clear_stale(roots) == 2 * len(KERNEL_MODULES)        # no digests yet: provenance unknown
    assert _cached(tmp_path) == set()
    assert (tmp_path / "pkg_a" / "__pycache__" / "low.cpython-311.pyc").exists()
    for key in KERNEL_MODULES:                                  # the kernels compile again
        _compile(tmp_path, key)
    assert clear_stale(roots) == 0 and _cached(tmp_path) == set(KERNEL_MODULES)


@pytest.mark.parametrize("edited, cleared", [
    # through a relative import inside a function, an absolute one, and `from package import module`
    ("pkg_a/low.py", {"pkg_a/low.py", "pkg_a/mid.py", "pkg_a/top.py", "pkg_b/user.py", "pkg_a/by_name.py"}),
    ("pkg_a/top.py", {"pkg_a/top.py", "pkg_b/user.py", "pkg_a/by_name.py"}),
    ("pkg_a/alone.py", {"pkg_a/alone.py", "pkg_a/by_name.py"}),
    # a lazy package counts as importing all of it; a module that imports by name, everything
    ("pkg_a/lazy/inner.py", {"pkg_a/lazy_user.py", "pkg_a/by_name.py"}),
    ("pkg_b/__init__.py", {"pkg_b/user.py", "pkg_a/by_name.py"}),
])
def test_an_edit_clears_the_kernels_of_the_modules_that_reach_it_and_no_others(tmp_path, edited, cleared):
    roots = _tree(tmp_path)
    clear_stale(roots)
    for key in KERNEL_MODULES:
        _compile(tmp_path, key)
    (tmp_path / edited).write_text((tmp_path / edited).read_text() + "# edited\n")
    assert clear_stale(roots) == 2 * len(cleared)
    assert _cached(tmp_path) == set(KERNEL_MODULES) - cleared
    assert clear_stale(roots) == 0                              # recorded: nothing more to clear


def test_a_new_or_removed_source_clears_its_importers_and_a_kernel_of_no_known_source_goes(tmp_path):
    roots = _tree(tmp_path)
    clear_stale(roots)
    for key in KERNEL_MODULES:
        _compile(tmp_path, key)
    (tmp_path / "pkg_a" / "__pycache__" / "gone.f-1.py311.nbi").write_bytes(b"index")
    (tmp_path / "pkg_a" / "new.py").write_text("Z = 3\n")     # imported by nothing yet
    assert clear_stale(roots) == 1 + 2                         # gone's, and by_name's (everything)
    assert _cached(tmp_path) == set(KERNEL_MODULES) - {"pkg_a/by_name.py"}
    (tmp_path / "pkg_a" / "low.py").unlink()
    clear_stale(roots)
    assert _cached(tmp_path) == {"pkg_a/alone.py", "pkg_a/lazy_user.py"}


def _age_kernels(tmp_path, seconds):
    """Every cached kernel file of KERNEL_MODULES written ``seconds`` before its sources were."""
    newest = max(os.stat(tmp_path / key).st_mtime_ns for key in MODULES)
    for folder in {_folder(tmp_path, key, None) for key in KERNEL_MODULES}:
        for path in folder.iterdir():
            if path.suffix in (".nbi", ".nbc"):
                os.utime(path, ns=(newest - int(seconds * 1e9),) * 2)


def test_a_kernel_older_than_a_source_it_reaches_goes_even_where_the_digests_match(tmp_path):
    """An edit put back after some process compiled on it (the digests as recorded, the kernel
    built on the edit), or a source touched: the kernels older than what their module reaches go,
    those of modules that do not reach it stay."""
    roots = _tree(tmp_path)
    clear_stale(roots)
    for key in KERNEL_MODULES:
        _compile(tmp_path, key)
    _age_kernels(tmp_path, 0.0)                                # compiled as the sources were written
    assert clear_stale(roots) == 0
    low = tmp_path / "pkg_a" / "low.py"
    stat = os.stat(low)
    os.utime(low, ns=(stat.st_atime_ns, stat.st_mtime_ns + 10**9))   # the same text, written later
    assert clear_stale(roots) == 2 * 5
    assert _cached(tmp_path) == {"pkg_a/alone.py", "pkg_a/lazy_user.py"}


def test_a_source_that_does_not_parse_counts_as_importing_everything_and_stops_nothing(tmp_path):
    roots = _tree(tmp_path)
    (tmp_path / "pkg_a" / "alone.py").write_text("def broken(:\n")
    clear_stale(roots)
    for key in KERNEL_MODULES:
        _compile(tmp_path, key)
    (tmp_path / "pkg_b" / "__init__.py").write_text("# edited\n")
    clear_stale(roots)
    assert "pkg_a/alone.py" not in _cached(tmp_path) and "pkg_a/low.py" in _cached(tmp_path)


def test_an_aliased_import_module_counts_as_importing_by_name(tmp_path):
    (tmp_path / "pkg" / "__init__.py").parent.mkdir()
    (tmp_path / "pkg" / "__init__.py").write_text("")
    (tmp_path / "pkg" / "a.py").write_text("from importlib import import_module as im\nM = im('pkg.b')\n")
    (tmp_path / "pkg" / "b.py").write_text("")
    graph = dependencies([tmp_path / "pkg"])
    assert graph["pkg/a.py"] == {"pkg/__init__.py", "pkg/b.py"}


def test_numba_cache_dir_is_where_the_kernels_and_the_digests_are(tmp_path, monkeypatch):
    cache = tmp_path / "numba-cache"
    roots = _tree(tmp_path, cache)
    _compile(tmp_path, "pkg_a/low.py")                         # __pycache__'s: not this cache's
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(cache))
    clear_stale(roots)
    assert _cached(tmp_path, cache) == set() and (cache / DIGEST_FILE).is_file()
    assert _cached(tmp_path) == {"pkg_a/low.py"}
    for key in KERNEL_MODULES:
        _compile(tmp_path, key, cache)
    (tmp_path / "pkg_a" / "top.py").write_text("import pkg_a.mid\n# edited\n")
    clear_stale(roots)
    assert _cached(tmp_path, cache) == set(KERNEL_MODULES) - {"pkg_a/top.py", "pkg_b/user.py",
                                                              "pkg_a/by_name.py"}


@pytest.mark.parametrize("record", ["0123abcd\n", '{"sources": {}}', '{"sources": {"pkg_a/low.py": "', ""])
def test_digests_recorded_in_another_form_or_cut_clear_the_whole_cache(tmp_path, record):
    roots = _tree(tmp_path)
    (tmp_path / "pkg_a" / "__pycache__" / DIGEST_FILE).write_text(record)
    assert clear_stale(roots) == 2 * len(KERNEL_MODULES)


def test_the_projects_kernels_are_cleared_by_an_edit_of_what_they_call_and_kept_by_a_nodes():
    """On the project's own sources: the static balance, the integrator and the controller's
    kernels reach the Lie group module; the model's kernels do not reach a node's shell."""
    graph = dependencies(package_roots())
    after_lie = affected({"soft_arm_model/lie.py"}, graph)
    for key in ("soft_arm_model/kernels.py", "soft_arm_model/statics.py", "soft_arm_model/integrators.py",
                "soft_arm_control/collocated.py", "soft_arm_drivers/sim/simulated_rig.py"):
        assert key in after_lie, key
    after_node = affected({"soft_arm_drivers/can/motor_driver_node.py"}, graph)
    assert not after_node & {"soft_arm_model/kernels.py", "soft_arm_control/trust_region.py",
                             "soft_arm_drivers/sim/pendulum.py"}, after_node
    assert set(_sources(package_roots())) == set(graph)


def test_the_project_packages_are_the_roots():
    names = [r.name for r in package_roots()]
    assert names[0] == "soft_arm_model" and "soft_arm_control" in names and "soft_arm_drivers" in names
