"""Delta entries: a value sent as its quantised change since the last value on the same link.

Bytes are the paper's headline number (Table 1), and in an iterative solver a separator moves a
little each round. A *delta entry* carries, instead of the whole value, the change ``d`` since
the value the receiver already holds for that key (docs/wire-format.md, flag ``0x02``):

- poses (separators, translation-stage init values): ``d = Log(T_base⁻¹ T)`` (dof values),
  rebuilt as ``T_base Exp(d̂)``;
- relaxed rotations (rotation-stage init values): ``d = R − R_base`` (d² values), rebuilt as
  ``R_base + d̂``.

``d`` is quantised with one shared power-of-two scale per entry: an exponent byte ``e`` and one
int8 per component, ``d̂ = 2^e q`` with ``|q| ≤ 127``, so each component is off by at most
``2^(e−1) ≤ max|d| / 254``. The sender keeps exactly what the receiver rebuilds (the decoded
absolute value, then each rebuilt delta), so quantisation errors are carried into the next delta
instead of accumulating (error feedback, as in DPCM).

Loss: every delta names the round of its base. The receiver applies it only when the value it
holds for that key is from that round; otherwise it drops the entry and counts it
(``DeltaDecoder.unresolved``). The sender falls back to an absolute value every
``absolute_every`` rounds per key, so a lost datagram costs at most that many rounds of a stale
anchor, exactly like a lost absolute value under the agent's resend period.

One ``DeltaEncoder`` per directed link on the sending side, one ``DeltaDecoder`` per directed
link on the receiving side. Pure (numpy and the geometry only); the codec calls them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from dran_edge import geometry as geo

#: Largest quantised component (int8, symmetric).
Q_MAX = 127
#: A change larger than this (any component, metres / radians / matrix entries) goes absolute:
#: the int8 grid would be coarser than 1 % of a metre or radian.
MAX_DELTA = 1.0
#: Exponent range of the scale byte (int8).
_E_MIN, _E_MAX = -127, 127

POSE = "pose"
LINEAR = "linear"


def quantise(d: np.ndarray) -> tuple[int, np.ndarray]:
    """``(e, q)`` with ``2^e q ≈ d``, ``q`` int8 in [−127, 127] (see the module docstring)."""
    d = np.asarray(d, dtype=np.float64).ravel()
    m = float(np.max(np.abs(d), initial=0.0))
    if m == 0.0:
        return _E_MIN, np.zeros(d.size, np.int8)
    e = min(max(math.ceil(math.log2(m / Q_MAX)), _E_MIN), _E_MAX)
    q = np.clip(np.rint(d / 2.0**e), -Q_MAX, Q_MAX).astype(np.int8)
    return e, q


def dequantise(e: int, q: np.ndarray) -> np.ndarray:
    return q.astype(np.float64) * 2.0**e


def difference(kind: str, base: np.ndarray, value: np.ndarray) -> np.ndarray:
    """The change from ``base`` to ``value`` in the entry's coordinates (flat)."""
    if kind == POSE:
        return geo.log(geo.between(base, value)).ravel()
    return (np.asarray(value, np.float64) - base).ravel()


def rebuild(kind: str, base: np.ndarray, d_hat: np.ndarray) -> np.ndarray:
    """``base ⊕ d̂``: what sender and receiver both hold after a delta entry."""
    if kind == POSE:
        return base @ geo.exp(d_hat)
    return base + d_hat.reshape(base.shape)


def value_bytes(n_components: int) -> int:
    """Bytes of one delta value: the exponent byte and one int8 per component."""
    return 1 + n_components


@dataclass
class DeltaEncoder:
    """Sender side of one directed link: the value the receiver holds per key."""

    absolute_every: int = 10
    """Rounds after which a key is sent absolute again (recovers from lost datagrams)."""
    held: dict = field(default_factory=dict)
    """key -> (value the receiver rebuilds, round it was sent, round of the last absolute)."""

    def plan(self, key: tuple, kind: str, value: np.ndarray, round_: int):
        """``None`` (send absolute) or ``(base_round, e, q, rebuilt)`` for a delta entry."""
        prev = self.held.get(key)
        if prev is None or round_ <= prev[1] or round_ - prev[2] >= self.absolute_every:
            return None
        base, base_round, _ = prev
        d = difference(kind, base, value)
        if not np.all(np.isfinite(d)) or np.max(np.abs(d), initial=0.0) > MAX_DELTA:
            return None
        e, q = quantise(d)
        return base_round, e, q, rebuild(kind, base, dequantise(e, q))

    def sent_absolute(self, key: tuple, decoded: np.ndarray, round_: int) -> None:
        self.held[key] = (decoded, round_, round_)

    def sent_delta(self, key: tuple, rebuilt: np.ndarray, round_: int) -> None:
        self.held[key] = (rebuilt, round_, self.held[key][2])


@dataclass
class DeltaDecoder:
    """Receiver side of one directed link: the last value held per key and its round."""

    held: dict = field(default_factory=dict)
    stamps: dict = field(default_factory=dict)
    """key -> stamp_ns carried by the key's absolute entries (delta entries omit it)."""
    unresolved: int = 0
    """Delta entries dropped because the base they name is not the one held (a lost or
    reordered datagram); the sender's next absolute value repairs the key."""

    def absolute(
        self, key: tuple, value: np.ndarray, round_: int, stamp_ns: int | None = None
    ) -> None:
        prev = self.held.get(key)
        if prev is None or round_ >= prev[1]:
            self.held[key] = (value, round_)
            if stamp_ns is not None:
                self.stamps[key] = stamp_ns

    def stamp(self, key: tuple) -> int:
        return self.stamps.get(key, 0)

    def resolve(
        self, key: tuple, kind: str, base_round: int, e: int, q: np.ndarray, round_: int
    ) -> np.ndarray | None:
        prev = self.held.get(key)
        if prev is None or prev[1] != base_round:
            self.unresolved += 1
            return None
        value = rebuild(kind, prev[0], dequantise(e, q))
        self.held[key] = (value, round_)
        return value
