"""Atomic checkpoints: round trips, torn files detected, a kill -9 during saves never corrupts."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from dran_edge.daemon.checkpoint import CheckpointStore, atomic_write, dumps, loads, next_boot_epoch
from dran_edge.errors import DecodeError


def sample_state(seed: int = 0) -> dict:
    rng = np.random.default_rng(seed)
    return {
        "graph": {"poses": rng.normal(size=(5, 4, 4)), "ids": np.arange(5, dtype=np.int64)},
        "duals": {(1, 7): rng.normal(size=6), (2, 3): rng.normal(size=6)},
        "y": {3: np.eye(4), 9: np.eye(4) * 2},
        "seq": 42,
        "epoch": 3,
        "name": "dingo1",
        "nan": float("nan"),
        "none": None,
        "list": [1, 2.5, "x", np.float64(3.0)],
    }


def test_round_trip_keeps_arrays_and_keys():
    state = sample_state()
    back = loads(dumps(state))
    np.testing.assert_array_equal(back["graph"]["poses"], state["graph"]["poses"])
    assert back["graph"]["ids"].dtype == np.int64
    assert set(back["duals"]) == {(1, 7), (2, 3)}
    np.testing.assert_array_equal(back["duals"][(1, 7)], state["duals"][(1, 7)])
    assert set(back["y"]) == {3, 9}
    assert back["seq"] == 42 and back["name"] == "dingo1" and back["none"] is None
    assert np.isnan(back["nan"]) and back["list"] == [1, 2.5, "x", 3.0]


def test_corruption_and_truncation_are_decode_errors():
    data = dumps(sample_state())
    with pytest.raises(DecodeError):
        loads(data[: len(data) // 2])
    flipped = bytearray(data)
    i = data.index(b"graph")  # inside the JSON metadata
    flipped[i] ^= 0x01
    with pytest.raises(DecodeError):
        loads(bytes(flipped))
    with pytest.raises(DecodeError):
        loads(b"not a checkpoint")
    with pytest.raises(TypeError):
        dumps({"bad": object()})


def test_store_falls_back_to_previous_generation(tmp_path):
    store = CheckpointStore(tmp_path)
    assert store.load() is None
    store.save({"gen": 1})
    store.save({"gen": 2})
    assert store.load()["gen"] == 2
    store.current.write_bytes(store.current.read_bytes()[:50])  # torn newest generation
    assert store.load()["gen"] == 1
    assert not list(tmp_path.glob(".*.tmp.*")), "temp files left behind"


def test_boot_epoch_increments_durably(tmp_path):
    assert [next_boot_epoch(tmp_path) for _ in range(3)] == [1, 2, 3]
    (tmp_path / "boot_epoch").write_text("garbage")
    assert next_boot_epoch(tmp_path) == 1


def test_atomic_write_replaces(tmp_path):
    p = tmp_path / "f"
    atomic_write(p, b"one")
    atomic_write(p, b"two")
    assert p.read_bytes() == b"two"


WRITER = """
import sys, numpy as np
from dran_edge.daemon.checkpoint import CheckpointStore
store = CheckpointStore(sys.argv[1])
big = np.random.default_rng(0).normal(size=(20000, 4, 4))
i = 0
print("go", flush=True)
while True:
    i += 1
    store.save({"i": i, "big": big, "check": float(big.sum()) + i})
"""


@pytest.mark.parametrize("delay_s", [0.3, 0.7, 1.1])
def test_kill_9_during_saves_leaves_a_loadable_checkpoint(tmp_path, delay_s):
    proc = subprocess.Popen([sys.executable, "-c", WRITER, str(tmp_path)], stdout=subprocess.PIPE)
    assert proc.stdout.readline().strip() == b"go"
    deadline = time.monotonic() + 30
    while not (tmp_path / "checkpoint.npz").exists() and time.monotonic() < deadline:
        time.sleep(0.01)
    time.sleep(delay_s)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    state = CheckpointStore(tmp_path).load()
    assert state is not None
    assert state["check"] == pytest.approx(float(state["big"].sum()) + state["i"])
