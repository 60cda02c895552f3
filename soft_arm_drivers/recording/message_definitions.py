"""Message definitions as rosbag2 stores them in MCAP schemas: a type's ``.msg`` text with every
nested type's text, and its RIHS01 type hash, read from the ``share/`` of the installed interface
packages (``AMENT_PREFIX_PATH``, then this Python's prefix, where the PyPI ROS packages put them).
"""
from __future__ import annotations

import json
import os
import sys
from pathlib import Path

_PRIMITIVE_TYPES = frozenset({"bool", "byte", "char", "float32", "float64", "int8", "uint8",
                              "int16", "uint16", "int32", "uint32", "int64", "uint64", "string",
                              "wstring"})
_DEFINITION_SEPARATOR = "=" * 80


class UnknownMessageTypeError(LookupError):
    """A message type name is malformed or its ``.msg`` definition is not installed."""


def message_definition(type_name: str) -> str:
    """The full ``ros2msg`` definition of ``type_name`` (``pkg/msg/Type``) as rosbag2 stores it
    in MCAP schemas: the type's ``.msg`` text followed by every nested type's text.

    Raises :class:`UnknownMessageTypeError` if the name is malformed or a ``.msg`` is missing.
    """
    root = _split_type_name(type_name)
    seen: set[tuple[str, str]] = set()

    def text_with_dependencies(package: str, name: str) -> str:
        text = _read_msg(package, name)
        parts = [text]
        for dependency in _dependencies(text, package):
            if dependency not in seen:
                seen.add(dependency)
                parts.append(f"\n{_DEFINITION_SEPARATOR}\nMSG: {'/'.join(dependency)}\n")
                parts.append(text_with_dependencies(*dependency))
        return "".join(parts)

    return text_with_dependencies(*root)


def type_description_hash(type_name: str) -> str:
    """The RIHS01 type hash of ``type_name`` from its rosidl ``.json``; ``""`` without one."""
    package, name = _split_type_name(type_name)
    path = _find_interface_file(package, name, ".json")
    if path is None:
        return ""
    description = json.loads(path.read_text(encoding="utf-8"))
    full_name = f"{package}/msg/{name}"
    return next((entry["hash_string"] for entry in description["type_hashes"]
                 if entry["type_name"] == full_name), "")


def _split_type_name(type_name: str) -> tuple[str, str]:
    parts = type_name.split("/")
    if len(parts) != 3 or parts[1] != "msg" or not all(parts):
        raise UnknownMessageTypeError(
            f"message type must look like 'package/msg/Type', got {type_name!r}")
    return parts[0], parts[2]


def _interface_prefixes() -> list[Path]:
    ament = [Path(p) for p in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p]
    return ament + [Path(sys.prefix)]


def _find_interface_file(package: str, name: str, suffix: str) -> Path | None:
    for prefix in _interface_prefixes():
        path = prefix / "share" / package / "msg" / f"{name}{suffix}"
        if path.is_file():
            return path
    return None


def _read_msg(package: str, name: str) -> str:
    path = _find_interface_file(package, name, ".msg")
    if path is None:
        searched = ", ".join(str(p) for p in _interface_prefixes())
        raise UnknownMessageTypeError(
            f"no definition of {package}/msg/{name}: {package}/msg/{name}.msg is not under "
            f"share/ of any of {searched}")
    return path.read_bytes().decode("utf-8")


def _dependencies(text: str, package: str) -> list[tuple[str, str]]:
    """Nested message types used by the fields of a ``.msg`` text, sorted by name."""
    found = set()
    for line in text.splitlines():
        tokens = line.split("#", 1)[0].split()
        if len(tokens) < 2:  # blank, comment only
            continue
        base = tokens[0].split("[", 1)[0].split("<", 1)[0]  # drop array and string bounds
        if base in _PRIMITIVE_TYPES:
            continue
        dep_package, _, dep_name = base.rpartition("/")
        found.add((dep_package.split("/", 1)[0] or package, dep_name))
    return sorted(found)
