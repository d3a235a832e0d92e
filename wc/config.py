"""Typed, validated params: YAML sections -> frozen dataclasses.

Every stage reads its sections of `params.yaml` through `load_section`, so an unknown key, a
missing key or a value of the wrong type fails with one message naming the key path and the file.
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import types
import typing
from pathlib import Path
from typing import Any, TypeVar

import yaml

T = TypeVar("T")


class ParamsError(ValueError):
    """A params file is malformed: names the file and the dotted key."""


def add_params_arguments(parser: argparse.ArgumentParser) -> None:
    """The `--params FILE` and repeated `--set key.sub=value` options every stage and benchmark takes."""
    parser.add_argument("--params", default="params.yaml", help="params file (default: params.yaml)")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                        help="override one param, e.g. --set sim.iterations=5 (repeatable)")


class Replace(dict):
    """A mapping tagged `!replace` in an override file: it replaces the base file's mapping instead of merging."""


class _ParamsLoader(yaml.SafeLoader):
    """YAML's safe loader plus the `!replace` tag."""


_ParamsLoader.add_constructor("!replace", lambda loader, node: Replace(loader.construct_mapping(node, deep=True)))


def merged(base: dict[str, Any], override: dict[str, Any]) -> dict[str, Any]:
    """`base` with `override` on top: mappings merge key by key (a `Replace` one replaces), anything else replaces."""
    out = dict(base)
    for key, value in override.items():
        if isinstance(value, dict) and not isinstance(value, Replace) and isinstance(out.get(key), dict):
            out[key] = merged(out[key], value)
        else:
            out[key] = dict(value) if isinstance(value, Replace) else value
    return out


def _load_params_file(path: Path, seen: tuple[Path, ...] = ()) -> dict[str, Any]:
    """One params file as a dict; a file with `extends: <base>` or `extends: [<base>, ...]` (relative to it) is
    loaded on top of its bases, merged in order."""
    if not path.is_file():
        raise ParamsError(f"params file not found: {path}" + (f" (extended by {seen[-1]})" if seen else ""))
    if path.resolve() in seen:
        raise ParamsError(f"{path}: params files extend each other in a cycle: {' -> '.join(map(str, seen))}")
    try:
        data = yaml.load(path.read_text(), Loader=_ParamsLoader)
    except yaml.YAMLError as err:
        raise ParamsError(f"{path}: not valid YAML: {err}") from err
    if not isinstance(data, dict):
        raise ParamsError(f"{path}: top level must be a mapping, got {type(data).__name__}")
    bases = data.pop("extends", None)
    if bases is None:
        return data
    bases = [bases] if isinstance(bases, str) else bases
    if not isinstance(bases, list) or not bases or not all(isinstance(b, str) for b in bases):
        raise ParamsError(f"{path}: extends must name a params file or a list of them, got {bases!r}")
    loaded: dict[str, Any] = {}
    for base in bases:
        loaded = merged(loaded, _load_params_file(path.parent / base, (*seen, path.resolve())))
    return merged(loaded, data)


def read_params(path: str | Path, overrides: list[str] | None = None) -> dict[str, Any]:
    """Load a YAML params file and apply `key.sub=value` overrides (values parsed as YAML).

    A file may start from another: `extends: ../params.yaml` (relative to the file) loads that one first and puts
    this file's values on top, mappings merged key by key; a mapping tagged `!replace` replaces the base's whole.
    `extends: [a.yaml, b.yaml]` merges b on top of a, then this file on top of both.
    """
    path = Path(path)
    data = _load_params_file(path)
    for item in overrides or []:
        key, sep, raw = item.partition("=")
        if not sep:
            raise ParamsError(f"override {item!r} is not of the form key.sub=value")
        set_dotted(data, key, yaml.safe_load(raw), f"{path}: override {item!r}")
    data["_source"] = str(path)
    return data


def set_dotted(params: dict[str, Any], key: str, value: Any, where: str) -> None:
    """Set params[a][b]...[leaf] = value for key "a.b....leaf"; every section and the leaf must exist already
    (ParamsError naming `where` and the key otherwise)."""
    node = params
    *parents, leaf = key.split(".")
    for part in parents:
        if not isinstance(node.get(part), dict):
            raise ParamsError(f"{where}: {part!r} of {key!r} is not a params section")
        node = node[part]
    if leaf not in node:
        raise ParamsError(f"{where}: unknown key {key!r}")
    node[leaf] = value


def load_section(params: dict[str, Any], name: str, cls: type[T]) -> T:
    """Build dataclass `cls` from `params[name]`, validating keys and types."""
    source = params.get("_source", "<params>")
    if name not in params:
        raise ParamsError(f"{source}: missing section {name!r}")
    return _build(cls, params[name], name, source)


def params_hash(params: dict[str, Any], sections: list[str]) -> str:
    """Stable short hash of the named sections (what a stage's output depends on)."""
    blob = json.dumps({s: params.get(s) for s in sections}, sort_keys=True, default=str)
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def without_keys(params: dict[str, Any], section: str, keys: tuple[str, ...]) -> dict[str, Any]:
    """`params` with `keys` left out of `section` (what a stage's output does not depend on, e.g. where it runs)."""
    return {**params, section: {k: v for k, v in params[section].items() if k not in keys}}


def _build(tp: Any, value: Any, key: str, source: str) -> Any:
    origin = typing.get_origin(tp)
    if dataclasses.is_dataclass(tp):
        if not isinstance(value, dict):
            raise ParamsError(f"{source}: {key} must be a mapping, got {value!r}")
        hints = typing.get_type_hints(tp)
        fields = {f.name: f for f in dataclasses.fields(tp)}
        unknown = sorted(set(value) - set(fields))
        if unknown:
            raise ParamsError(f"{source}: unknown key {key}.{unknown[0]} (expected one of {sorted(fields)})")
        kwargs = {}
        for fname, field in fields.items():
            if fname in value:
                kwargs[fname] = _build(hints[fname], value[fname], f"{key}.{fname}", source)
            elif field.default is dataclasses.MISSING and field.default_factory is dataclasses.MISSING:
                raise ParamsError(f"{source}: missing key {key}.{fname}")
        obj = tp(**kwargs)
        check = getattr(obj, "validate", None)
        if check is not None:
            try:
                check()
            except ValueError as err:
                raise ParamsError(f"{source}: {key}: {err}") from err
        return obj
    if origin is typing.Union or origin is types.UnionType:
        args = typing.get_args(tp)
        if value is None and type(None) in args:
            return None
        inner = [a for a in args if a is not type(None)]
        return _build(inner[0], value, key, source)
    if origin is typing.Literal:
        if value not in typing.get_args(tp):
            raise ParamsError(f"{source}: {key} must be one of {typing.get_args(tp)}, got {value!r}")
        return value
    if origin in (tuple, list):
        if not isinstance(value, (list, tuple)):
            raise ParamsError(f"{source}: {key} must be a list, got {value!r}")
        args = typing.get_args(tp)
        if origin is tuple and args and args[-1] is not Ellipsis:
            if len(value) != len(args):
                raise ParamsError(f"{source}: {key} must have {len(args)} entries, got {len(value)}")
            return tuple(_build(a, v, f"{key}[{i}]", source) for i, (a, v) in enumerate(zip(args, value)))
        item = args[0] if args else Any
        built = [_build(item, v, f"{key}[{i}]", source) for i, v in enumerate(value)]
        return tuple(built) if origin is tuple else built
    if origin is dict:
        if not isinstance(value, dict):
            raise ParamsError(f"{source}: {key} must be a mapping, got {value!r}")
        _, item = typing.get_args(tp)
        return {k: _build(item, v, f"{key}.{k}", source) for k, v in value.items()}
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ParamsError(f"{source}: {key} must be a number, got {value!r}")
        return float(value)
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ParamsError(f"{source}: {key} must be an integer, got {value!r}")
        return value
    if tp is bool:
        if not isinstance(value, bool):
            raise ParamsError(f"{source}: {key} must be true or false, got {value!r}")
        return value
    if tp is str:
        if not isinstance(value, str):
            raise ParamsError(f"{source}: {key} must be a string, got {value!r}")
        return value
    return value
