"""Physical parameters from TOML data files into frozen, validated dataclasses.

Every parameter of the simulator lives in a data file under ``gelsim/assets/`` with its
unit in the key (``pitch_mm``, ``force_n``, ``sigma_px``). This module turns a
parsed TOML table into a frozen dataclass:

* unknown keys are rejected (a typo must not silently fall back to a default);
* missing keys without a default are rejected;
* nested dataclasses, lists of dataclasses and fixed-length tuples are built
  recursively;
* numeric ranges declared with :func:`param` are enforced.

Errors are :class:`~gelsim.errors.GelsimError` with the file and dotted key.
"""
from __future__ import annotations

import dataclasses
import importlib.resources
import math
import tomllib
import types
import typing
from pathlib import Path
from typing import Any, TypeVar

from .errors import GelsimError

T = TypeVar("T")


def package_dir(package: str, name: str) -> Path:
    """The data folder ``name`` shipped inside ``package``, found through importlib.resources (so an
    installed wheel finds it wherever it lives, not only a checkout). Packages are installed unzipped
    (a wheel's files lie on disk), so the folder is a real directory the loaders can glob."""
    folder = importlib.resources.files(package) / name
    path = Path(str(folder))
    if not path.is_dir():
        raise GelsimError(f"{package}'s data folder {name}/ is missing from {path.parent}; reinstall gelsim "
                          "(make install, or pip install the wheel)")
    return path


#: gelsim/assets: every physical parameter's data file (fabrics, sensors, fidelity levels, motions, tables).
ASSETS_DIR = package_dir("gelsim", "assets")


def param(default: Any = dataclasses.MISSING, *, lo: float | None = None, hi: float | None = None,
          lo_open: bool = False, doc: str = "") -> Any:
    """A dataclass field with an allowed range ``[lo, hi]`` (``(lo, hi]`` if ``lo_open``)."""
    meta = {"lo": lo, "hi": hi, "lo_open": lo_open, "doc": doc}
    if default is dataclasses.MISSING:
        return dataclasses.field(metadata=meta)
    if isinstance(default, (list, dict, set)):
        raise TypeError("use an immutable default (tuple) for parameters")
    return dataclasses.field(default=default, metadata=meta)


def load_toml(path: str | Path) -> dict:
    """Parse a TOML file; a missing or malformed file is a GelsimError naming it."""
    path = Path(path)
    try:
        with path.open("rb") as f:
            return tomllib.load(f)
    except FileNotFoundError:
        raise GelsimError(f"{path}: file not found; check the path") from None
    except tomllib.TOMLDecodeError as e:
        raise GelsimError(f"{path}: malformed TOML ({e}); fix the file's syntax") from None


def _check_number(value: Any, f: dataclasses.Field, where: str) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return
    if not math.isfinite(value):
        raise GelsimError(f"{where}: {value} is not a finite number; give a finite value")
    lo, hi = f.metadata.get("lo"), f.metadata.get("hi")
    lo_open = f.metadata.get("lo_open", False)
    if lo is not None and (value < lo or (lo_open and value == lo)):
        bound = f"> {lo}" if lo_open else f">= {lo}"
        raise GelsimError(f"{where}: {value} is out of range; it must be {bound}"
                          + (f" and <= {hi}" if hi is not None else ""))
    if hi is not None and value > hi:
        raise GelsimError(f"{where}: {value} is out of range; it must be <= {hi}"
                          + (f" and >= {lo}" if lo is not None else ""))


def _convert(tp: Any, value: Any, where: str, field: dataclasses.Field | None) -> Any:
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        non_none = [a for a in args if a is not type(None)]
        return _convert(non_none[0], value, where, field)
    if dataclasses.is_dataclass(tp):
        if not isinstance(value, dict):
            raise GelsimError(f"{where}: expected a table, got {type(value).__name__}")
        return build(tp, value, where)
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            raise GelsimError(f"{where}: expected a list, got {type(value).__name__}")
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_convert(args[0], v, f"{where}[{i}]", field) for i, v in enumerate(value))
        if len(value) != len(args):
            raise GelsimError(f"{where}: expected {len(args)} values, got {len(value)}")
        return tuple(_convert(a, v, f"{where}[{i}]", field) for i, (a, v) in enumerate(zip(args, value)))
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise GelsimError(f"{where}: expected a number, got {value!r}")
        if field is not None:
            _check_number(value, field, where)
        return float(value)
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise GelsimError(f"{where}: expected an integer, got {value!r}")
        if field is not None:
            _check_number(value, field, where)
        return value
    if tp is bool:
        if not isinstance(value, bool):
            raise GelsimError(f"{where}: expected true or false, got {value!r}")
        return value
    if tp is str:
        if not isinstance(value, str):
            raise GelsimError(f"{where}: expected a string, got {value!r}")
        return value
    if typing.get_origin(tp) is typing.Literal:
        if value not in args:
            raise GelsimError(f"{where}: {value!r} is not one of {', '.join(map(repr, args))}")
        return value
    return value


def build(cls: type[T], data: dict, where: str = "") -> T:
    """Build dataclass ``cls`` from a TOML table, validating keys, types and ranges."""
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
    unknown = sorted(set(data) - set(fields))
    if unknown:
        raise GelsimError(f"{where or cls.__name__}: unknown key {unknown[0]!r}; "
                          f"known keys are {', '.join(sorted(fields))}")
    kwargs = {}
    for name, f in fields.items():
        key = f"{where}.{name}" if where else name
        if name not in data:
            if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
                raise GelsimError(f"{key}: missing; add it to the file")
            continue
        kwargs[name] = _convert(hints[name], data[name], key, f)
    obj = cls(**kwargs)
    check = getattr(obj, "validate", None)
    if callable(check):
        check(where or cls.__name__)
    return obj


def check_ranges(obj: Any, where: str) -> None:
    """Re-check the declared ranges of a parameter dataclass built in code (not from a file)."""
    for f in dataclasses.fields(obj):
        value = getattr(obj, f.name)
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            _check_number(value, f, f"{where}: {f.name}")


def to_dict(obj: Any) -> Any:
    """Plain-data form of a parameter dataclass (tuples become lists), for JSON/TOML."""
    if dataclasses.is_dataclass(obj):
        return {f.name: to_dict(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, (list, tuple)):
        return [to_dict(v) for v in obj]
    return obj


def _split_comment(line: str) -> tuple[str, str | None]:
    """``line`` split at its first ``#`` outside double quotes: (before, comment or None)."""
    quoted = False
    for i, ch in enumerate(line):
        if ch == '"' and (i == 0 or line[i - 1] != "\\"):
            quoted = not quoted
        elif ch == "#" and not quoted:
            return line[:i], line[i + 1:].strip()
    return line, None


def toml_entries(path: str | Path) -> list[tuple[str, str, str | None]]:
    """Every ``key = value`` line of a TOML file, in order, as ``(dotted key, value text, comment)``:
    keys in a ``[section]`` are ``"section.key"``, keys of the n-th ``[[name]]`` table ``"name[n].key"``;
    the comment is the line's trailing one, continued by comment-only lines right below it that are
    indented past the line's start (None without one)."""
    out: list[tuple[str, str, str | None]] = []
    section, counts = "", {}
    last = None
    for line in Path(path).read_text().splitlines():
        s = line.strip()
        if last is not None and s.startswith("#") and len(line) - len(line.lstrip()) > 0:
            key, value, note = out[last]
            out[last] = (key, value, f"{note} {s.lstrip('#').strip()}".strip())
            continue
        last = None
        if s.startswith("[["):
            name = s.strip("[]").strip()
            counts[name] = counts.get(name, -1) + 1
            section = f"{name}[{counts[name]}]"
        elif s.startswith("["):
            section = s.strip("[]").strip()
        elif s and not s.startswith("#") and "=" in s:
            before, note = _split_comment(s)
            key, value = (t.strip() for t in before.split("=", 1))
            out.append((f"{section}.{key}" if section else key, value, note))
            if note is not None:
                last = len(out) - 1
    return out


def toml_comments(path: str | Path) -> dict[str, str]:
    """The trailing comments of a TOML file's ``key = value  # comment`` lines (with their continuation
    lines, :func:`toml_entries`), by dotted key (``"section.key"``; keys before any table: ``"key"``), for
    :func:`dump_toml` to keep them. Keys in arrays of tables (``[[lights]]``) and lines with a string
    value are skipped."""
    out: dict[str, str] = {}
    for key, value, note in toml_entries(path):
        if note is None or "[" in key or '"' in value:
            continue
        out[key] = note
    return out


def dump_toml(data: dict, header: str = "", comments: dict[str, str] | None = None) -> str:
    """Serialise nested plain data (as from :func:`to_dict`) to TOML text; ``comments`` (by dotted
    key, see :func:`toml_comments`) go after their keys' values."""
    comments = comments or {}
    def fmt(v: Any) -> str:
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, float):
            return repr(float(v))
        if isinstance(v, int):
            return str(v)
        if isinstance(v, str):
            return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
        if isinstance(v, (list, tuple)):
            return "[" + ", ".join(fmt(x) for x in v) + "]"
        raise TypeError(f"cannot write {type(v).__name__} to TOML")

    lines = [f"# {h}" if h else "#" for h in header.splitlines()] if header else []

    def emit(table: dict, prefix: str) -> None:
        scalars = {k: v for k, v in table.items() if not isinstance(v, dict)
                   and not (isinstance(v, list) and v and all(isinstance(x, dict) for x in v))}
        for k, v in scalars.items():
            note = comments.get(f"{prefix}.{k}" if prefix else k)
            lines.append(f"{k} = {fmt(v)}" + (f"  # {note}" if note else ""))
        for k, v in table.items():
            name = f"{prefix}.{k}" if prefix else k
            if isinstance(v, dict):
                lines.append("")
                lines.append(f"[{name}]")
                emit(v, name)
            elif isinstance(v, list) and v and all(isinstance(x, dict) for x in v):
                for item in v:
                    lines.append("")
                    lines.append(f"[[{name}]]")
                    emit(item, name)

    emit(data, "")
    return "\n".join(lines) + "\n"
