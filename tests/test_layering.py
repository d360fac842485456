"""The layering rule of DESIGN §2, enforced.

- Core modules of ``dran_edge`` import only numpy, scipy, yaml, the standard library and
  other core modules — never ``dran_edge.perception`` / ``dran_edge.comms`` or a shell.
- Nothing imports a hardware library (pyrealsense2, depthai, zmq, systemd) at module
  import time: importing every module of the package leaves them out of ``sys.modules``.
"""

from __future__ import annotations

import ast
import json
import pathlib
import subprocess
import sys

ROOT = pathlib.Path(__file__).resolve().parents[1]

# Shells own clocks, sockets, threads, files and processes; they may import anything (lazily
# for hardware). Every other module under dran_edge/ is core.
SHELL_MODULES = {
    "cli",
    "daemon",
    "ingest_server",
    "notify",
    "checkpoint",
    "replay",
    "simulate",
    "evaluate",
    "multiagent",
    "run_dir",
    "journal",  # the daemon's on-disk ingest journal
    "sim_writer",  # writes simulated runs (renders frames, encodes ingest bytes)
    "dgs",  # DGS baseline driven over the in-process bus (experiment driver)
    "objects_sim",  # the Ego-like object experiment driver
    "replay_robots",  # replay's per-robot drivers (daemon code, transports)
    "dran_node",  # a DRAN agent as a comms.loopback node (simulation scenario inside)
}
SHELL_PACKAGES = {"commands", "ros"}  # ros: the rclpy bridge node and its socket client
# Shell modules inside sub-packages (path under dran_edge/): bag import/export (rosbags, files),
# the ROS message conversion (encodes ingest records with dran_edge.comms), recordings, plots.
SHELL_FILES = {
    "formats/bags.py",
    "formats/bag_sinks.py",
    "formats/run_bag.py",
    "formats/ros_msgs.py",
    "formats/recorded.py",
    "evaluation/traj_outputs.py",
}
CORE_THIRD_PARTY = {"numpy", "scipy", "yaml"}
HARDWARE = {"pyrealsense2", "depthai", "zmq", "systemd"}


def _core_files() -> list[pathlib.Path]:
    out = []
    for path in sorted((ROOT / "dran_edge").rglob("*.py")):
        rel = path.relative_to(ROOT / "dran_edge")
        if rel.parts[0] in SHELL_PACKAGES or (len(rel.parts) == 1 and path.stem in SHELL_MODULES) \
                or rel.as_posix() in SHELL_FILES:
            continue
        out.append(path)
    return out


def _imported_modules(path: pathlib.Path) -> list[tuple[int, str]]:
    tree = ast.parse(path.read_text(), filename=str(path))
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            found.append((node.lineno, node.module))
    return found


def test_core_imports_only_numpy_scipy_stdlib_and_core():
    stdlib = set(sys.stdlib_module_names) | {"__future__"}
    bad = []
    for path in _core_files():
        for lineno, name in _imported_modules(path):
            top = name.split(".")[0]
            if top == "dran_edge":
                parts = name.split(".")
                if len(parts) > 1 and (
                    parts[1] in {"perception", "comms"} | SHELL_PACKAGES | SHELL_MODULES
                ):
                    bad.append(f"{path.relative_to(ROOT)}:{lineno} imports shell {name}")
            elif top not in stdlib and top not in CORE_THIRD_PARTY:
                bad.append(f"{path.relative_to(ROOT)}:{lineno} imports {name}")
    assert not bad, "core modules must stay pure:\n" + "\n".join(bad)


def test_no_hardware_library_is_imported_at_module_import_time():
    code = f"""
import importlib, json, pkgutil, sys
import dran_edge, dran_edge.perception, dran_edge.comms
names = []
for pkg in (dran_edge, dran_edge.perception, dran_edge.comms):
    for info in pkgutil.walk_packages(pkg.__path__, pkg.__name__ + "."):
        names.append(info.name)
failed = {{}}
for name in names:
    try:
        importlib.import_module(name)
    except Exception as exc:  # reported below: every module must import
        failed[name] = repr(exc)
loaded = sorted(m for m in {sorted(HARDWARE)!r} if m in sys.modules)
print(json.dumps({{"modules": len(names), "failed": failed, "hardware_loaded": loaded}}))
"""
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=ROOT
    )
    assert out.returncode == 0, out.stderr
    result = json.loads(out.stdout.strip().splitlines()[-1])
    assert result["modules"] > 5
    assert result["failed"] == {}, result["failed"]
    assert result["hardware_loaded"] == [], result["hardware_loaded"]


def test_cli_help_is_instant_and_lists_every_command():
    from dran_edge import cli

    out = subprocess.run(
        [sys.executable, "-c", "import sys; from dran_edge.cli import main; sys.exit(main(['--help']))"],
        capture_output=True,
        text=True,
        timeout=60,
        cwd=ROOT,
    )
    assert out.returncode == 0
    for name in cli.COMMANDS:
        assert name in out.stdout
