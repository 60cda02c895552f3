"""soft-arm-warmup's bytecode: the package's modules are compiled once, not at every node's start."""
import importlib.util
import json
import os
import subprocess
import sys

from soft_arm_experiments.warmup import compile_bytecode

# Run in a process of its own with PYTHONDONTWRITEBYTECODE set: imports argv[1] and prints the
# modules that Python compiled from source on the way (none, where the bytecode is there).
COMPILED_FROM_SOURCE = """
import importlib, json, sys
from importlib.machinery import SourceFileLoader
compiled, source_to_code = [], SourceFileLoader.source_to_code
def recorded(self, data, path, *args, **kwargs):
    compiled.append(path)
    return source_to_code(self, data, path, *args, **kwargs)
SourceFileLoader.source_to_code = recorded
importlib.import_module(sys.argv[1])
print(json.dumps(compiled))
"""


def _compiled_from_source(module: str, path: str = "") -> list:
    env = dict(os.environ, PYTHONDONTWRITEBYTECODE="1",
               PYTHONPATH=os.pathsep.join(filter(None, [path, os.environ.get("PYTHONPATH")])))
    out = subprocess.run([sys.executable, "-c", COMPILED_FROM_SOURCE, module], env=env,
                         capture_output=True, text=True, timeout=120, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_the_bytecode_is_written_whatever_the_environment_says_and_a_missing_package_is_named(
        tmp_path, monkeypatch):
    sources = [tmp_path / "warm_pkg" / "__init__.py", tmp_path / "warm_pkg" / "sub" / "__init__.py",
               tmp_path / "warm_pkg" / "sub" / "leaf.py"]
    for source in sources:
        source.parent.mkdir(parents=True, exist_ok=True)
        source.write_text("VALUE = 1\n", encoding="utf-8")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setattr(sys, "dont_write_bytecode", True)
    assert _compiled_from_source("warm_pkg.sub.leaf", str(tmp_path)) == [str(s) for s in sources]

    assert compile_bytecode(("warm_pkg", "no_such_package_of_soft_arm")) == ["no_such_package_of_soft_arm"]
    for source in sources:
        assert os.path.exists(importlib.util.cache_from_source(str(source))), source
    assert _compiled_from_source("warm_pkg.sub.leaf", str(tmp_path)) == []
    # an edited module is compiled from its source again (Python checks the source's time stamp)
    os.utime(sources[2], (os.stat(sources[2]).st_atime, os.stat(sources[2]).st_mtime + 10))
    assert _compiled_from_source("warm_pkg.sub.leaf", str(tmp_path)) == [str(sources[2])]


def test_after_the_warm_up_a_node_process_compiles_none_of_the_package():
    assert compile_bytecode() == []
    assert _compiled_from_source("soft_arm_experiments.experiment") == []
