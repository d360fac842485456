"""Faults of a rehearsal: what they are, how they are written, when they act (docs/rehearsal.md).

A fault file (YAML)::

    faults:
      - {kind: kill, robot: dingo3, at_s: 60, restart_s: 80}      # kill -9, start again
      - {kind: partition, robots: [dingo2, dingo5], at_s: 60, end_s: 90}
      - {kind: silent, robot: dingo4, at_s: 30, end_s: 50}         # radio off
      - {kind: loss, link: [dingo1, dingo2], probability: 0.3, at_s: 0, end_s: 180}
      - {kind: clock_step, robot: dingo2, at_s: 40, step_s: 30}    # wall clock jumps 30 s

Robots are named by name or id; times are mission seconds from the run's start. The same
faults as flags: ``--kill ROBOT:AT_S:RESTART_S``, ``--partition R[,R...]:AT_S:END_S``,
``--silent ROBOT:AT_S:END_S``, ``--loss A-B:P[:AT_S:END_S]``, ``--clock-step ROBOT:AT_S:STEP_S``.

:func:`actions` turns faults into a time-ordered list of :class:`Action` (start and end of
each), which the fleet applies when the mission clock reaches them.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from dran_edge.errors import InputError

KINDS = ("kill", "partition", "silent", "loss", "clock_step")
_KEYS = {
    "kill": ({"kind", "robot", "at_s", "restart_s"}, {"restart_s"}),
    "partition": ({"kind", "robots", "at_s", "end_s"}, set()),
    "silent": ({"kind", "robot", "at_s", "end_s"}, set()),
    "loss": ({"kind", "link", "probability", "at_s", "end_s"}, {"at_s", "end_s"}),
    "clock_step": ({"kind", "robot", "at_s", "step_s"}, set()),
}


@dataclass(frozen=True)
class Fault:
    """One fault; ``robots`` are robot ids (one for kill/silent/clock_step, the group for a
    partition, the two ends for loss)."""

    kind: str
    robots: tuple[int, ...]
    at_s: float
    end_s: float | None = None
    """kill: restart time (None: never restarted); partition/silent/loss: when it ends (loss:
    None, until the end)."""
    probability: float = 0.0
    step_s: float = 0.0

    def describe(self, names: dict[int, str]) -> str:
        who = ",".join(names.get(r, str(r)) for r in self.robots)
        if self.kind == "kill":
            return f"kill -9 {who} at {self.at_s:g} s" + (
                f", restart at {self.end_s:g} s" if self.end_s is not None else ""
            )
        if self.kind == "loss":
            until = "the end" if self.end_s is None else f"{self.end_s:g} s"
            return f"loss {self.probability:g} on {who} from {self.at_s:g} s to {until}"
        if self.kind == "clock_step":
            return f"clock step of {self.step_s:+g} s on {who} at {self.at_s:g} s"
        return f"{self.kind} {who} from {self.at_s:g} s to {self.end_s:g} s"


@dataclass(frozen=True)
class Action:
    """``start`` or ``end`` of fault number ``index`` at mission second ``t_s``."""

    t_s: float
    what: str
    index: int
    fault: Fault


def _robot(value: Any, ids: dict[str, int], where: str) -> int:
    key = str(value)
    if key in ids:
        return ids[key]
    if key.isdigit() and int(key) in ids.values():
        return int(key)
    raise InputError(f"{where}: no robot {value!r} in this run (robots: {', '.join(sorted(ids))})")


def _number(value: Any, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise InputError(f"{where}: expected a number, got {value!r}")
    return float(value)


def fault_from_dict(d: Any, ids: dict[str, int], where: str, mission_s: float) -> Fault:
    """One entry of a fault file; InputError naming ``where`` and the key on any problem."""
    if not isinstance(d, dict) or d.get("kind") not in KINDS:
        raise InputError(
            f"{where}: expected a mapping with kind one of {', '.join(KINDS)}, got {d!r}"
        )
    kind = d["kind"]
    allowed, optional = _KEYS[kind]
    unknown = set(d) - allowed
    missing = allowed - optional - set(d)
    if unknown or missing:
        raise InputError(
            f"{where}: {kind} takes {', '.join(sorted(allowed - {'kind'}))}"
            + (f"; unknown {sorted(unknown)}" if unknown else "")
            + (f"; missing {sorted(missing)}" if missing else "")
        )
    at = _number(d.get("at_s", 0.0), f"{where}.at_s")
    if kind == "kill":
        restart = d.get("restart_s")
        f = Fault(
            kind,
            (_robot(d["robot"], ids, f"{where}.robot"),),
            at,
            None if restart is None else _number(restart, f"{where}.restart_s"),
        )
    elif kind == "partition":
        group = d["robots"]
        if not isinstance(group, list) or not group:
            raise InputError(f"{where}.robots: expected a list of robots, got {group!r}")
        robots = tuple(sorted({_robot(r, ids, f"{where}.robots") for r in group}))
        if len(robots) >= len(ids):
            raise InputError(f"{where}.robots: a partition needs robots on both sides")
        f = Fault(kind, robots, at, _number(d["end_s"], f"{where}.end_s"))
    elif kind == "silent":
        f = Fault(
            kind,
            (_robot(d["robot"], ids, f"{where}.robot"),),
            at,
            _number(d["end_s"], f"{where}.end_s"),
        )
    elif kind == "loss":
        link = d["link"]
        if not isinstance(link, list) or len(link) != 2:
            raise InputError(f"{where}.link: expected two robots, got {link!r}")
        ends = tuple(_robot(r, ids, f"{where}.link") for r in link)
        if ends[0] == ends[1]:
            raise InputError(f"{where}.link: expected two different robots, got {link!r}")
        p = _number(d["probability"], f"{where}.probability")
        if not 0.0 < p <= 1.0:
            raise InputError(f"{where}.probability: expected 0 < p <= 1, got {p}")
        end = d.get("end_s")
        f = Fault(kind, ends, at, None if end is None else _number(end, f"{where}.end_s"), p)
    else:
        f = Fault(
            kind,
            (_robot(d["robot"], ids, f"{where}.robot"),),
            at,
            step_s=_number(d["step_s"], f"{where}.step_s"),
        )
    if at < 0 or (f.end_s is not None and f.end_s <= at):
        raise InputError(f"{where}: expected 0 <= at_s < the end/restart time, got {d!r}")
    return f


def load_faults(path: str | Path, ids: dict[str, int], mission_s: float) -> list[Fault]:
    """A fault file (see the module docstring)."""
    import yaml

    p = Path(path)
    try:
        data = yaml.safe_load(p.read_text(encoding="utf-8"))
    except OSError as exc:
        raise InputError(f"cannot read the fault file: {exc.strerror}", path=str(p)) from None
    except yaml.YAMLError as exc:
        raise InputError(f"not valid YAML: {exc}", path=str(p)) from None
    if (
        not isinstance(data, dict)
        or set(data) != {"faults"}
        or not isinstance(data["faults"], list)
    ):
        raise InputError("expected a mapping with one key, 'faults', holding a list", path=str(p))
    try:
        return [
            fault_from_dict(d, ids, f"faults[{i}]", mission_s) for i, d in enumerate(data["faults"])
        ]
    except InputError as exc:
        raise InputError(str(exc), path=str(p)) from None


def _split(text: str, flag: str, n: tuple[int, ...]) -> list[str]:
    parts = text.split(":")
    if len(parts) not in n:
        raise InputError(f"{flag}: cannot read {text!r} (see 'dran-edge rehearse --help')")
    return parts


def faults_from_flags(
    *,
    kill=(),
    partition=(),
    silent=(),
    loss=(),
    clock_step=(),
    ids: dict[str, int],
    mission_s: float,
) -> list[Fault]:
    """The faults of the command-line flags (formats in the module docstring)."""
    out = []
    for t in kill:
        p = _split(t, "--kill", (2, 3))
        d = {"kind": "kill", "robot": p[0], "at_s": _flt(p[1], "--kill")}
        if len(p) == 3:
            d["restart_s"] = _flt(p[2], "--kill")
        out.append(fault_from_dict(d, ids, f"--kill {t}", mission_s))
    for t in partition:
        p = _split(t, "--partition", (3,))
        out.append(
            fault_from_dict(
                {
                    "kind": "partition",
                    "robots": p[0].split(","),
                    "at_s": _flt(p[1], "--partition"),
                    "end_s": _flt(p[2], "--partition"),
                },
                ids,
                f"--partition {t}",
                mission_s,
            )
        )
    for t in silent:
        p = _split(t, "--silent", (3,))
        out.append(
            fault_from_dict(
                {
                    "kind": "silent",
                    "robot": p[0],
                    "at_s": _flt(p[1], "--silent"),
                    "end_s": _flt(p[2], "--silent"),
                },
                ids,
                f"--silent {t}",
                mission_s,
            )
        )
    for t in loss:
        p = _split(t, "--loss", (2, 4))
        d = {"kind": "loss", "link": p[0].split("-"), "probability": _flt(p[1], "--loss")}
        if len(p) == 4:
            d.update(at_s=_flt(p[2], "--loss"), end_s=_flt(p[3], "--loss"))
        out.append(fault_from_dict(d, ids, f"--loss {t}", mission_s))
    for t in clock_step:
        p = _split(t, "--clock-step", (3,))
        out.append(
            fault_from_dict(
                {
                    "kind": "clock_step",
                    "robot": p[0],
                    "at_s": _flt(p[1], "--clock-step"),
                    "step_s": _flt(p[2], "--clock-step"),
                },
                ids,
                f"--clock-step {t}",
                mission_s,
            )
        )
    return out


def _flt(text: str, flag: str) -> float:
    try:
        return float(text)
    except ValueError:
        raise InputError(f"{flag}: expected a number, got {text!r}") from None


def actions(faults: list[Fault]) -> list[Action]:
    """Start and end of every fault, in time order (ends before starts at the same time)."""
    out = []
    for i, f in enumerate(faults):
        out.append(Action(f.at_s, "start", i, f))
        if f.end_s is not None and f.kind != "clock_step":
            out.append(Action(f.end_s, "end", i, f))
    return sorted(out, key=lambda a: (a.t_s, a.what != "end", a.index))
