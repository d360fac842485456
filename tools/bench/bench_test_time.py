"""`make test`'s time against a baseline commit's, run side by side on this machine.

    .venv/bin/python tools/bench/bench_test_time.py                       # base 1ec7aa4, HEAD with auto workers
    .venv/bin/python tools/bench/bench_test_time.py --workers auto 4 --repeat 2
    .venv/bin/python tools/bench/bench_test_time.py --base REV --base-workers 0 --cold-types
    .venv/bin/python tools/bench/bench_test_time.py --quick   # HEAD against itself, one test file

The shared 2-core machines change speed by 2x within an hour, so an absolute time measured on
another day says little: this script checks the baseline commit out into a temporary git
worktree (with a copy of this checkout's .venv, the baseline installed into it in editable
mode), then runs the baseline's test command and this checkout's `make test` steps one after
the other, alternating the order on every repeat (ABBA), and prints each wall time and the
ratio of this checkout's median to the baseline's.

- Baseline: ``pytest -q -m "not slow and not hardware"`` in the worktree, with
  ``--base-workers`` pytest-xdist workers (default 0: in one process, as ``make test`` ran before
  pytest-xdist came in).
- This checkout: the steps of ``make test`` after setup, as the Makefile runs them — ``ruff
  check``, ``ruff format --check``, then ``mypy`` (with ``--cold-types`` from an empty cache, as
  on a fresh clone) in the background at nice 19 beside ``pytest -q $(PYTEST_PARALLEL) -m "not
  slow and not hardware"`` (the Makefile's pytest-xdist options) for each ``--workers`` W.
- ``--fresh-bytecode``: both arms with Python's default bytecode caching (an environment's
  PYTHONDONTWRITEBYTECODE removed), each run started from a tree without ``__pycache__``
  folders (outside .venv), as a fresh clone's first run on a default Python. Without it the
  caller's environment holds; where it sets PYTHONDONTWRITEBYTECODE, every process (each test
  worker, each ``dran-edge`` child process) compiles the repository's modules from source.

The default baseline, 1ec7aa4, is the last commit before the offline-bundle work (the commit
whose ``make test`` time the bundle must not worsen). A run whose tests fail is reported and
makes the script exit 1. One BLAS thread in every run, as the Makefile sets. ``--tests`` runs
only the named test files (relative to the repository) in both arms; ``--quick`` runs
tests/test_config.py of HEAD against itself with no lint or type check, to check the script.
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
DEFAULT_BASE = "1ec7aa4"
MARKERS = "not slow and not hardware"
LINT_PATHS = ["dran_edge", "comms", "perception", "tests", "tools"]


def _env(fresh_bytecode: bool = False) -> dict[str, str]:
    env = dict(os.environ)
    env["OPENBLAS_NUM_THREADS"] = "1"
    env["OMP_NUM_THREADS"] = "1"
    env.pop("PYTHONPATH", None)
    if fresh_bytecode:
        env.pop("PYTHONDONTWRITEBYTECODE", None)
    return env


def _clear_bytecode(tree: Path) -> None:
    """Remove the compiled modules (and pytest's rewritten test modules) under ``tree``, outside
    its .venv: the state of a fresh clone."""
    for d in tree.rglob("__pycache__"):
        if ".venv" not in d.relative_to(tree).parts:
            shutil.rmtree(d, ignore_errors=True)


def _run(cmd: list[str], cwd: Path, env: dict[str, str]) -> tuple[int, str, float]:
    t0 = time.perf_counter()
    p = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True)
    return p.returncode, p.stdout + p.stderr, time.perf_counter() - t0


def _summary(output: str) -> str:
    """pytest's last line: '839 passed, 4 skipped in 191.31s' without the time."""
    lines = [ln for ln in output.strip().splitlines() if re.search(r"\d+ (passed|failed)", ln)]
    if not lines:
        return "no pytest summary"
    return re.sub(r"\s+in [\d.]+s.*$", "", lines[-1].strip("= "))


def _failures(output: str, lines: int = 30) -> str:
    """What a failed step said: pytest's ``E`` and ``FAILED`` lines, else the output's end."""
    found = [ln for ln in output.splitlines() if ln.startswith(("E ", "FAILED", "ERROR"))]
    return "\n".join(found[:lines]) if found else output[-2000:]


def _pytest_args(workers: str, makefile: Path = REPO / "Makefile") -> list[str]:
    """The Makefile's PYTEST_PARALLEL with ``workers`` (nothing for 0: one process; a Makefile
    from before pytest-xdist: ``-n W --dist loadfile``)."""
    if workers in ("0", ""):
        return []
    for line in makefile.read_text().splitlines():
        if line.startswith("PYTEST_PARALLEL"):
            return line.split(":=", 1)[1].replace("$(PYTEST_WORKERS)", workers).split()
    return ["-n", workers, "--dist", "loadfile"]


def prepare_base(rev: str, workdir: Path) -> Path:
    """A worktree of ``rev`` with its own copy of this checkout's .venv, ``rev`` installed into it
    in editable mode (no network: no dependencies, no build isolation)."""
    tree = workdir / "base"
    subprocess.run(
        ["git", "-C", str(REPO), "worktree", "add", "--detach", str(tree), rev],
        check=True,
        capture_output=True,
    )
    shutil.copytree(REPO / ".venv", tree / ".venv", symlinks=True)
    subprocess.run(
        [str(tree / ".venv" / "bin" / "python"), "-m", "pip", "install", "-q"]
        + ["--no-deps", "--no-build-isolation", "-e", str(tree)],
        check=True,
        capture_output=True,
    )
    where = subprocess.run(
        [
            str(tree / ".venv" / "bin" / "python"),
            "-c",
            "import dran_edge; print(dran_edge.__file__)",
        ],
        cwd=tree,
        check=True,
        capture_output=True,
        text=True,
    ).stdout.strip()
    if not where.startswith(str(tree)):
        raise SystemExit(f"the baseline venv imports dran_edge from {where}, not from {tree}")
    return tree


def run_base(
    tree: Path, workers: str, tests: list[str], fresh_bytecode: bool = False
) -> tuple[bool, str, float]:
    py = str(tree / ".venv" / "bin" / "python")
    cmd = [py, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-m", MARKERS, *tests]
    if fresh_bytecode:
        _clear_bytecode(tree)
    rc, out, wall = _run(cmd + _pytest_args(workers, tree / "Makefile"), tree, _env(fresh_bytecode))
    return rc == 0, _summary(out) if rc == 0 else f"failed:\n{_failures(out)}", wall


def run_head(
    workers: str,
    cold_types: bool,
    workdir: Path,
    tests: list[str],
    checks: bool = True,
    fresh_bytecode: bool = False,
) -> tuple[bool, str, float]:
    """The steps of `make test` after setup, timed together as the Makefile runs them: ruff
    check and format, then mypy in the background at nice 19 beside pytest (``checks`` False:
    pytest only)."""
    venv = REPO / ".venv" / "bin"
    env = _env(fresh_bytecode)
    lint = [
        [str(venv / "ruff"), "check", *LINT_PATHS],
        [str(venv / "ruff"), "format", "--check", *LINT_PATHS],
    ]
    mypy = ["nice", "-n", "19", str(venv / "python"), "-m", "mypy"] + (
        ["--cache-dir", str(workdir / f"mypy-{time.monotonic_ns()}")] if cold_types else []
    )
    pytest = (
        [str(venv / "python"), "-m", "pytest", "-q", "-p", "no:cacheprovider", "-m", MARKERS]
        + tests
        + _pytest_args(workers)
    )
    if fresh_bytecode:
        _clear_bytecode(REPO)
    t0 = time.perf_counter()
    for cmd in lint if checks else []:
        rc, out, _ = _run(cmd, REPO, env)
        if rc != 0:
            return False, f"ruff failed:\n{_failures(out)}", time.perf_counter() - t0
    types = None
    if checks:
        types = subprocess.Popen(
            mypy, cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True
        )
    try:
        rc, out, _ = _run(pytest, REPO, env)
        types_out = types.communicate()[0] if types is not None else ""
    finally:
        if types is not None and types.poll() is None:
            types.kill()
    wall = time.perf_counter() - t0
    if types is not None and types.returncode != 0:
        return False, f"mypy failed:\n{types_out[-2000:]}", wall
    if rc != 0:
        return False, f"pytest failed:\n{_failures(out)}", wall
    return True, _summary(out), wall


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument(
        "--base", default=DEFAULT_BASE, help=f"baseline commit (default {DEFAULT_BASE})"
    )
    ap.add_argument(
        "--base-workers", default="0", help="pytest-xdist workers for the baseline (default 0)"
    )
    ap.add_argument(
        "--workers",
        nargs="+",
        default=["auto"],
        help="pytest-xdist workers for this checkout, one run each (default: auto)",
    )
    ap.add_argument("--repeat", type=int, default=1, help="runs of each arm (default 1)")
    ap.add_argument(
        "--cold-types", action="store_true", help="mypy from an empty cache, as on a fresh clone"
    )
    ap.add_argument(
        "--tests", nargs="+", default=[], help="only these test files (default: the whole suite)"
    )
    ap.add_argument(
        "--fresh-bytecode",
        action="store_true",
        help="Python's default bytecode caching (PYTHONDONTWRITEBYTECODE unset), every run from "
        "a tree without compiled modules, as a fresh clone's first run",
    )
    ap.add_argument("--keep", action="store_true", help="keep the baseline worktree")
    ap.add_argument(
        "--quick",
        action="store_true",
        help="HEAD against itself on tests/test_config.py, no lint or types (checks the script)",
    )
    args = ap.parse_args(argv)
    if args.quick:
        args.base, args.tests = "HEAD", args.tests or ["tests/test_config.py"]
    if not (REPO / ".venv" / "bin" / "python").exists():
        ap.error("no .venv in this checkout: run `make setup` first")

    # a SIGTERM ends the run through the cleanup below (the worktree removed, the test run killed)
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))
    workdir = Path(tempfile.mkdtemp(prefix="bench-test-time-"))
    failed = False
    times: dict[str, list[float]] = {}
    try:
        print(f"preparing the baseline {args.base} in {workdir}/base ...", file=sys.stderr)
        tree = prepare_base(args.base, workdir)
        arms = [("base", args.base_workers)] + [("head", w) for w in args.workers]
        for rep in range(args.repeat):
            order = arms if rep % 2 == 0 else arms[::-1]
            for arm, w in order:
                label = f"{arm} -n {w}"
                print(f"[{rep + 1}/{args.repeat}] {label} ...", file=sys.stderr, flush=True)
                if arm == "base":
                    ok, summary, wall = run_base(tree, w, args.tests, args.fresh_bytecode)
                else:
                    ok, summary, wall = run_head(
                        w,
                        args.cold_types,
                        workdir,
                        args.tests,
                        not args.quick,
                        args.fresh_bytecode,
                    )
                failed |= not ok
                times.setdefault(label, []).append(wall)
                print(f"{label:<14} {wall:7.1f} s  {'ok ' if ok else 'FAIL'} {summary}", flush=True)
    finally:
        if not args.keep:
            subprocess.run(
                ["git", "-C", str(REPO), "worktree", "remove", "--force", str(workdir / "base")],
                capture_output=True,
            )
            shutil.rmtree(workdir, ignore_errors=True)
    base_label = f"base -n {args.base_workers}"
    if base_label in times:
        base = statistics.median(times[base_label])
        print(f"\nmedians (baseline {args.base}, {base:.1f} s):")
        for label, ts in times.items():
            print(
                f"  {label:<14} {statistics.median(ts):7.1f} s  ratio {statistics.median(ts) / base:.2f}"
            )
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
