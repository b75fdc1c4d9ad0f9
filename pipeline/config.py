"""Typed configuration: one frozen dataclass per stage, filled from defaults, a YAML file and --set.

`--set section.key=value` (nested: `nerf_fit.model.n_levels=8`) values are parsed as YAML scalars
and coerced to the field's declared type; unknown sections or keys are errors that list what exists.
Field documentation is the string literal written under each field (read from the source), which
`pag config --doc` prints.
"""
from __future__ import annotations

import ast
import dataclasses
import inspect
import re
import textwrap
import types
import typing
from pathlib import Path
from typing import Any, Literal, get_args, get_origin

import yaml


class ConfigError(ValueError):
    """A config file or --set override does not fit the declared config."""


@dataclasses.dataclass(frozen=True)
class RunConfig:
    """Settings of the run itself (section `run`)."""

    device: str = "auto"
    """torch device for the model stages: 'auto' ('cuda' where torch sees a GPU, else 'cpu'), 'cpu', 'cuda' (every
    GPU, one nerf_fit worker each) or 'cuda:N' (GPU N only)."""
    scheduler: str = ""
    """dask.distributed scheduler address for nerf_fit ('' = start a local cluster)."""
    progress: bool = True
    """show progress on stderr: bars on an interactive terminal, plain lines (one per unit of work, no
    carriage returns) when stderr is a pipe or a file; false = quiet (`--no-progress`)."""
    progress_interval_s: float = 2.0
    """when stderr is not a terminal, the least seconds between two progress lines of one task (the first
    and last unit of each phase always get a line); 0 = a line for every unit of work. Raise it for
    shorter logs of long rows."""

    def __post_init__(self) -> None:
        if not re.fullmatch(r"auto|cpu|cuda(:\d+)?", str(self.device)):
            raise ConfigError(f"run.device must be 'auto', 'cpu', 'cuda' or 'cuda:N', got {self.device!r}")
        if not self.progress_interval_s >= 0:
            raise ConfigError(f"run.progress_interval_s must be >= 0 seconds, got {self.progress_interval_s}")


def _coerce(value: Any, tp: Any, where: str) -> Any:
    origin = get_origin(tp)
    if tp is Any:
        return value
    if origin is Literal:
        allowed = get_args(tp)
        if value not in allowed:
            raise ConfigError(f"{where}: {value!r} is not one of {list(allowed)}")
        return value
    if origin in (typing.Union, types.UnionType):
        args = get_args(tp)
        if value is None and type(None) in args:
            return None
        errors = []
        for a in args:
            if a is type(None):
                continue
            try:
                return _coerce(value, a, where)
            except ConfigError as err:
                errors.append(str(err))
        raise ConfigError(f"{where}: {value!r} fits none of {args}")
    if origin in (tuple, list):
        if isinstance(value, str):
            value = [v.strip() for v in value.split(",") if v.strip()] if value else []
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{where}: expected a list, got {value!r}")
        args = get_args(tp)
        if origin is tuple and len(args) == 2 and args[1] is Ellipsis:
            return tuple(_coerce(v, args[0], where) for v in value)
        if origin is tuple and args:
            if len(args) != len(value):
                raise ConfigError(f"{where}: expected {len(args)} values, got {len(value)}")
            return tuple(_coerce(v, a, where) for v, a in zip(value, args))
        return origin(value)
    if dataclasses.is_dataclass(tp):
        if isinstance(value, tp):
            return value
        if not isinstance(value, dict):
            raise ConfigError(f"{where}: expected a mapping of {tp.__name__} fields, got {value!r}")
        return build(tp, value, where)
    if tp is bool:
        if isinstance(value, bool):
            return value
        if isinstance(value, str) and value.lower() in ("true", "false", "yes", "no", "1", "0", "on", "off"):
            return value.lower() in ("true", "yes", "1", "on")
        if isinstance(value, int) and value in (0, 1):
            return bool(value)
        raise ConfigError(f"{where}: expected true/false, got {value!r}")
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, (int, float, str)):
            raise ConfigError(f"{where}: expected an integer, got {value!r}")
        try:
            f = float(value)
        except ValueError:
            raise ConfigError(f"{where}: expected an integer, got {value!r}") from None
        if f != int(f):
            raise ConfigError(f"{where}: expected an integer, got {value!r}")
        return int(f)
    if tp is float:
        if isinstance(value, bool):
            raise ConfigError(f"{where}: expected a number, got {value!r}")
        try:
            return float(value)
        except (TypeError, ValueError):
            raise ConfigError(f"{where}: expected a number, got {value!r}") from None
    if tp is str:
        return "" if value is None else str(value)
    return value


def build(cls: type, values: dict[str, Any], where: str) -> Any:
    """Instantiate dataclass `cls` from a mapping, coercing types and rejecting unknown keys."""
    hints = typing.get_type_hints(cls)
    names = [f.name for f in dataclasses.fields(cls)]
    unknown = [k for k in values if k not in names]
    if unknown:
        raise ConfigError(f"{where}: unknown key(s) {unknown}; valid keys: {names}")
    kwargs = {k: _coerce(v, hints[k], f"{where}.{k}") for k, v in values.items()}
    try:
        return cls(**kwargs)
    except (TypeError, ValueError) as err:
        raise ConfigError(f"{where}: {err}") from err


def to_dict(obj: Any) -> Any:
    if dataclasses.is_dataclass(obj):
        return {f.name: to_dict(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, tuple):
        return [to_dict(v) for v in obj]
    return obj


def parse_set(items: list[str]) -> dict[str, Any]:
    """['a.b=1', 'a.c.d=x'] -> {'a': {'b': 1, 'c': {'d': 'x'}}} with YAML-parsed scalars."""
    out: dict[str, Any] = {}
    for item in items:
        if "=" not in item:
            raise ConfigError(f"--set {item!r}: expected section.key=value")
        key, raw = item.split("=", 1)
        parts = key.strip().split(".")
        if len(parts) < 2 or not all(parts):
            raise ConfigError(f"--set {item!r}: key must be section.key (e.g. synth.seed=3)")
        try:
            value = yaml.safe_load(raw) if raw.strip() else ""
        except yaml.YAMLError:
            value = raw
        node = out
        for p in parts[:-1]:
            node = node.setdefault(p, {})
            if not isinstance(node, dict):
                raise ConfigError(f"--set {item!r}: {p!r} is set both as a value and as a section")
        node[parts[-1]] = value
    return out


def merge(base: dict[str, Any], over: dict[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for k, v in over.items():
        out[k] = merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def load_file(path: Path | None) -> dict[str, Any]:
    if path is None:
        return {}
    if not path.is_file():
        raise ConfigError(f"config file {path} does not exist")
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as err:
        raise ConfigError(f"config file {path} is not valid YAML: {err}") from err
    if not isinstance(data, dict):
        raise ConfigError(f"config file {path}: expected a mapping of sections, got {type(data).__name__}")
    return data


def resolve(sections: dict[str, type], raw: dict[str, Any]) -> dict[str, Any]:
    """Build every section's dataclass from the merged raw mapping."""
    unknown = [k for k in raw if k not in sections]
    if unknown:
        raise ConfigError(f"unknown config section(s) {unknown}; sections: {sorted(sections)}")
    out = {}
    for name, cls in sections.items():
        values = raw.get(name) or {}
        if not isinstance(values, dict):
            raise ConfigError(f"section {name!r}: expected a mapping, got {values!r}")
        out[name] = build(cls, values, name)
    return out


def field_docs(cls: type) -> dict[str, str]:
    """Docstrings written under dataclass fields, read from the class source (for a class generated from
    another one, such as an override layer, the source of the class its `__docs_from__` names)."""
    try:
        src = textwrap.dedent(inspect.getsource(getattr(cls, "__docs_from__", cls)))
    except (OSError, TypeError):
        return {}
    tree = ast.parse(src)
    docs: dict[str, str] = {}
    body = tree.body[0].body if tree.body and isinstance(tree.body[0], ast.ClassDef) else []
    for prev, node in zip(body, body[1:]):
        if (isinstance(prev, ast.AnnAssign) and isinstance(prev.target, ast.Name)
                and isinstance(node, ast.Expr) and isinstance(node.value, ast.Constant)
                and isinstance(node.value.value, str)):
            docs[prev.target.id] = " ".join(node.value.value.split())
    return docs


def describe(section: str, cls: type, value: Any | None = None, indent: str = "") -> list[str]:
    """Human-readable lines: `section.field = value  # doc` for `pag config --doc`."""
    docs = field_docs(cls)
    value = cls() if value is None else value
    lines = []
    for f in dataclasses.fields(cls):
        v = getattr(value, f.name)
        if dataclasses.is_dataclass(v):
            lines += describe(f"{section}.{f.name}", type(v), v, indent)
            continue
        doc = docs.get(f.name, "")
        lines.append(f"{indent}{section}.{f.name} = {to_dict(v)!r}" + (f"    # {doc}" if doc else ""))
    return lines
