"""Suite-wide setup: one BLAS thread, as `make test` and every dran-edge shell use.

`dran_edge.cli.commands.bench` sets OPENBLAS_NUM_THREADS=1 when it is imported, which in a bare
`pytest` run happens after numpy has loaded OpenBLAS with its default pool: the test process
then keeps several threads while the processes it starts later get one, and
tests/test_radio.py's bit-identity check between the in-process and the three-process fleet
fails on the last bits. Set here, before any test module imports numpy, both sides match.
"""

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")


import pytest  # noqa: E402

#: The test files that take longest (CPU seconds per file, `pytest --durations=0`, 2026-11-26),
#: longest first. pytest-xdist's --dist loadfile hands files to its workers in collection order,
#: so these start first and the short files fill in around them (longest-first scheduling).
#: By default xdist orders the files by their number of tests instead, which starts a long file
#: with few tests late, so that one worker can run alone at the end.
#: test_bench_quick.py goes first: it starts a dozen benchmark processes at once, and a file
#: with real-time checks (a daemon's 2 s watchdog cadence) running beside that burst failed
#: 2 of 4 suite runs; at the start the other worker builds test_replay.py's simulated run.
#: The order changes no result (every file's tests keep their own order).
LONGEST_FILES = (
    "test_bench_quick.py",
    "test_replay.py",
    "test_local_graph.py",
    "test_import_bag.py",
    "test_codec.py",
    "test_multiagent.py",
    "test_daemon_systemd.py",
    "test_eval.py",
    "test_dish_fuzz.py",
    "test_rehearsal.py",
    "test_dist_init.py",
    "test_perception_tagpose.py",
    "test_stopping.py",
    "test_daemon_crash.py",
)


def pytest_collection_modifyitems(config, items):
    """Longest files first (``LONGEST_FILES``), the rest in collection order; stable."""
    rank = {name: k for k, name in enumerate(LONGEST_FILES)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))


#: The small simulated mission the bag and trajectory-format tests share (3 robots, 16 s,
#: rendered frames at 1 Hz, so the replay runs the AprilTag pipeline).
SMALL_SIM = dict(
    robots=3, objects=3, duration_s=16.0, seed=5, arena_m=5.0, frame_rate_hz=1.0, mocap_rate_hz=10.0
)
SMALL_REPLAY = dict(workers=1, settle_rounds=5)


@pytest.fixture(scope="session")
def small_sim_run(tmp_path_factory):
    """(run_dir, replay report) of SMALL_SIM, simulated and replayed once per session.

    Tests must not write into run_dir (copy it first)."""
    from dran_edge.replay.run import ReplayOptions, replay_run
    from dran_edge.sim.writer import write_run
    from dran_edge.sim.mission import SimParams, generate_mission

    run = tmp_path_factory.mktemp("small_sim") / "run"
    write_run(generate_mission(SimParams(**SMALL_SIM)), run, frames="render", workers=1)
    report = replay_run(run, ReplayOptions(**SMALL_REPLAY)).report
    return run, report


def flip_one_bit(rng, datagram: bytes) -> bytes:
    """``datagram`` with one random bit after the magic and version flipped (forgery tests)."""
    mutated = bytearray(datagram)
    pos = int(rng.integers(4, len(mutated)))
    mutated[pos] ^= 1 << int(rng.integers(0, 8))
    return bytes(mutated)


def assert_forgeries_rejected(verifier, forgeries, n: int) -> dict:
    """Check ``n`` (kind, datagram) forgeries: none accepted, at least 95 % for their trailer
    (``bad_tag``; only a flipped header bit may fail earlier, e.g. as another fleet or a stale
    epoch). Returns the count per reject reason."""
    from dran_edge.comms.auth import Reject

    reasons: dict = {}
    for i, (kind, data) in enumerate(forgeries):
        msg, reason = verifier.check(data)
        assert msg is None, f"forgery {i} (kind {kind}) was accepted"
        reasons[reason] = reasons.get(reason, 0) + 1
    assert sum(reasons.values()) == n
    assert reasons[Reject.BAD_TAG] >= 0.95 * n, reasons
    return reasons


def mutate_datagram(data, datagram: bytes) -> bytes:
    """A hypothesis-drawn corruption of ``datagram``: one bit flipped, cut short, or bytes
    inserted (the forgery tests of the HMAC and the Ed25519 trailers)."""
    from hypothesis import strategies as st

    mutated = bytearray(datagram)
    i = data.draw(st.integers(0, len(mutated) - 1))
    op = data.draw(st.sampled_from(["flip", "cut", "extend"]))
    if op == "flip":
        mutated[i] ^= 1 << data.draw(st.integers(0, 7))
    elif op == "cut":
        del mutated[i:]
    else:
        mutated[i:i] = data.draw(st.binary(min_size=1, max_size=20))
    return bytes(mutated)
