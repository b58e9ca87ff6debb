"""Allowed ranges of the pipeline's numeric settings: declared beside each config field, checked in one place.

Every size, count, distance, rate and probability of a config dataclass carries its range in the field's
metadata, next to its default and its docstring::

    k: int = field(default=9, metadata=within(1, 64))  # its docstring follows, as for any field

The dataclass's ``__post_init__`` calls :func:`check_bounds`, the one place ranges are enforced. It checks
every field that declares one: a number, each number of a tuple (``grid_cells``), each value of a mapping
at any depth (``class_recall.car``); ``None`` (an optional setting left unset) is not checked. A value
outside raises :class:`~leap_core.errors.ConfigError` naming the field, the value and the range:
``k: must be in [1, 64], got 1000000000`` (``leap_core.config.config_from_dict`` prefixes the field's
absolute path: ``pipeline.smoothing.k``).

Why upper bounds: a setting's value sizes memory or time somewhere (``smoothing.k`` neighbours per voxel
are queried and mixed per chunk; ``fusion.chunk_points`` points are reduced at once; a voxel or grid cell
far smaller than a LiDAR's precision multiplies the cells), so an absurd value must be refused where the
config is read, with the field named, not found out by a worker running out of memory. The ranges are
wide: every value a study or preset of this project used lies inside. :func:`bounds_rows` lists them for
docs/METHOD.md (section F, "Allowed ranges").
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from typing import Any

from leap_core.errors import ConfigError

SEED_MAX = 2**32 - 1
"""Largest seed a config takes: any 32-bit unsigned value (numpy's and torch's seeding take them all)."""

BOUND_KEY = "leap_bound"
"""The key of a field's :class:`Bound` in its ``dataclasses.field(metadata=...)``."""


def _number_text(value: float) -> str:
    """``64``, ``0.01``, ``1e-07``, ``20000000``: integers as integers, other numbers as ``%g``."""
    if isinstance(value, int) or (math.isfinite(value) and value == int(value) and abs(value) < 1e15):
        return str(int(value))
    return f"{value:g}"


@dataclass(frozen=True)
class Bound:
    """The allowed values of one numeric setting: ``low ≤ v ≤ high`` (``<`` on an open end), or one of
    ``also``."""

    low: float
    high: float
    low_open: bool = False
    """``low`` itself is not allowed."""
    high_open: bool = False
    """``high`` itself is not allowed."""
    unit: str = ""
    """Shown after the range (``m``, ``px``, ``nats``)."""
    also: tuple[float, ...] = ()
    """Values allowed outside the range, each with a meaning of its own (``-1`` = every core)."""

    def __post_init__(self) -> None:
        if not self.low <= self.high:
            raise ValueError(f"a bound needs low <= high, got {self.low}, {self.high}")

    def allows(self, value: float) -> bool:
        """Whether ``value`` lies in the range (NaN never does) or is one of :attr:`also`."""
        if value in self.also:
            return True
        above = value > self.low if self.low_open else value >= self.low
        below = value < self.high if self.high_open else value <= self.high
        return bool(above and below)

    def text(self) -> str:
        """``[1, 64]``, ``(0, 1]``, ``[0.01, 10] m``, ``[1, 256] or -1``."""
        out = (
            f"{'(' if self.low_open else '['}{_number_text(self.low)}, "
            f"{_number_text(self.high)}{')' if self.high_open else ']'}"
        )
        if self.unit:
            out += f" {self.unit}"
        if self.also:
            out += " or " + " or ".join(_number_text(v) for v in self.also)
        return out


def within(
    low: float,
    high: float,
    *,
    low_open: bool = False,
    high_open: bool = False,
    unit: str = "",
    also: tuple[float, ...] = (),
) -> dict[str, Bound]:
    """A field's metadata declaring its range: ``field(default=9, metadata=within(1, 64))``."""
    return {BOUND_KEY: Bound(low, high, low_open, high_open, unit, also)}


def field_bound(config: Any, name: str) -> Bound | None:
    """The :class:`Bound` of field ``name`` of the config dataclass (or instance) ``config``, or None."""
    for f in dataclasses.fields(config):
        if f.name == name:
            bound = f.metadata.get(BOUND_KEY)
            return bound if isinstance(bound, Bound) else None
    return None


def _numbers(value: Any, path: tuple[str, ...]) -> Iterator[tuple[tuple[str, ...], Any]]:
    """``(field path, number)`` of every number a field's value holds: itself, a tuple's items (at the
    field's path), a mapping's values (at ``path + (key,)``), at any depth; None holds none."""
    if value is None:
        return
    if isinstance(value, Mapping):
        for key, item in value.items():
            yield from _numbers(item, (*path, str(key)))
    elif isinstance(value, (tuple, list)):
        for item in value:
            yield from _numbers(item, path)
    else:
        yield path, value


def _value_text(value: Any, limit: int = 40) -> str:
    text = repr(value)
    return text if len(text) <= limit else text[:limit] + "..."


def check_bounds(config: Any) -> None:
    """Check every field of the config dataclass instance ``config`` that declares a :class:`Bound`.

    Raises:
        ConfigError: ``field`` = the field's path relative to ``config`` (``("k",)``,
            ``("class_recall", "car")``), message ``must be in <range>, got <value>``.
    """
    for f in dataclasses.fields(config):
        bound = f.metadata.get(BOUND_KEY)
        if not isinstance(bound, Bound):
            continue
        for path, number in _numbers(getattr(config, f.name), (f.name,)):
            if isinstance(number, bool) or not isinstance(number, (int, float)):
                raise ConfigError(
                    f"must be a number in {bound.text()}, got {_value_text(number)}", field=path
                )
            if not bound.allows(number):
                raise ConfigError(f"must be in {bound.text()}, got {_value_text(number)}", field=path)


def bounds_rows(config_type: type, prefix: str = "") -> list[tuple[str, Bound]]:
    """``(dotted setting path, bound)`` of every bounded field of ``config_type`` and of the config
    dataclasses its fields default to (``consistency.backbone.channels``), in field order."""
    rows: list[tuple[str, Bound]] = []
    instance = config_type()
    for f in dataclasses.fields(config_type):
        bound = f.metadata.get(BOUND_KEY)
        if isinstance(bound, Bound):
            rows.append((f"{prefix}{f.name}", bound))
            continue
        value = getattr(instance, f.name)
        if dataclasses.is_dataclass(value) and not isinstance(value, type):
            rows += bounds_rows(type(value), f"{prefix}{f.name}.")
    return rows


__all__ = ["BOUND_KEY", "SEED_MAX", "Bound", "bounds_rows", "check_bounds", "field_bound", "within"]
