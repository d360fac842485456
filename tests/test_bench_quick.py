"""Every benchmark in tools/bench/ still runs: each script with ``--quick`` in its own process.

A quick run uses small inputs (generated g2o graphs instead of the shared dataset, a few frames,
a 2 s mission), so it checks that the script works and reports what it should, not its speed:
no timing is asserted (docs/benchmarks.md). Where a quick run computes a result that has a
right answer (a solver's optimum, two step variants that must agree, our ATE against evo's),
that is checked too.

The selected scripts start together when the first test needs one (one process each, ~15 s of
CPU in all): on a busy 2-core machine that takes a fair share of the CPU for the whole set
instead of a fraction of a core for one script after another. Under pytest-xdist the file must
stay on one worker (``make test`` uses ``--dist loadfile``): with ``--dist load`` every worker
that gets one of its tests would start all the scripts.
"""

from __future__ import annotations

import importlib.util
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
BENCH = ROOT / "tools" / "bench"
PERCEPTION = ("cv2", "pupil_apriltags")

#: test name -> (script, extra arguments, modules it needs)
SCRIPTS = {
    "test_bench_g2o": ("bench_g2o.py", ("--no-gtsam",), ()),
    "test_bench_cholesky": ("bench_cholesky.py", (), ()),
    "test_bench_table1": ("bench_table1.py", (), ()),
    "test_bench_eval": ("bench_eval.py", (), ("evo",)),
    "test_bench_perception": ("bench_perception.py", (), PERCEPTION),
    "test_nees_perception": ("nees_perception.py", (), PERCEPTION),
    "test_bench_schur": ("bench_schur.py", (), ()),
    "test_bench_bounded_graph": ("bench_bounded_graph.py", (), ()),
    "test_bench_replay": ("bench_replay.py", (), PERCEPTION),
    "test_bench_comms": ("bench_comms.py", (), ()),
    "test_bench_robot_budget": ("bench_robot_budget.py", (), PERCEPTION),
    "test_bench_solve_policy": ("bench_solve_policy.py", ("--no-gtsam",), ()),
    # minutes even when quick (a 0.2 GB bag; DRAN runs to 1000 rounds; real daemons): slow
    "test_bench_bags": ("bench_bags.py", (), ("rosbags",)),
    "test_bench_generalisation": ("bench_generalisation.py", (), ()),
    "test_bench_stopping": ("bench_stopping.py", (), ()),
    "test_bench_gap_bytes": ("bench_gap_bytes.py", (), ()),
    "test_bench_rehearsal": ("bench_rehearsal.py", (), ()),
    # copies the .venv (~1 GB) into a git worktree of HEAD: slow
    "test_bench_test_time": ("bench_test_time.py", (), ()),
}


def _missing(modules) -> list[str]:
    return [m for m in modules if importlib.util.find_spec(m) is None]


@pytest.fixture(scope="module")
def runs(request, tmp_path_factory):
    """Start every selected, runnable script with --quick; yield name -> (process, out, err)."""
    selected = {item.name for item in request.session.items if item.module is request.module}
    env = {
        **os.environ,
        "OPENBLAS_NUM_THREADS": "1",
        "OMP_NUM_THREADS": "1",
        "PYTHONDONTWRITEBYTECODE": "1",
    }
    tmp = tmp_path_factory.mktemp("bench_quick")
    procs = {}
    for test, (script, args, needs) in SCRIPTS.items():
        if test in selected and not _missing(needs):
            out, err = tmp / f"{script}.out", tmp / f"{script}.err"
            with open(out, "w") as fo, open(err, "w") as fe:
                procs[script] = (
                    subprocess.Popen(
                        [sys.executable, str(BENCH / script), "--quick", *args],
                        cwd=ROOT,
                        env=env,
                        stdout=fo,
                        stderr=fe,
                    ),
                    out,
                    err,
                )
    yield procs
    for p, _, _ in procs.values():
        if p.poll() is None:
            p.kill()
            p.wait()


def run_quick(runs, test: str) -> str:
    """The stdout of the test's script (``--quick``); skip if a module it needs is missing."""
    script, _, needs = SCRIPTS[test]
    if _missing(needs):
        pytest.skip(f"{script} needs {', '.join(_missing(needs))}")
    proc, out, err = runs[script]
    rc = proc.wait(timeout=300)
    assert rc == 0, f"{script} --quick exited {rc}:\n{err.read_text()[-3000:]}"
    return out.read_text()


def floats(line: str) -> list[float]:
    return [float(x) for x in re.findall(r"-?\d+\.\d+(?:e[-+]\d+)?|-?\d+e[-+]\d+", line)]


def test_every_benchmark_has_a_quick_test():
    """A new bench_*.py in tools/bench/ must be added here (and get a --quick mode)."""
    scripts = {p.name for p in BENCH.glob("*.py") if not p.name.startswith("_")}
    assert scripts == {script for script, _, _ in SCRIPTS.values()}
    assert all(callable(globals().get(test)) for test in SCRIPTS)


def test_bench_g2o(runs):
    out = run_quick(runs, "test_bench_g2o")
    rows = [line for line in out.splitlines() if line.startswith("quick-se")]
    assert [r.split()[0] for r in rows] == ["quick-se2", "quick-se3"]
    for r in rows:
        # columns: n m F_init | geo s, it, F, relF* | GTSAM (empty) | chordal s, it, F, relF*
        cols = r.replace("|", " ").split()
        rel_geo, rel_chordal = float(cols[7]), float(cols[-2])
        assert abs(rel_chordal) < 1e-8  # the chordal solve reaches the optimum _common computed
        assert abs(rel_geo) < 1e-6  # the geodesic one (Gauss–Newton, 1e-5 stop) gets close
    assert "ratio = our wall time / GTSAM's" in out


def test_bench_cholesky(runs):
    out = run_quick(runs, "test_bench_cholesky")
    rows = [line for line in out.splitlines() if line.startswith("quick-se")]
    assert len(rows) == 2
    for r in rows:
        resid = [float(x) for x in re.findall(r"\d+e[-+]\d+", r)]
        assert len(resid) == 2 and max(resid) < 1e-9  # SuperLU and ours both solve A + μI
        assert r.rstrip().endswith("x")  # the speed-up column
    assert "speed-up = SuperLU factorisation time" in out


def test_bench_table1(runs):
    out = run_quick(runs, "test_bench_table1")
    header, row = out.splitlines()[:2]
    assert "DRAN F" in header and "DGS MB" in header
    name, F_star, F0, F, gap = row.split()[:5]
    assert name == "quick-se2"
    # DRAN starts from the distributed init above F* and ends between F* and its start
    assert float(F_star) <= float(F) * (1 + 1e-9) and float(F) < float(F0)
    assert float(gap) == pytest.approx(100 * (float(F) / float(F_star) - 1), abs=2e-3)


def test_bench_eval(runs):
    out = run_quick(runs, "test_bench_eval")
    ate = dict(re.findall(r"^\s+(evo|ours)\s*:.*ATE (\d+\.\d+) m", out, re.MULTILINE))
    assert set(ate) == {"evo", "ours"}
    assert float(ate["ours"]) == pytest.approx(float(ate["evo"]), abs=1e-4)
    assert "ratio evo/ours time:" in out and "ratio baseline/ours" in out


def test_bench_perception(runs):
    out = run_quick(runs, "test_bench_perception")
    assert out.count("--- scene:") == 2
    assert len(re.findall(r"ratio full/bare = \d+\.\d+", out)) == 2
    detected = [int(x) for x in re.findall(r"tags detected: (\d+)", out)]
    assert len(detected) == 2 and min(detected) > 0


def test_nees_perception(runs):
    out = run_quick(runs, "test_nees_perception")
    means = [float(x) for x in re.findall(r"NEES mean (\d+\.\d+)", out)]
    assert len(means) == 6 and all(0 < m < 100 for m in means)  # 3 conditions x 2 covariances


def test_bench_schur(runs):
    out = run_quick(runs, "test_bench_schur")
    diff = floats(next(line for line in out.splitlines() if "step difference" in line))[0]
    assert diff < 1e-10  # the reduced step equals the full dense one
    ratios = re.findall(r"ratio to schur\s+(\d+\.\d+)", out)
    assert len(ratios) == 3
    costs = {
        line.split()[0]: float(line.split()[-1])
        for line in out.splitlines()
        if "local cost after" in line
    }
    assert set(costs) == {"schur", "full-dense", "full-sparse"}
    assert max(costs.values()) == pytest.approx(min(costs.values()), rel=1e-8)
    assert "agent round" in out


def test_bench_bounded_graph(runs):
    out = run_quick(runs, "test_bench_bounded_graph")
    rows = [line for line in out.splitlines() if re.match(r"\| \d+ \|", line)]
    assert len(rows) == 2  # a report every 50 keyframes
    for r in rows:
        nodes = int(r.split("|")[2].split("/")[0])
        assert nodes <= 40  # the bounded graph keeps its cap
    assert "bounded, sparsified prior" in out and "peak RSS" in out


def test_bench_replay(runs):
    out = run_quick(runs, "test_bench_replay")
    arms = [line for line in out.splitlines() if line.startswith(("full ", "back-end only"))]
    assert len(arms) == 2
    for a in arms:
        assert float(a.split(")")[-1].split()[0]) == pytest.approx(2.0)  # mission s
    assert re.search(r"ratio wall\(full\) / wall\(back-end only\): \d+\.\d+", out)


def test_bench_comms(runs):
    out = run_quick(runs, "test_bench_comms")
    assert re.search(r"ours\s+\d+\.\d+ ms\s+\d+ B in 2 datagrams", out)
    assert re.search(r"json\+hmac .*x smaller", out)
    pos, rot = floats(next(line for line in out.splitlines() if line.startswith("== precision")))[
        -2:
    ]
    assert pos < 1e-4 and rot < 1e-5  # far under the solver's tolerances
    # the loopback part needs a draft-enabled libzmq; without one the script says so
    assert "RADIO/DISH" in out and (re.search(r"answers \d+/24", out) or "not run" in out)


def test_bench_robot_budget(runs):
    out = run_quick(runs, "test_bench_robot_budget")
    for phase in ("local_step", "acceptance", "codec", "round"):
        line = next(line for line in out.splitlines() if line.strip().startswith(phase))
        here, robot = floats(line)[:2]
        assert robot == pytest.approx(2.5 * here, rel=0.05, abs=0.06)  # the x2.5 core model
    assert "rounds that would exceed 500 ms on the robot:" in out
    assert "perception per frame" in out


def test_bench_solve_policy(runs):
    out = run_quick(runs, "test_bench_solve_policy")
    rows = [
        line
        for line in out.splitlines()
        if line.startswith("| ") and "/" in line and not line.startswith("| graph")
    ]
    assert rows, out
    assert "time after/before" in out


@pytest.mark.slow
def test_bench_bags(runs):
    out = run_quick(runs, "test_bench_bags")
    assert "rosbags iterate+deser." in out and "dran-edge import-bag" in out
    assert "the baseline's time" in out


@pytest.mark.slow
def test_bench_generalisation(runs):
    out = run_quick(runs, "test_bench_generalisation")
    assert "worst case per family" in out
    assert [
        line.split("|")[1].strip()
        for line in out.splitlines()
        if line.startswith("| ") and not line.startswith("| family")
    ]


@pytest.mark.slow
def test_bench_stopping(runs):
    out = run_quick(runs, "test_bench_stopping")
    ratios = [float(x) for x in re.findall(r"F/F\*=(\d+\.\d+)", out)]
    assert ratios and min(ratios) >= 1.0 - 1e-6  # nothing below the optimum


@pytest.mark.slow
def test_bench_rehearsal(runs):
    out = run_quick(runs, "test_bench_rehearsal")
    assert "SR_ATE %" in out and "targets (SR_ATE within 5 points of replay" in out


def test_bench_gap_bytes(runs):
    out = run_quick(runs, "test_bench_gap_bytes")
    row = next(line for line in out.splitlines() if line.startswith("| quick-chain"))
    cells = [c.strip() for c in row.strip("|").split("|")]
    mb, ratio = float(cells[3].split()[0]), float(cells[4])
    # the refined chain gets below 1e-3 within a few hundred kB: MB > 0, ratio = MB / 1 MB
    assert 0 < mb < 1 and ratio == pytest.approx(mb, abs=1e-3)


@pytest.mark.slow
def test_bench_test_time(runs):
    out = run_quick(runs, "test_bench_test_time")
    runs_ = [line for line in out.splitlines() if " -n " in line and not line.startswith(" ")]
    rows = {line.split()[0] + line.split()[2]: line for line in runs_}
    assert {"base0", "headauto"} <= set(rows), out
    assert all(" ok " in row for row in rows.values()), out  # both arms' tests passed
    ratio = float(re.search(r"head -n auto\s+[\d.]+ s\s+ratio (\d+\.\d+)", out).group(1))
    assert ratio > 0
