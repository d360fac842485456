"""Field helpers of the configuration dataclasses: ranges and choices in each field's metadata,
checked on construction (``_Checked``) and by the loader."""

from __future__ import annotations

import dataclasses
import math
import re
from dataclasses import field
from typing import Any

from dran_edge.errors import ConfigError

_NAME_RE = re.compile(r"^[A-Za-z0-9_.-]{1,15}$")


def _f(default: Any, *, lo: float | None = None, hi: float | None = None,
       choices: tuple | None = None, lo_open: bool = False) -> Any:
    """A dataclass field with its valid range (``lo <= v <= hi``; ``lo < v`` if ``lo_open``)."""
    meta = {"lo": lo, "hi": hi, "choices": choices, "lo_open": lo_open}
    if isinstance(default, (list, dict, tuple)) and not isinstance(default, tuple):
        return field(default_factory=lambda: default, metadata=meta)
    if dataclasses.is_dataclass(default):
        return field(default_factory=lambda d=default: d, metadata=meta)
    return field(default=default, metadata=meta)


def _check_value(value: Any, meta: dict, key: str) -> None:
    """Range / choice check of one scalar field; raises ConfigError naming ``key``."""
    if not meta:
        return
    choices = meta.get("choices")
    if choices is not None and value not in choices:
        raise ConfigError(f"{key}: expected one of {', '.join(map(repr, choices))}, got {value!r}")
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
