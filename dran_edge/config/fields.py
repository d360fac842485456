"""Field helpers of the configuration dataclasses: ranges and choices in each field's metadata,
checked on construction (``_Checked``) and by the loader."""

from __future__ import annotations

import dataclasses
import math
import re
import typing
from dataclasses import field
from enum import Enum
from typing import Any

from dran_edge.errors import ConfigError

_NAME_RE = re.compile(r"^[A-Za-z0-9_.-]{1,15}$")

_Choice = typing.TypeVar("_Choice", bound="StrChoice")


class StrChoice(str, Enum):
    """A choice among fixed strings, checked once where a config is loaded or built: members
    compare equal to their strings and print, format and serialise (JSON) as them."""

    def __str__(self) -> str:
        return str.__str__(self)

    def __format__(self, format_spec: str) -> str:
        return str.__format__(self, format_spec)

    @classmethod
    def parse(cls: type[_Choice], value: Any, key: str) -> _Choice:
        """The member named by ``value`` (a member or its string); ValueError naming ``key``,
        the bad value and the allowed ones otherwise."""
        try:
            return cls(value)
        except ValueError:
            allowed = ", ".join(repr(m.value) for m in cls)
            raise ValueError(f"{key}: expected one of {allowed}, got {value!r}") from None


class Residual(StrChoice):
    """The edge residual of paper eq. 2."""

    GEODESIC = "geodesic"
    """Log(T̃⁻¹ T_p⁻¹ T_q) ∈ se(d)."""
    CHORDAL = "chordal"
    """The entries of T̃⁻¹ T_p⁻¹ T_q − I (rotation and translation parts)."""


class RobustKernel(StrChoice):
    """A robust kernel ρ on squared whitened residual norms (``none``: least squares)."""

    NONE = "none"
    HUBER = "huber"
    CAUCHY = "cauchy"


def _f(
    default: Any,
    *,
    lo: float | None = None,
    hi: float | None = None,
    choices: tuple | None = None,
    lo_open: bool = False,
) -> Any:
    """A dataclass field with its valid range (``lo <= v <= hi``; ``lo < v`` if ``lo_open``)."""
    meta = {"lo": lo, "hi": hi, "choices": choices, "lo_open": lo_open}
    if isinstance(default, (list, dict, tuple)) and not isinstance(default, tuple):
        return field(default_factory=lambda: default, metadata=meta)
    if dataclasses.is_dataclass(default):
        frozen_default: Any = default
        return field(default_factory=lambda: frozen_default, metadata=meta)
    return field(default=default, metadata=meta)


def _check_value(value: Any, meta: dict, key: str) -> None:
    """Range / choice check of one scalar field; raises ConfigError naming ``key``."""
    if not meta:
        return
    choices = meta.get("choices")
    if choices is not None and value not in choices:
        allowed = ", ".join(repr(getattr(c, "value", c)) for c in choices)
        raise ConfigError(f"{key}: expected one of {allowed}, got {value!r}")
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        if isinstance(value, float) and not math.isfinite(value):
            raise ConfigError(f"{key}: expected a finite number, got {value!r}")
        lo, hi = meta.get("lo"), meta.get("hi")
        if lo is not None:
            if meta.get("lo_open") and not value > lo:
                raise ConfigError(f"{key}: expected a value > {lo}, got {value!r}")
            if not meta.get("lo_open") and not value >= lo:
                raise ConfigError(f"{key}: expected a value >= {lo}, got {value!r}")
        if hi is not None and not value <= hi:
            raise ConfigError(f"{key}: expected a value <= {hi}, got {value!r}")


def _validate_fields(obj: Any) -> None:
    for f in dataclasses.fields(obj):
        value = getattr(obj, f.name)
        if isinstance(f.default, StrChoice):
            # a string choice (from code) becomes its member, once, here
            _check_value(value, dict(f.metadata), f.name)
            object.__setattr__(obj, f.name, type(f.default)(value))
            continue
        if isinstance(value, tuple):
            for i, item in enumerate(value):
                if not dataclasses.is_dataclass(item):
                    _check_value(item, dict(f.metadata), f"{f.name}[{i}]")
        else:
            _check_value(value, dict(f.metadata), f.name)


class _Checked:
    """Mixin: validate field ranges on construction (also for configs built in code)."""

    def __post_init__(self) -> None:
        _validate_fields(self)
        self._check()

    def _check(self) -> None:
        """Cross-field checks; raise ConfigError naming the field."""
