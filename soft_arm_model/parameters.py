"""The parameter engine every soft_arm config file goes through (ROS 2 parameter layout).

A parameter file holds ``<node>: {ros__parameters: {<namespace>: {...}}}`` (``/**`` applies to every
node). A schema maps dotted keys to ``(kind, check, allowed)``; kinds are float, int, bool, str and
their lists floats, ints, strs. Every key is required (a value is never silently defaulted), every
value is checked, and a bad one raises :class:`ConfigError` naming ``namespace.key``, the value and
what is allowed. Overrides are dotted keys relative to the namespace, applied before validation so
that an override is checked like a value from the file. Numbers follow ROS 2's YAML rules.
"""
from __future__ import annotations

import copy
import difflib
import math
import os
import re
import sys
from typing import Any, Mapping

import yaml


class _RosYamlLoader(getattr(yaml, "CSafeLoader", yaml.SafeLoader)):
    """Safe YAML loader that reads ``1.5e5`` as a float, as ROS 2's parameter parser does
    (PyYAML's YAML 1.1 resolver would read it as a string). On libyaml's parser where PyYAML has
    it (its wheels do), ten times the pure-Python one's speed."""


_RosYamlLoader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?(?:[0-9][0-9_]*)(?:\.[0-9_]*)?[eE][-+]?[0-9]+$"),
    list("-+0123456789"))


def parse_yaml(text):
    """Parse YAML text with ROS 2's number rules."""
    return yaml.load(text, Loader=_RosYamlLoader)  # noqa: S506 - a SafeLoader subclass


class ConfigError(ValueError):
    """A configuration value is missing, unknown or out of range."""


def split_overrides(pairs, namespaces) -> dict:
    """Group ``namespace.key=value`` strings (command-line ``--set``) by namespace, one of
    ``namespaces``: {namespace: {key: value}}, values still strings; ConfigError for a malformed pair."""
    groups = {ns: {} for ns in namespaces}
    for pair in pairs or ():
        key, sep, value = pair.partition("=")
        ns, dot, rest = key.partition(".")
        if not sep or not dot or ns not in groups:
            raise ConfigError(f"--set expects namespace.key=value with namespace one of "
                              f"{', '.join(groups)}; got {pair!r}")
        groups[ns][rest] = value
    return groups


def flatten_tree(tree: Mapping, prefix: str = "") -> dict:
    """The leaves of a nested parameter tree by dotted key."""
    flat = {}
    for k, v in tree.items():
        key = f"{prefix}{k}"
        if isinstance(v, Mapping):
            flat.update(flatten_tree(v, key + "."))
        else:
            flat[key] = v
    return flat


def _coerce(full_key: str, value: Any, kind: str, allowed: str):
    def bad():
        return ConfigError(f"{full_key} = {value!r} is not valid: expected {allowed}")

    def scalar(v, k):
        if k == "float":
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(float(v)):
                raise bad()
            return float(v)
        if k == "int":
            if isinstance(v, bool) or not isinstance(v, int):
                raise bad()
            return int(v)
        if k == "bool":
            if not isinstance(v, bool):
                raise bad()
            return v
        if not isinstance(v, str):
            raise bad()
        return v

    if kind in ("floats", "ints", "strs", "bools"):
        if not isinstance(value, (list, tuple)):
            raise bad()
        return tuple(scalar(v, kind[:-1]) for v in value)
    return scalar(value, kind)


def _unknown_key(namespace: str, key: str, known) -> ConfigError:
    close = difflib.get_close_matches(key, list(known), n=3)
    hint = f"; did you mean {', '.join(namespace + '.' + c for c in close)}?" if close else ""
    return ConfigError(f"unknown key {namespace}.{key}{hint}")


def apply_overrides(params: dict, overrides: Mapping[str, Any] | None, schema: Mapping,
                    namespace: str) -> dict:
    """Return a copy of a parameter tree with dotted-key overrides applied.

    Keys are relative to ``namespace`` (a leading ``namespace.`` is accepted). String values are
    parsed as YAML (``"2e5"`` -> 200000.0, ``"[1, 2]"`` -> list). A key that ``schema`` does not
    know raises :class:`ConfigError` with the closest known keys.
    """
    out = copy.deepcopy(params)
    for key, value in (overrides or {}).items():
        key = key[len(namespace) + 1:] if key.startswith(namespace + ".") else key
        if not any(_matches(key, k) for k in schema):
            raise _unknown_key(namespace, key, schema)
        if isinstance(value, str):
            try:
                value = parse_yaml(value)
            except (yaml.YAMLError, UnicodeError) as exc:     # libyaml: bytes not UTF-8 (surrogates)
                raise ConfigError(f"{namespace}.{key}: cannot parse {value!r}: {exc}") from None
        node = out
        *parents, leaf = key.split(".")
        for part in parents:
            node = node.setdefault(part, {})
        node[leaf] = value
    return out


def _matches(key: str, pattern: str) -> bool:
    """Schema keys may hold one ``*`` path element (a name chosen by the user, e.g. a task name)."""
    if "*" not in pattern:
        return key == pattern
    parts, pparts = key.split("."), pattern.split(".")
    return len(parts) == len(pparts) and all(p == "*" or p == k for k, p in zip(parts, pparts))


def schema_entry(schema: Mapping, key: str):
    """The (kind, check, allowed) of the dotted ``key`` (its pattern's), or None when unknown."""
    pattern = next((k for k in schema if _matches(key, k)), None)
    return None if pattern is None else schema[pattern]


def check_value(schema: Mapping, namespace: str, key: str, raw: Any):
    """One value of ``namespace.key`` checked like :func:`validate_tree` checks a file's: the coerced
    value, or ConfigError naming the key, the value and what is allowed (also for an unknown key)."""
    entry = schema_entry(schema, key)
    if entry is None:
        raise _unknown_key(namespace, key, schema)
    kind, check, allowed = entry
    value = _coerce(f"{namespace}.{key}", raw, kind, allowed)
    if check is not None and not check(value):
        raise ConfigError(f"{namespace}.{key} = {raw!r} is not valid: expected {allowed}")
    return value


_INTERVAL = re.compile(r"\bin ([\[(])\s*([-+]?[0-9][0-9_.]*(?:e[-+]?[0-9]+)?)\s*,\s*"
                       r"([-+]?[0-9][0-9_.]*(?:e[-+]?[0-9]+)?)\s*([\])])")


def allowed_interval(allowed: str):
    """The interval a schema's ``allowed`` text states, as (low, high, low included, high included),
    or None when it states none: "a rate in (0, 1e6] N/s" -> (0.0, 1e6, False, True)."""
    m = _INTERVAL.search(allowed)
    if m is None:
        return None
    return float(m.group(2)), float(m.group(3)), m.group(1) == "[", m.group(4) == "]"


def validate_tree(params: Mapping, schema: Mapping, namespace: str) -> dict:
    """Check a parameter tree against ``schema`` (dotted key -> (kind, check, allowed)).

    Returns the coerced values by dotted key. Unknown and missing keys and values that fail their
    check raise :class:`ConfigError` naming ``namespace.key``, the value and what is allowed.
    Patterns with a ``*`` element match any name there; they are optional as a group.
    """
    flat = flatten_tree(params)
    for key in flat:
        if schema_entry(schema, key) is None:
            raise _unknown_key(namespace, key, schema)
    missing = [k for k in schema if "*" not in k and k not in flat]
    if missing:
        raise ConfigError(f"missing key {namespace}.{missing[0]} (expected {schema[missing[0]][2]})")
    return {key: check_value(schema, namespace, key, raw) for key, raw in flat.items()}


def default_config_dir() -> str:
    """The package's ``config/`` directory: the source tree, or ``share/soft_arm/config`` once installed."""
    here = os.path.dirname(os.path.abspath(__file__))
    candidates = [os.path.join(os.path.dirname(here), "config"),
                  os.path.join(sys.prefix, "share", "soft_arm", "config")]
    try:  # a sourced ROS 2 installation (colcon install space)
        from ament_index_python.packages import get_package_share_directory
        candidates.insert(0, os.path.join(get_package_share_directory("soft_arm"), "config"))
    except Exception:  # noqa: BLE001 - ament_index is optional outside a ROS installation
        pass
    for path in candidates:
        if os.path.isfile(os.path.join(path, "arm.yaml")):
            return path
    raise ConfigError("cannot find the soft_arm config directory (looked in: " + ", ".join(candidates) + ")")


def read_parameters(path: str, node: str = "/**") -> dict:
    """Return the ``ros__parameters`` mapping of ``node`` in a ROS 2 parameter file. ConfigError,
    naming the file, for a file that cannot be read, is not UTF-8, is not YAML, or is not in the
    ROS 2 parameter layout (``<node>: {ros__parameters: {<namespace>: ...}}``, not empty)."""
    layout = f"expected '{node}: {{ros__parameters: ...}}' (ROS 2 parameter layout)"
    try:
        with open(path, encoding="utf-8") as fh:
            doc = parse_yaml(fh)
    except IsADirectoryError:
        raise ConfigError(f"cannot read config file {path}: it is a directory, not a file") from None
    except OSError as exc:
        raise ConfigError(f"cannot read config file {path}: {exc.strerror}") from None
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{path} is not UTF-8 text (byte {exc.start}: {exc.reason})") from None
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path} is not valid YAML: {exc}") from None
    if not isinstance(doc, dict) or node not in doc:
        raise ConfigError(f"{path}: {layout}")
    entry = doc[node]
    if not isinstance(entry, dict) or "ros__parameters" not in entry:
        raise ConfigError(f"{path}: {node} holds {_kind(entry)}: {layout}")
    params = entry["ros__parameters"]
    if not params:
        raise ConfigError(f"{path}: {node}.ros__parameters is empty: {layout}")
    if not isinstance(params, dict):
        raise ConfigError(f"{path}: {node}.ros__parameters holds {_kind(params)}, not namespaces: {layout}")
    return params


def _kind(value) -> str:
    """What a YAML value is, for a message: "a number 5", "nothing", "a list"."""
    if value is None:
        return "nothing"
    if isinstance(value, (list, tuple)):
        return "a list"
    if isinstance(value, dict):
        return "a mapping without ros__parameters"
    return f"{type(value).__name__} {value!r}"


def load_section(path: str, namespace: str, schema: Mapping, overrides: Mapping[str, Any] | None = None,
                 node: str = "/**") -> dict:
    """Validated values (dotted key -> value) of ``namespace`` in the parameter file ``path``, with
    ``overrides`` applied first; a ConfigError names the file."""
    params = read_parameters(path, node)
    tree = params
    for part in namespace.split("."):
        if not isinstance(tree, dict) or part not in tree:
            raise ConfigError(f"{path}: no '{namespace}' parameters under {node}.ros__parameters")
        tree = tree[part]
    if not isinstance(tree, dict):
        raise ConfigError(f"{path}: no '{namespace}' parameters under {node}.ros__parameters")
    try:
        return validate_tree(apply_overrides(tree, overrides, schema, namespace), schema, namespace)
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from None
