"""One config engine for the project's TOML files (scenarios, bench files, dataset specs): typed reads of a table
that refuse unknown keys, dotted-path overrides, and a TOML writer.

Every error is one ``ConfigError`` (or the subclass a file kind names: ``ScenarioError``, ``BenchError``,
``DatasetError``) that says ``file: dotted.key: expected <form>, got <value>``; an error in what an override set
names the override first (``override KEY=VALUE on file: ...``; the command line shows ``--set KEY=VALUE: ...``), and a
misspelt key is named with the closest valid one (``did you mean 'exposure_s'?``, :func:`closest_key`).  Files are
data: nothing here imports or calls what a file names.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import tomllib
from typing import Any

import numpy as np

REQUIRED = object()  # default meaning "the key must be present"


class ConfigError(ValueError):
    """A TOML file (or override) whose content does not have the expected form.  ``override``: the dotted key of the
    override the error lies in (None: the file's own content); ``detail``: the message after that override's name."""

    override: str | None = None
    detail: str = ""


def closest_key(key: str, candidates) -> str | None:
    """The candidate (a string) that ``key`` most likely misspells, or None: difflib's closest at a ratio >= 0.75,
    except a sibling key that differs by one whole ``_``-separated word unlike its counterpart (``coeffs_x_px`` and
    ``coeffs_y_px``, ``initial_ra_deg`` and ``initial_dec_deg`` name different things; ``exposur_s`` misspells
    ``exposure_s``)."""
    if not isinstance(key, str):
        return None
    for match in difflib.get_close_matches(key, [c for c in candidates if isinstance(c, str)], n=3, cutoff=0.75):
        words, other = key.split("_"), match.split("_")
        differ = [(a, b) for a, b in zip(words, other, strict=False) if a != b] if len(words) == len(other) else []
        if len(differ) == 1 and difflib.SequenceMatcher(None, *differ[0]).ratio() <= 0.5:
            continue
        return match
    return None


def parse_toml(text: str, source: str, error: type[ConfigError] = ConfigError) -> dict:
    """The TOML document ``text`` as a dict; invalid TOML raises ``error`` naming ``source``."""
    try:
        return tomllib.loads(text)
    except (tomllib.TOMLDecodeError, RecursionError) as exc:
        raise error(f"{source}: not valid TOML: {exc}") from exc


def finite(x: float) -> bool:
    """``math.isfinite`` that calls an int too large for a float non-finite instead of raising OverflowError."""
    try:
        return math.isfinite(x)
    except OverflowError:
        return False


def is_number(x: Any) -> bool:
    return isinstance(x, int | float) and not isinstance(x, bool) and finite(x)


class Table:
    """Typed access to one TOML table that remembers which keys were read, to refuse the rest."""

    def __init__(self, data: Any, path: str, source: str, error: type[ConfigError] = ConfigError,
                 overrides: dict[str, str] | None = None):
        self.path, self.source, self.error = path, source, error
        # dotted key -> the override that set it, as its errors name it ("override motion.rate_dps=[0, 0, 5]")
        self.overrides = overrides or {}
        if not isinstance(data, dict):
            self.fail("", "a table", data)
        self.data, self.used = data, set()

    def where(self, key: str) -> str:
        return f"{self.path}.{key}" if self.path and key else (self.path or key or "(top level)")

    def located(self, key: str, text: str, where: str | None = None, unknown: bool = False) -> ConfigError:
        """The error ``text`` about ``key`` (or the place ``where``), located ``file: dotted.key: text``.  When an
        override set the key or a table above it (for an ``unknown`` key, also a key below it), the message opens
        naming it (``override KEY=VALUE on file: dotted.key: text``), and the error's ``override`` and ``detail``
        (the message after the override, as the command line shows it: ``--set KEY=VALUE: detail``) are set."""
        where = str(self.where(key) if where is None else where)
        for given, label in self.overrides.items():
            if where == given or where.startswith(given + ".") or (unknown and given.startswith(where + ".")):
                exc = self.error(f"{label} on {self.source}: {where}: {text}")
                exc.override, exc.detail = given, text if where == given else f"{where}: {text}"
                return exc
        return self.error(f"{self.source}: {where}: {text}")

    def fail(self, key: str, expected: str, got: Any = REQUIRED) -> None:
        found = "it is missing" if got is REQUIRED else f"got {got!r}"
        if got is REQUIRED:
            typo = closest_key(key, [k for k in self.data if k not in self.used])
            if typo is not None:
                found += f" (found {typo!r}: did you mean {key!r}?)"
        raise self.located(key, f"expected {expected}, {found}")

    def child(self, data: Any, path: str) -> Table:
        """A table below this one (same file, error kind and overrides)."""
        return Table(data, path, self.source, self.error, self.overrides)

    def raw(self, key: str, default: Any, expected: str) -> Any:
        """The value of ``key`` (``default`` when absent); a present ``None`` (an override) is always refused."""
        self.used.add(key)
        if key not in self.data:
            if default is REQUIRED:
                self.fail(key, expected or "a value")
            return default
        if self.data[key] is None:
            self.fail(key, expected or "a value", None)
        return self.data[key]

    def get(self, key: str, default: Any = None) -> Any:
        """The raw value of ``key`` (``default`` when absent), checked by the caller."""
        return self.raw(key, default, "")

    def integer_list(self, key: str, default: Any, low: int) -> Any:
        """A non-empty list of integers >= ``low`` (``default`` when absent)."""
        expected = f"a non-empty list of integers >= {low}"
        v = self.raw(key, default, expected)
        ok = isinstance(v, list) and v and all(isinstance(x, int) and not isinstance(x, bool) and x >= low for x in v)
        if v is not default and not ok:
            self.fail(key, expected, v)
        return v

    def number(self, key, default=REQUIRED, low=-math.inf, high=math.inf, *, low_open=False, integer=False):
        kind = "an integer" if integer else "a number"
        lb, hb = ("(" if low_open else "["), "]"
        expected = f"{kind} in {lb}{low:g}, {high:g}{hb}"
        v = self.raw(key, default, expected)
        if v is None:
            return None
        ok_type = isinstance(v, int) if integer else isinstance(v, int | float)
        if isinstance(v, bool) or not ok_type or not finite(v):
            self.fail(key, expected, v)
        if (v <= low if low_open else v < low) or v > high:
            self.fail(key, expected, v)
        return v

    def string(self, key, default=REQUIRED, choices: tuple[str, ...] | None = None) -> str:
        expected = f"one of {', '.join(repr(c) for c in choices)}" if choices else "a string"
        v = self.raw(key, default, expected)
        if not isinstance(v, str) or (choices and v not in choices):
            self.fail(key, expected, v)
        return v

    def vector(self, key, n: int | None, default=REQUIRED, low=-math.inf, high=math.inf) -> tuple[float, ...] | None:
        """A list of ``n`` finite numbers (any length when ``n`` is None), each in [``low``, ``high``]."""
        expected = f"a list of {n} numbers" if n else "a non-empty list of numbers"
        if low > -math.inf or high < math.inf:
            expected += f" in [{low:g}, {high:g}]"
        v = self.raw(key, default, expected)
        if v is None:
            return None
        if (
            not isinstance(v, list | tuple)
            or (len(v) != n if n else not v)
            or not all(is_number(x) and low <= x <= high for x in v)
        ):
            self.fail(key, expected, v)
        return tuple(float(x) for x in v)

    def matrix(self, key, default=REQUIRED) -> np.ndarray | None:
        expected = "a 3x3 matrix (a list of 3 lists of 3 numbers)"
        v = self.raw(key, default, expected)
        if v is None:
            return None
        try:
            m = np.array(v, dtype=np.float64)
        except (TypeError, ValueError, OverflowError):
            m = None
        if m is None or m.shape != (3, 3) or not np.all(np.isfinite(m)):
            self.fail(key, expected, v)
        return m

    def table(self, key, required: bool = False) -> Table | None:
        v = self.raw(key, REQUIRED if required else None, "a table")
        return None if v is None else self.child(v, self.where(key))

    def tables(self, key) -> list[Table]:
        v = self.raw(key, REQUIRED, "an array of tables ([[...]])")
        if not isinstance(v, list) or not v:
            self.fail(key, "a non-empty array of tables ([[...]])", v)
        return [self.child(item, f"{self.where(key)}.{i}") for i, item in enumerate(v)]

    def finish(self) -> None:
        extra = sorted(set(self.data) - self.used)
        if extra:
            allowed = ", ".join(sorted(self.used)) or "none"
            typo = closest_key(extra[0], self.used)
            guess = "" if typo is None else f"did you mean {typo!r}? "
            raise self.located(extra[0], f"unknown key ({guess}allowed here: {allowed})", unknown=True)

    def build(self, what: str, fn, *args, **kwargs):
        """Call a model constructor, turning its ValueError into this table's error, located in this table."""
        try:
            return fn(*args, **kwargs)
        except ConfigError:
            raise
        except ValueError as exc:
            raise self.located("", str(exc), where=self.path or what) from exc


def dataclass_from_table(tbl: Table | None, cls):
    """Fill a frozen dataclass of numbers / number vectors from a table whose keys are its field names."""
    if tbl is None:
        return cls()
    kwargs = {}
    for f in dataclasses.fields(cls):
        if not f.init:
            continue
        default = f.default if f.default is not dataclasses.MISSING else f.default_factory()
        if isinstance(default, tuple) and default and isinstance(default[0], tuple):
            value = tbl.matrix(f.name, None)
            value = None if value is None else tuple(map(tuple, value.tolist()))
        elif isinstance(default, tuple):
            value = tbl.vector(f.name, len(default), None)
        elif isinstance(default, bool):
            value = tbl.raw(f.name, None, "true or false")
            if value is not None and not isinstance(value, bool):
                tbl.fail(f.name, "true or false", value)
        else:
            value = tbl.number(f.name, None, integer=isinstance(default, int) and not isinstance(default, bool))
        if value is not None:
            kwargs[f.name] = value
    tbl.finish()
    try:
        return cls(**kwargs)
    except ValueError as exc:  # the model's checks name the field first: "adc_bits must be ..."
        word = str(exc).split(" ", 1)[0].rsplit(".", 1)[-1]
        key = word if word in {f.name for f in dataclasses.fields(cls)} else ""
        raise tbl.located(key, str(exc)) from exc


def apply_override(data: dict, dotted: str, value: Any, source: str, error: type[ConfigError] = ConfigError) -> None:
    """Set ``data[dotted]`` in place: tables by key (created when missing), arrays by index (``heads.0.width``)."""
    parts = dotted.split(".")
    if not dotted or not all(parts):
        raise error(f"{source}: override {dotted!r}: expected a dotted key path like 'motion.rate_dps'")
    node: Any = data
    for i, part in enumerate(parts):
        last = i == len(parts) - 1
        if isinstance(node, list):
            if not (part.isascii() and part.isdigit()) or int(part) >= len(node):
                where = ".".join(parts[:i])
                raise error(f"{source}: override {dotted!r}: {where} has {len(node)} items, no item {part!r}")
            if last:
                node[int(part)] = value
            else:
                node = node[int(part)]
        elif isinstance(node, dict):
            if last:
                node[part] = value
            else:
                node = node.setdefault(part, {})
        else:
            where = ".".join(parts[:i])
            raise error(f"{source}: override {dotted!r}: {where} is not a table")


def toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int | float):
        return repr(float(v) if isinstance(v, float) else int(v))
    if isinstance(v, str):
        return '"' + "".join(
            "\\" + c if c in '"\\' else f"\\u{ord(c):04x}" if ord(c) < 0x20 or ord(c) == 0x7F else c for c in v
        ) + '"'
    if isinstance(v, list | tuple):
        return "[" + ", ".join(toml_value(x) for x in v) + "]"
    raise TypeError(f"cannot write {type(v).__name__} to TOML")


def dump_toml(data: dict, prefix: str = "") -> str:
    """TOML text of ``data`` (scalars, arrays, tables, arrays of tables)."""
    lines, children = [], []
    for key, value in data.items():
        if isinstance(value, dict):
            children.append((key, value, False))
        elif isinstance(value, list) and value and all(isinstance(x, dict) for x in value):
            children.append((key, value, True))
        else:
            lines.append(f"{key} = {toml_value(value)}")
    out = "\n".join(lines)
    for key, value, is_array in children:
        name = f"{prefix}{key}"
        for item in value if is_array else [value]:
            header = f"[[{name}]]" if is_array else f"[{name}]"
            out += f"\n\n{header}\n" + dump_toml(item, f"{name}.")
    return out.strip("\n") + "\n" if not prefix else out.strip("\n")
