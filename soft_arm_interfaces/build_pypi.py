#!/usr/bin/env python3
"""Build ``soft_arm_interfaces`` into the active Python environment, without ROS or colcon.

On a ROS 2 installation colcon builds this package from ``CMakeLists.txt``. The PyPI ROS wheels
(``ros-jazzy-rclpy`` and its dependencies) carry the same rosidl generators, headers and libraries
but no CMake tooling, so this script does what ``rosidl_generate_interfaces`` does, for C and
Python only:

1. translates ``msg/*.msg`` to ``.idl`` (rosidl_adapter) and computes the type descriptions and
   their RIHS01 hashes (rosidl_generator_type_description);
2. generates the C structures, the C type support dispatch, the Fast DDS (fastrtps_c) and
   introspection type supports and the Python classes with their C extensions (the generator
   classes of the rosidl_* packages, called directly: ``rosidl generate`` refuses to run because
   every wheel ships both an egg-info and a dist-info, so each generator's entry point is found twice);
3. compiles them with gcc/g++ into the five libraries and three Python extensions that colcon would
   build, and installs them into the environment's prefix as a ROS installation lays them out:
   ``lib/libsoft_arm_interfaces__*.so`` (where the wheels' bootstrapper points LD_LIBRARY_PATH and
   where the rmw finds the type supports), the Python package ``soft_arm_interfaces`` in
   site-packages, and ``share/soft_arm_interfaces`` (package.xml, the ``.msg``, ``.idl`` and
   ``.json`` files, which the recorder reads for its MCAP schemas and type hashes) with the ament
   index entries ``packages`` and ``rosidl_interfaces``. C/C++ headers are not installed.

It is idempotent: a stamp in ``share/soft_arm_interfaces`` records a digest of everything the
build depends on (the package's files, this script, the generators' versions, Python and numpy);
when it matches and every installed file is there, nothing is done. A build takes 10-20 s.

Usage: ``python soft_arm_interfaces/build_pypi.py [--prefix DIR] [--force]``. Needs the
rosidl generators (installed with ``ros-jazzy-rclpy``), gcc and g++ (or ``CC`` and ``CXX``), the
Python headers and numpy. Exits 1 with what is missing or what failed.
"""
from __future__ import annotations

import argparse
import contextlib
import hashlib
import io
import json
import os
import shutil
import subprocess
import sys
import sysconfig
import tempfile
import time
import xml.etree.ElementTree as ET
from concurrent.futures import ThreadPoolExecutor
from importlib import metadata
from pathlib import Path

SOURCE = Path(__file__).resolve().parent
GENERATORS = ("rosidl_adapter", "rosidl_generator_c", "rosidl_generator_py",
              "rosidl_generator_type_description", "rosidl_typesupport_c",
              "rosidl_typesupport_fastrtps_c", "rosidl_typesupport_introspection_c")
# the type supports the C dispatch library chooses from at run time (as on a Jazzy installation)
TYPESUPPORTS = ("rosidl_typesupport_fastrtps_c", "rosidl_typesupport_introspection_c")
STAMP = "pypi_build.json"


class BuildError(RuntimeError):
    """The package cannot be built here: what is missing, or which step failed and its output."""


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--prefix", type=Path, default=Path(sys.prefix),
                        help="install prefix (default: this Python's, the active venv)")
    parser.add_argument("--force", action="store_true", help="rebuild even when up to date")
    args = parser.parse_args(argv)
    try:
        result = build(args.prefix.resolve(), force=args.force)
    except BuildError as exc:
        print(f"soft_arm_interfaces: cannot build: {exc}", file=sys.stderr)
        return 1
    state = f"built in {result['seconds']:.1f} s" if result["built"] else "up to date"
    print(f"soft_arm_interfaces: {state} in {args.prefix}")
    return 0


def build(prefix: Path, force: bool = False, source: Path = SOURCE) -> dict:
    """Build the package in ``source`` into ``prefix`` unless it is up to date there (``force``:
    always). Returns ``built`` (whether it built), ``seconds`` and the installed ``files``
    (paths relative to ``prefix``). Raises :class:`BuildError`."""
    start = time.monotonic()
    name, dependencies = _manifest(source)
    messages = sorted((source / "msg").glob("*.msg"))
    if not messages:
        raise BuildError(f"no msg/*.msg in {source}")
    layout = _Layout(prefix, name)
    digest = _digest(source, messages)
    if not force and _up_to_date(layout, digest):
        return {"built": False, "seconds": time.monotonic() - start, "files": _stamp(layout)["files"]}
    tools = _tools()
    search = _share_prefixes()
    includes = _interface_includes(dependencies, search)
    with tempfile.TemporaryDirectory(prefix=f"{name}-build-") as tmp:
        work = Path(tmp)
        generated = _generate(name, source, messages, includes, search, work)
        staged = _compile(name, dependencies, generated, tools, work,
                          os.path.relpath(layout.lib, layout.python / name))
        files = _install(name, source, messages, generated, staged, layout)
    layout.stamp.write_text(json.dumps({"digest": digest, "files": files}, indent=1) + "\n",
                            encoding="utf-8")
    return {"built": True, "seconds": time.monotonic() - start, "files": files}


class _Layout:
    """Where a ROS installation puts each part, under ``prefix``."""

    def __init__(self, prefix: Path, name: str):
        self.prefix = prefix
        self.lib = prefix / "lib"
        self.python = Path(sysconfig.get_path("platlib", vars={"base": prefix, "platbase": prefix}))
        self.share = prefix / "share" / name
        self.index = prefix / "share" / "ament_index" / "resource_index"
        self.stamp = self.share / STAMP


def _manifest(source: Path) -> tuple[str, list]:
    """The package's name and the interface packages it depends on (package.xml)."""
    try:
        root = ET.parse(source / "package.xml").getroot()
    except (OSError, ET.ParseError) as exc:
        raise BuildError(f"unreadable {source / 'package.xml'}: {exc}") from None
    dependencies = [e.text.strip() for tag in ("depend", "build_depend") for e in root.findall(tag)]
    return root.findtext("name").strip(), dependencies


def _digest(source: Path, messages) -> str:
    """A digest of every input of the build."""
    h = hashlib.sha256()
    for path in [Path(__file__).resolve(), source / "package.xml", *messages]:
        h.update(path.name.encode() + b"\0" + path.read_bytes() + b"\0")
    versions = {}
    for dist in GENERATORS + ("numpy",):
        try:
            versions[dist] = metadata.version(dist)
        except metadata.PackageNotFoundError:
            versions[dist] = None
    h.update(json.dumps([sys.version, versions], sort_keys=True).encode())
    return h.hexdigest()


def _stamp(layout: _Layout) -> dict:
    try:
        return json.loads(layout.stamp.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {}


def _up_to_date(layout: _Layout, digest: str) -> bool:
    stamp = _stamp(layout)
    return stamp.get("digest") == digest and all((layout.prefix / f).is_file() for f in stamp["files"])


def _tools() -> dict:
    """The compilers and the headers the build needs; BuildError naming what is missing."""
    missing = []
    for module in GENERATORS:
        try:
            __import__(module)
        except ImportError as exc:
            missing.append(f"the Python module {module} ({exc}; it comes with ros-jazzy-rclpy: "
                           "pip install -e .)")
    tools = {"cc": os.environ.get("CC", "gcc"), "cxx": os.environ.get("CXX", "g++")}
    for key, what in (("cc", "a C compiler (apt-get install gcc, or set CC)"),
                      ("cxx", "a C++ compiler (apt-get install g++, or set CXX)")):
        if shutil.which(tools[key]) is None:
            missing.append(f"{what}: {tools[key]!r} is not on PATH")
    tools["python_include"] = sysconfig.get_paths()["include"]
    if not (Path(tools["python_include"]) / "Python.h").is_file():
        missing.append(f"the Python headers (no Python.h in {tools['python_include']}: install "
                       f"python{sys.version_info.major}.{sys.version_info.minor}-dev)")
    try:
        import numpy
        tools["numpy_include"] = numpy.get_include()
    except ImportError:
        missing.append("numpy")
    if missing:
        raise BuildError("missing " + "; ".join(missing))
    return tools


def _share_prefixes() -> list:
    """Prefixes whose ``share/`` holds installed interface packages and the generators' templates:
    ``AMENT_PREFIX_PATH``, then this Python's prefix (where the PyPI ROS wheels install them)."""
    paths = [Path(p) for p in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p]
    return list(dict.fromkeys(paths + [Path(sys.prefix)]))


def _interface_includes(dependencies, search) -> dict:
    """Every interface package the messages need, with its dependencies' (package.xml), found in
    ``share/`` of ``search``: {package: share directory}."""
    found, pending = {}, list(dependencies)
    while pending:
        package = pending.pop()
        if package in found:
            continue
        share = next((p / "share" / package for p in search if (p / "share" / package / "msg").is_dir()),
                     None)
        if share is None:
            raise BuildError(f"the interface package {package} is not installed under share/ of any "
                             f"of {', '.join(map(str, search))}")
        found[package] = share
        root = ET.parse(share / "package.xml").getroot()
        pending += [e.text.strip() for tag in ("depend", "build_depend") for e in root.findall(tag)
                    if any((p / "share" / e.text.strip() / "msg").is_dir() for p in search)]
    return found


@contextlib.contextmanager
def _step(what: str):
    """Run a generator step with its chatter captured; BuildError with it if the step fails."""
    out = io.StringIO()
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(out):
            yield
    except Exception as exc:
        raise BuildError(f"{what} failed: {type(exc).__name__}: {exc}\n{out.getvalue()}") from exc


def _generate(name, source, messages, includes, search, work) -> dict:
    """Generate the IDL, type descriptions, C, type support and Python code into ``work``;
    returns their directories by generator."""
    from rosidl_adapter.msg import convert_msg_to_idl
    from rosidl_generator_c.cli import GenerateC
    from rosidl_generator_py.cli import GeneratePython
    from rosidl_generator_type_description.cli import HashTypeDescription
    from rosidl_typesupport_c.cli import GenerateCTypesupport
    from rosidl_typesupport_fastrtps_c.cli import GenerateFastRTPSCTypesupport
    from rosidl_typesupport_introspection_c.cli import GenerateIntrospectionCTypesupport

    # the generators find their templates with ament_index_python
    ament = os.pathsep.join(map(str, search))
    previous = os.environ.get("AMENT_PREFIX_PATH")
    os.environ["AMENT_PREFIX_PATH"] = ament
    try:
        idl_root = work / "idl"
        with _step("translating the .msg files to .idl"):
            for msg in messages:
                convert_msg_to_idl(source, name, msg.relative_to(source), idl_root / "msg")
        idl = [f"{idl_root}:msg/{m.stem}.idl" for m in messages]
        include_paths = [str(p) for p in includes.values()]
        # each generator writes under <its directory>/<package>/, the include root of its headers
        out = {key: work / key / name for key in ("type_description", "c", "introspection_c",
                                                  "fastrtps_c", "typesupport_c", "py")}
        with _step("computing the type descriptions"):
            descriptions = HashTypeDescription("type_description").generate_type_hashes(
                name, idl, include_paths, out["type_description"])
        with _step("generating the C code"):
            GenerateC("c").generate(name, idl, include_paths, out["c"],
                                    type_description_files=descriptions)
        with _step("generating the introspection type support"):
            GenerateIntrospectionCTypesupport("introspection_c").generate(
                name, idl, include_paths, out["introspection_c"])
        with _step("generating the Fast DDS type support"):
            GenerateFastRTPSCTypesupport("fastrtps_c").generate(name, idl, include_paths,
                                                                out["fastrtps_c"])
        with _step("generating the C type support dispatch"):
            GenerateCTypesupport("typesupport_c", typesupport_implementations=list(TYPESUPPORTS)
                                 ).generate(name, idl, include_paths, out["typesupport_c"])
        with _step("generating the Python code"):
            out["py"].mkdir(parents=True)
            (out["py"] / "__init__.py").write_text("")
            GeneratePython("py", typesupport_implementations=["rosidl_typesupport_c", *TYPESUPPORTS]
                           ).generate(name, idl, include_paths, out["py"])
    finally:
        if previous is None:
            os.environ.pop("AMENT_PREFIX_PATH")
        else:
            os.environ["AMENT_PREFIX_PATH"] = previous
    out["idl"] = idl_root
    return out


def _compile(name, dependencies, generated, tools, work, lib_from_python: str) -> dict:
    """Compile the generated code (as the rosidl CMake functions do) into ``work/stage``;
    returns the built libraries and Python extensions: {target: path}. ``lib_from_python``: the
    relative path from the installed Python package to the installed libraries."""
    prefix = Path(sys.prefix)
    include_root = prefix / "include"
    # the wheels install each package's headers under include/<package>/ (ROS's layout)
    includes = [f"-I{include_root}"] + [f"-I{d}" for d in sorted(include_root.iterdir()) if d.is_dir()]
    includes += [f"-I{generated[g].parent}" for g in ("c", "introspection_c", "fastrtps_c", "py")]
    stage = work / "stage"
    stage.mkdir()
    deps = list(dependencies)
    lib = f"-L{prefix / 'lib'}"
    # the libraries find each other in their own directory; the Python extensions in <prefix>/lib
    rpath_lib = "-Wl,-rpath,$ORIGIN"
    c_flags = ["-std=c11", "-O2", "-fPIC", "-w"]
    cxx_flags = ["-std=c++17", "-O2", "-fPIC", "-w"]

    def sources(key, suffix):
        return sorted(str(p) for p in generated[key].rglob(f"*{suffix}"))

    def link(target, compiler, flags, srcs, libs, extra=()):
        out = stage / target
        cmd = [compiler, *flags, "-shared", *includes, *extra, *srcs, "-o", str(out), lib,
               f"-L{stage}", rpath_lib, *libs]
        run = subprocess.run(cmd, capture_output=True, text=True)
        if run.returncode != 0:
            raise BuildError(f"compiling {target} failed ({' '.join(cmd[:3])} ...):\n{run.stderr[-4000:]}")
        return out

    generator_c = f"{name}__rosidl_generator_c"
    define = f"-DROSIDL_GENERATOR_C_BUILDING_DLL_{name}"
    built = {}
    built["generator_c"] = link(f"lib{generator_c}.so", tools["cc"], c_flags, sources("c", ".c"),
                                [f"-l{d}__rosidl_generator_c" for d in deps]
                                + ["-lrosidl_runtime_c", "-lrcutils"], [define])
    jobs = {
        "introspection_c": (f"lib{name}__rosidl_typesupport_introspection_c.so", tools["cc"], c_flags,
                            sources("introspection_c", ".c"),
                            [f"-l{generator_c}", "-lrosidl_typesupport_introspection_c",
                             "-lrosidl_runtime_c"]
                            + [f"-l{d}__rosidl_typesupport_introspection_c" for d in deps],
                            [f"-DROSIDL_TYPESUPPORT_INTROSPECTION_C_BUILDING_DLL_{name}"]),
        "fastrtps_c": (f"lib{name}__rosidl_typesupport_fastrtps_c.so", tools["cxx"], cxx_flags,
                       sources("fastrtps_c", ".cpp"),
                       [f"-l{generator_c}", "-lfastcdr", "-lrosidl_runtime_c",
                        "-lrosidl_typesupport_fastrtps_c", "-lrosidl_typesupport_fastrtps_cpp"]
                       + [f"-l{d}__rosidl_typesupport_fastrtps_c" for d in deps],
                       [f"-DROSIDL_TYPESUPPORT_FASTRTPS_C_BUILDING_DLL_{name}"]),
        "typesupport_c": (f"lib{name}__rosidl_typesupport_c.so", tools["cxx"], cxx_flags,
                          sources("typesupport_c", ".cpp"),
                          [f"-l{generator_c}", "-lrosidl_runtime_c", "-lrosidl_typesupport_c"]
                          + [f"-l{d}__rosidl_typesupport_c" for d in deps], [define]),
    }
    with ThreadPoolExecutor(max_workers=2) as pool:
        futures = {key: pool.submit(link, *job) for key, job in jobs.items()}
        built.update({key: f.result() for key, f in futures.items()})
    py_c = [s for s in sources("py", ".c") if ".ep." not in Path(s).name]
    py_flags = [f"-I{tools['python_include']}", f"-I{tools['numpy_include']}"]
    built["generator_py"] = link(f"lib{name}__rosidl_generator_py.so", tools["cc"], c_flags, py_c,
                                 [f"-l{generator_c}", f"-l{name}__rosidl_typesupport_c",
                                  "-lrosidl_runtime_c", "-lrosidl_typesupport_c"]
                                 + [f"-l{d}__rosidl_generator_py" for d in deps], py_flags)
    extensions = {}
    with ThreadPoolExecutor(max_workers=2) as pool:
        for ts in ("rosidl_typesupport_c", *TYPESUPPORTS):
            entry = generated["py"] / f"_{name}_s.ep.{ts}.c"
            libs = [f"-l{name}__rosidl_generator_py", f"-l{name}__{ts}", f"-l{name}__rosidl_typesupport_c",
                    f"-l{generator_c}", "-lrosidl_runtime_c", "-lrosidl_typesupport_c"]
            extensions[f"{name}_s__{ts}.so"] = pool.submit(
                link, f"{name}_s__{ts}.so", tools["cc"], c_flags, [str(entry)], libs,
                py_flags + [f"-Wl,-rpath,$ORIGIN/{lib_from_python}"])
        built.update({key: f.result() for key, f in extensions.items()})
    return built


def _install(name, source, messages, generated, built, layout: _Layout) -> list:
    """Copy the build into ``layout``; returns the installed files relative to its prefix."""
    files = []

    def put(src: Path, dest: Path):
        dest.parent.mkdir(parents=True, exist_ok=True)
        tmp = dest.with_name(f".{dest.name}.tmp")
        shutil.copyfile(src, tmp)
        os.replace(tmp, dest)
        files.append(str(dest.relative_to(layout.prefix)))

    for key, path in built.items():
        if path.name.startswith("lib"):
            put(path, layout.lib / path.name)
    # the Python package: replaced whole, so that no module of a removed message stays behind
    package = layout.python / name
    shutil.rmtree(package, ignore_errors=True)
    for path in sorted(generated["py"].rglob("*.py")):
        put(path, package / path.relative_to(generated["py"]))
    for path in built.values():
        if not path.name.startswith("lib"):
            put(path, package / path.name)
    put(source / "package.xml", layout.share / "package.xml")
    for msg in messages:
        put(msg, layout.share / "msg" / msg.name)
        put(generated["idl"] / "msg" / f"{msg.stem}.idl", layout.share / "msg" / f"{msg.stem}.idl")
        put(generated["type_description"] / "msg" / f"{msg.stem}.json",
            layout.share / "msg" / f"{msg.stem}.json")
    index = {"packages": "", "rosidl_interfaces": "".join(
        f"msg/{m.stem}.idl\nmsg/{m.name}\n" for m in messages)}
    for kind, text in index.items():
        dest = layout.index / kind / name
        dest.parent.mkdir(parents=True, exist_ok=True)
        dest.write_text(text, encoding="utf-8")
        files.append(str(dest.relative_to(layout.prefix)))
    return sorted(files)


if __name__ == "__main__":
    sys.exit(main())
