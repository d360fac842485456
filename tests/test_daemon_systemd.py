"""The systemd protocol for real: the daemon as a process, NOTIFY_SOCKET on our own socket."""

from __future__ import annotations

import importlib.util
import os
import shutil
import socket
import subprocess
import sys
import time
import uuid
from pathlib import Path

import pytest
from daemon_helpers import NotifyListener, start_daemon, stop, wait_status, write_config

from dran_edge.comms import ingest as I
from dran_edge.daemon.status import query_status

REPO = Path(__file__).resolve().parents[1]
WATCHDOG_USEC = 2_000_000  # systemd would kill us after 2 s without a ping


def test_ready_watchdog_status_stopping(tmp_path):
    cfg = write_config(tmp_path)
    listener = NotifyListener(tmp_path / "notify.sock")
    proc = start_daemon(
        cfg, {"NOTIFY_SOCKET": str(listener.path), "WATCHDOG_USEC": str(WATCHDOG_USEC)}
    )
    try:
        listener.collect(60.0, until="READY=1")
        assert listener.times("READY=1"), "no READY=1"
        # sockets are up when READY arrives
        st = query_status(tmp_path / "run" / "status.sock")
        assert st["state"] == "running" and st["robot"]["name"] == "testbot"
        with socket.socket(socket.AF_UNIX) as s:
            s.connect(str(tmp_path / "run" / "ingest.sock"))
            s.sendall(
                I.pack_keyframe(1_000_000_000, [0, 0, 0], [0, 0, 0, 1])
                + b"\x00" * 40  # garbage: counted, not fatal
                + I.pack_keyframe(2_000_000_000, [1, 0, 0], [0, 0, 0, 1])
            )
        listener.collect(4.0)
        st = wait_status(
            tmp_path / "run" / "status.sock", lambda s: s["ingest"]["records"] == 2, proc=proc
        )
        assert st["ingest"]["rejected_by_reason"] == {"bad_magic": 1}
        rc, out = stop(proc)
        listener.collect(2.0, until="STOPPING=1")
    finally:
        if proc.poll() is None:
            proc.kill()
        listener.close()
    assert rc == 0, out
    ready = listener.times("READY=1")[0]
    pings = listener.times("WATCHDOG=1")
    assert pings and min(pings) > ready, "a watchdog ping before READY"
    assert len(pings) >= 3, f"only {len(pings)} watchdog pings in ~4 s"
    gaps = [b - a for a, b in zip(pings, pings[1:])]
    # Cadence: about WATCHDOG_USEC/2, never faster than a tick, never near the timeout.
    assert min(gaps) >= 0.2 * 0.9, gaps
    assert max(gaps) < WATCHDOG_USEC / 1e6, gaps
    statuses = [m for _, m in listener.messages if m.startswith("STATUS=")]
    assert any("rounds=" in m and "records=2" in m and "rejected=1" in m for m in statuses), (
        statuses
    )
    assert listener.times("STOPPING=1"), "no STOPPING=1 on SIGTERM"
    assert "not started by systemd" not in out


def test_without_systemd_says_so_once_and_runs(tmp_path):
    cfg = write_config(tmp_path)
    proc = start_daemon(cfg, {})
    try:
        wait_status(
            tmp_path / "run" / "status.sock", lambda s: s["rounds"]["ticks"] >= 3, proc=proc
        )
    finally:
        rc, out = stop(proc)
    assert rc == 0, out
    assert out.count("not started by systemd") == 1, out


def test_laptop_config_starts_reports_ready_and_idles(tmp_path):
    listener = NotifyListener(tmp_path / "notify.sock")
    proc = start_daemon(
        REPO / "calib" / "fleet" / "laptop.yaml",
        {"NOTIFY_SOCKET": str(listener.path)},
        cwd=tmp_path,
    )
    try:
        listener.collect(60.0, until="READY=1")
        st = wait_status(
            tmp_path / "dran-edge-state" / "run" / "status.sock",
            lambda s: s["rounds"]["ticks"] >= 2,
            proc=proc,
        )
        assert st["ingest"] is None and st["robot"]["name"] == "laptop"
    finally:
        rc, out = stop(proc)
        listener.close()
    assert listener.times("READY=1"), out
    assert rc == 0, out


def test_status_command_prints_health(tmp_path):
    cfg = write_config(tmp_path)
    proc = start_daemon(cfg, {})
    try:
        wait_status(
            tmp_path / "run" / "status.sock", lambda s: s["rounds"]["ticks"] >= 1, proc=proc
        )
        res = subprocess.run(
            [sys.executable, "-m", "dran_edge.cli.app", "status", "--config", str(cfg)],
            capture_output=True,
            text=True,
            timeout=30,
        )
    finally:
        stop(proc)
    assert res.returncode == 0, res.stderr
    for word in ("rounds", "graph", "ingest", "neighbours", "queues"):
        assert word in res.stdout
    res = subprocess.run(
        [
            sys.executable,
            "-m",
            "dran_edge.cli.app",
            "status",
            "--socket",
            str(tmp_path / "absent.sock"),
        ],
        capture_output=True,
        text=True,
        timeout=30,
    )
    assert res.returncode == 1 and "no daemon answers" in res.stderr


def _systemd_running() -> bool:
    return Path("/run/systemd/system").is_dir() and shutil.which("systemd-run") is not None


@pytest.mark.skipif(not _systemd_running(), reason="no running systemd on this machine")
def test_under_systemd_run(tmp_path):
    cfg = write_config(tmp_path)
    unit = f"dran-edge-test-{uuid.uuid4().hex[:8]}"
    user = [] if os.geteuid() == 0 else ["--user"]
    res = subprocess.run(
        [
            "systemd-run",
            *user,
            "--unit",
            unit,
            "--property=Type=notify",
            "--property=WatchdogSec=4",
            "--collect",
            sys.executable,
            "-m",
            "dran_edge.cli.app",
            "run",
            "--config",
            str(cfg),
        ],
        capture_output=True,
        text=True,
        timeout=60,
    )
    if res.returncode != 0:
        pytest.skip(f"systemd-run refused: {res.stderr.strip()}")
    try:
        # systemd-run returns after READY=1 for Type=notify
        time.sleep(5.0)  # longer than WatchdogSec: still active only if pings arrive
        show = subprocess.run(
            ["systemctl", *user, "show", unit, "-p", "ActiveState", "-p", "StatusText"],
            capture_output=True,
            text=True,
        )
        assert "ActiveState=active" in show.stdout, show.stdout
        assert "rounds=" in show.stdout
    finally:
        subprocess.run(["systemctl", *user, "stop", unit], capture_output=True)


@pytest.mark.parametrize(
    "name, instance",
    [
        ("dran-edge.service", "dran-edge.service"),
        ("dran-edge@.service", "dran-edge@dingo1.service"),
    ],
)
def test_unit_files_verify_and_keep_the_camera_reachable(tmp_path, name, instance):
    text = (REPO / "systemd" / name).read_text()
    for line in (
        "Type=notify",
        "WatchdogSec=",
        "Restart=on-failure",
        "StateDirectory=",
        "RuntimeDirectory=",
        "SupplementaryGroups=video plugdev",
        "DeviceAllow=char-usb_device rw",
        "DeviceAllow=char-video4linux rw",
    ):
        assert line in text, line
    assert "PrivateDevices=yes" not in text
    if not shutil.which("systemd-analyze"):
        pytest.skip("systemd-analyze not installed")
    exe = Path(sys.executable).parent / "dran-edge"
    unit = tmp_path / instance
    unit.write_text(text.replace("/opt/dran-edge/.venv/bin/dran-edge", str(exe)))
    res = subprocess.run(
        ["systemd-analyze", "verify", "--man=no", str(unit)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert res.returncode == 0, res.stdout + res.stderr


_NEEDS_CRYPTOGRAPHY = pytest.mark.skipif(
    importlib.util.find_spec("cryptography") is None, reason="no 'cryptography' (.[comms])"
)


@pytest.mark.parametrize(
    "policy",
    [
        "hmac",
        pytest.param("ed25519", marks=_NEEDS_CRYPTOGRAPHY),
        pytest.param("pairwise", marks=_NEEDS_CRYPTOGRAPHY),
    ],
)
def test_two_daemons_exchange_over_loopback_udp(tmp_path, policy):
    """Two robot processes, RADIO/DISH on 127.0.0.1, authenticated with a fleet key or with
    per-robot key pairs and the fleet's public-key file (made by the fleet-key command), used
    to sign (ed25519) or to agree a pair key (pairwise)."""
    from dran_edge.cli.app import main
    from dran_edge.comms.auth import write_fleet_key
    from dran_edge.comms.ingest import encode_event

    from dran_edge.sim.vio import vio_mission

    try:
        from dran_edge.comms.radio import hardened_libzmq_stamp, require_draft_zmq

        require_draft_zmq()
        if hardened_libzmq_stamp() is None:
            raise RuntimeError("libzmq not hardened")
    except Exception as exc:
        pytest.skip(f"no draft/hardened ZeroMQ here: {exc}")
    key = tmp_path / "fleet.key"
    if policy == "hmac":
        write_fleet_key(key)
    else:
        for r in (1, 2):
            assert (
                main(["fleet-key", "pair", str(tmp_path / f"r{r}.key"), "--robot-id", str(r)]) == 0
            )
        assert (
            main(
                [
                    "fleet-key",
                    "export",
                    str(tmp_path / "fleet.pub"),
                    "--fleet",
                    "testfleet",
                    str(tmp_path),
                ]
            )
            == 0
        )
    ports = []
    for _ in range(2):
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            s.bind(("127.0.0.1", 0))
            ports.append(s.getsockname()[1])
    procs, dirs = [], []
    try:
        for me, other in ((0, 1), (1, 0)):
            d = tmp_path / f"r{me + 1}"
            d.mkdir()
            dirs.append(d)
            cfg = write_config(
                d,
                robot={"id": me + 1, "name": f"r{me + 1}"},
                comms={
                    "transport": "udp",
                    "bind_address": "127.0.0.1",
                    "port": ports[me],
                    "key_file": str(key if policy == "hmac" else tmp_path / f"r{me + 1}.key"),
                    "auth": policy,
                    "public_keys_file": str(tmp_path / "fleet.pub") if policy != "hmac" else "",
                },
            )
            text = cfg.read_text() + (
                f"neighbours:\n- {{id: {other + 1}, name: r{other + 1}, "
                f"address: '127.0.0.1:{ports[other]}'}}\n"
            )
            cfg.write_text(text)
            procs.append(start_daemon(cfg, {}))
        for i, d in enumerate(dirs):
            wait_status(d / "run" / "status.sock", lambda s: s["state"] == "running", proc=procs[i])
            m = vio_mission(40, seed=11 + i)
            with socket.socket(socket.AF_UNIX) as s:
                s.connect(str(d / "run" / "ingest.sock"))
                s.sendall(b"".join(encode_event(e) for e in m.events))
        for i, d in enumerate(dirs):
            peer = str(2 - i)
            st = wait_status(
                d / "run" / "status.sock",
                lambda s, p=peer: s["neighbours"].get(p, {}).get("bytes_received", 0) > 0,
                proc=procs[i],
            )
            assert st["transport"]["datagrams_rejected"] == 0
    finally:
        outs = [stop(p) for p in procs]
    for i, (rc, out) in enumerate(outs):
        assert rc == 0, f"robot {i + 1} exited with {rc}; its log ends:\n{out[-4000:]}"


def test_udp_without_key_fails_with_one_clear_line(tmp_path):
    cfg = write_config(tmp_path, comms={"transport": "udp", "key_file": str(tmp_path / "nokey")})
    res = subprocess.run(
        [sys.executable, "-m", "dran_edge.cli.app", "run", "--config", str(cfg)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert res.returncode in (2, 3), res.stderr
    assert "dran-edge run: error:" in res.stderr and "Traceback" not in res.stderr
