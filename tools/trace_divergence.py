#!/usr/bin/env python3
"""Where do two machines' replays of the same recorded run part? (docs/notes/arm64-check.md)

    tools/trace_divergence.py record RUN_DIR OUT.npz   # on each machine (x86-64, the arm64 root)
    tools/trace_divergence.py compare A.npz B.npz      # on either
    tools/trace_divergence.py compare A.npz B.npz --coarse 1e-9

``record`` wraps every function and method defined in dran_edge (imported under their own
module, the layers the replay uses) so that each call appends (name, hash of its arguments,
hash of its result) when it returns, then replays a copy of RUN_DIR with the golden options
(tests/golden_helpers.py). Hashes cover numpy arrays bit for bit, numbers, strings and
containers of them; other objects (the agents themselves) are not hashed. ``compare`` walks
both records over the functions traced on both machines and prints the first calls whose
arguments hashed equal but whose results did not: in return order, so the first one printed
is the innermost traced function in which the floating point parted. With ``--coarse RTOL``
the comparison ignores roundoff (each call also stores its floats' sums and the hash of
everything else): it prints the first call whose arguments agree to RTOL and whose result does
not, i.e. where a last-bit difference became a different decision, and where the call
sequences part (a branch taken on one machine only).

A development tool (slow: every call is hashed); not part of make test.
"""

from __future__ import annotations

import argparse
import hashlib
import importlib
import inspect
import pkgutil
import shutil
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

#: Layers the replay does not go through, or whose results carry paths and clocks.
SKIP_MODULES = (
    "dran_edge.cli",
    "dran_edge.viz",
    "dran_edge.ros",
    "dran_edge.rehearsal",
    "dran_edge.daemon",
    "dran_edge.experiments",
    "dran_edge.evaluation.plots",
)
#: Functions whose results differ between machines for reasons that are not arithmetic.
NOT_ARITHMETIC = {
    "dran_edge.blas.set_blas_threads",
    "dran_edge.replay.run._cpu_s",
    "dran_edge.config.loader.load_config",
    "dran_edge.formats.run_dir.Run.load_config",
}


def _feed(x: Any, d: Any) -> None:
    if isinstance(x, np.ndarray):
        if x.dtype == object:
            for v in x.ravel():
                _feed(v, d)
        else:
            d.update(np.ascontiguousarray(x).tobytes())
    elif isinstance(x, (bool, int, float, np.floating, np.integer)):
        d.update(repr(float(x)).encode())
    elif isinstance(x, (list, tuple)):
        for v in x:
            _feed(v, d)
    elif isinstance(x, dict):
        for k, v in x.items():
            _feed(k, d)
            _feed(v, d)
    elif hasattr(x, "__dataclass_fields__"):
        for k in x.__dataclass_fields__:
            _feed(getattr(x, k, None), d)
    elif isinstance(x, str):
        d.update(x.encode())
    elif isinstance(x, bytes):
        d.update(x)


def _coarse(x: Any, d: Any, acc: list[float]) -> None:
    """Like ``_feed`` but floats go to ``acc`` (compared with a tolerance) and only their shape
    and every other leaf to the hash: a fingerprint that roundoff does not change."""
    if isinstance(x, np.ndarray) and x.dtype.kind == "f":
        d.update(repr(x.shape).encode())
        acc.extend(x.ravel().tolist())
    elif isinstance(x, float):
        acc.append(x)
    elif isinstance(x, (list, tuple)):
        d.update(f"<{len(x)}".encode())
        for v in x:
            _coarse(v, d, acc)
    elif isinstance(x, dict):
        for k in sorted(x, key=repr):
            d.update(repr(k).encode())
            _coarse(x[k], d, acc)
    elif isinstance(x, np.ndarray) and x.dtype == object:
        for v in x.ravel():
            _coarse(v, d, acc)
    elif hasattr(x, "__dataclass_fields__"):
        for k in x.__dataclass_fields__:
            _coarse(getattr(x, k, None), d, acc)
    elif isinstance(x, (np.floating,)):
        acc.append(float(x))
    else:
        _feed(x, d)


def _fingerprint(x: Any) -> tuple[int, float, float]:
    """(hash of the non-float leaves and float shapes, Σ |f|, Σ f·(1 + i/n)) over the floats f."""
    d = hashlib.blake2b(digest_size=8)
    acc: list[float] = []
    _coarse(x, d, acc)
    f = np.asarray(acc, dtype=np.float64)
    f = np.where(np.isfinite(f), f, 0.0)
    w = 1.0 + np.arange(len(f)) / max(len(f), 1)
    return int.from_bytes(d.digest(), "little", signed=True), float(np.abs(f).sum()), float(f @ w)


def _digest(x: Any) -> int:
    d = hashlib.blake2b(digest_size=8)
    _feed(x, d)
    return int.from_bytes(d.digest(), "little", signed=True)


def _modules() -> list[Any]:
    import dran_edge

    names = {
        info.name
        for info in pkgutil.walk_packages(dran_edge.__path__, "dran_edge.")
        if not info.name.startswith(SKIP_MODULES)
    }
    # comms/ and perception/ are top-level folders in a checkout (an editable install maps
    # them into dran_edge; a wheel has them inside): walk them too, once
    for name in ("dran_edge.comms", "dran_edge.perception"):
        pkg = importlib.import_module(name)
        names.update(info.name for info in pkgutil.walk_packages(pkg.__path__, name + "."))
    return [importlib.import_module(n) for n in sorted(names)]


def _install_tracer(record: list[tuple[str, int, int]], coarse: list[tuple[Any, ...]]) -> int:
    """Replace dran_edge's functions and methods by recording wrappers; returns how many."""

    def wrap(name: str, f: Callable[..., Any]) -> Callable[..., Any]:
        def traced(*args: Any, **kwargs: Any) -> Any:
            before = _digest((args, kwargs))
            fp_before = _fingerprint((args, kwargs))
            result = f(*args, **kwargs)
            record.append((name, before, _digest(result)))
            coarse.append(fp_before + _fingerprint(result))
            return result

        return traced

    mods = _modules()
    own: dict[int, Callable[..., Any]] = {}
    for mod in mods:
        for n, f in vars(mod).items():
            if inspect.isfunction(f) and f.__module__ == mod.__name__:
                own[id(f)] = wrap(f"{mod.__name__}.{n}", f)
    for mod in mods:  # the defining module and every module that imported the function
        for n, f in list(vars(mod).items()):
            if id(f) in own:
                setattr(mod, n, own[id(f)])
    methods = 0
    for mod in mods:
        for cname, cls in list(vars(mod).items()):
            if inspect.isclass(cls) and cls.__module__ == mod.__name__:
                for n, f in list(vars(cls).items()):
                    if inspect.isfunction(f) and not n.startswith("__"):
                        setattr(cls, n, wrap(f"{mod.__name__}.{cname}.{n}", f))
                        methods += 1
    return len(own) + methods


def record(run_dir: Path, out: Path) -> None:
    from dran_edge.replay.run import ReplayOptions, replay_run

    calls: list[tuple[str, int, int]] = []
    coarse: list[tuple[Any, ...]] = []
    n = _install_tracer(calls, coarse)
    work = Path(tempfile.mkdtemp()) / "run"
    shutil.copytree(run_dir, work)
    report = replay_run(work, ReplayOptions(workers=1, settle_rounds=10)).report
    names = sorted({c[0] for c in calls})
    index = {nm: i for i, nm in enumerate(names)}
    np.savez_compressed(
        out,
        names=np.array(names),
        name=np.array([index[c[0]] for c in calls], dtype=np.int32),
        args=np.array([c[1] for c in calls], dtype=np.int64),
        result=np.array([c[2] for c in calls], dtype=np.int64),
        coarse_hash=np.array([(c[0], c[3]) for c in coarse], dtype=np.int64),
        coarse_sums=np.array([(c[1], c[2], c[4], c[5]) for c in coarse], dtype=np.float64),
    )
    print(f"{n} functions traced, {len(calls)} calls -> {out}")
    print(f"bytes_total {report['bytes_total']}  sr_ate {report.get('sr_ate')!r}")


def _load(path: Path) -> list[tuple[str, int, int]]:
    z = np.load(path)
    names = [str(s) for s in z["names"]]
    return [
        (names[i], int(a), int(r))
        for i, a, r in zip(z["name"], z["args"], z["result"], strict=True)
    ]


def compare(a_path: Path, b_path: Path, show: int) -> int:
    a, b = _load(a_path), _load(b_path)
    common = {c[0] for c in a} & {c[0] for c in b}
    a = [c for c in a if c[0] in common and c[0] not in NOT_ARITHMETIC]
    b = [c for c in b if c[0] in common and c[0] not in NOT_ARITHMETIC]
    found = 0
    for i, (x, y) in enumerate(zip(a, b)):
        if x[0] != y[0]:
            print(f"call {i}: the call sequences part ({x[0]} vs {y[0]})")
            return 1
        if x[1] == y[1] and x[2] != y[2]:
            print(f"call {i}: {x[0]}: same arguments, different result")
            found += 1
            if found >= show:
                break
    if not found and len(a) == len(b):
        print(f"identical: {len(a)} calls")
    return 1 if found else 0


def compare_coarse(a_path: Path, b_path: Path, show: int, rtol: float) -> int:
    """First calls whose arguments agree up to roundoff (same discrete leaves, float sums within
    ``rtol``) and whose results do not: where a roundoff difference became a different decision."""
    za, zb = np.load(a_path), np.load(b_path)
    na = [str(za["names"][i]) for i in za["name"]]
    nb = [str(zb["names"][i]) for i in zb["name"]]
    ha, hb, sa, sb = za["coarse_hash"], zb["coarse_hash"], za["coarse_sums"], zb["coarse_sums"]

    def close(x: np.ndarray, y: np.ndarray, ref: float) -> bool:  # (Σ|f|, Σ f·w) within rtol·ref
        scale = rtol * max(x[0], y[0], ref) + 1e-300
        return bool(np.all(np.abs(x - y) <= scale))

    found = 0
    for i in range(min(len(na), len(nb))):
        if na[i] != nb[i]:
            print(f"call {i}: the call sequences part ({na[i]} vs {nb[i]})")
            return 1
        if na[i] in NOT_ARITHMETIC:
            continue
        # a result's roundoff is relative to its arguments' size (a cancellation to ~0 is not
        # a real difference): the reference for the result is the larger of the two sums
        args_close = ha[i, 0] == hb[i, 0] and close(sa[i, :2], sb[i, :2], 0.0)
        result_close = ha[i, 1] == hb[i, 1] and close(sa[i, 2:], sb[i, 2:], sa[i, 0])
        if args_close and not result_close:
            what = (
                "discrete parts" if ha[i, 1] != hb[i, 1] else f"floats {sa[i, 2]!r} vs {sb[i, 2]!r}"
            )
            print(f"call {i}: {na[i]}: arguments equal up to roundoff, results differ ({what})")
            found += 1
            if found >= show:
                break
    if not found:
        print(f"equal up to rtol {rtol}: {min(len(na), len(nb))} calls")
    return 1 if found else 0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    sub = p.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("record", help="replay RUN_DIR with every dran_edge call hashed")
    r.add_argument("run_dir", type=Path)
    r.add_argument("out", type=Path, help="the record (.npz)")
    c = sub.add_parser("compare", help="first calls where two records part")
    c.add_argument("a", type=Path)
    c.add_argument("b", type=Path)
    c.add_argument("--show", type=int, default=10, help="how many parting calls to print")
    c.add_argument(
        "--coarse",
        type=float,
        metavar="RTOL",
        help="compare up to roundoff (float sums within RTOL): find the first call where a "
        "last-bit difference became a real one (a different branch, count or size)",
    )
    args = p.parse_args(argv)
    if args.cmd == "record":
        record(args.run_dir, args.out)
        return 0
    if args.coarse is not None:
        return compare_coarse(args.a, args.b, args.show, args.coarse)
    return compare(args.a, args.b, args.show)


if __name__ == "__main__":
    sys.exit(main())
