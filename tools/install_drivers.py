#!/usr/bin/env python3
"""Install dran-edge's optional camera drivers one by one; a missing one never fails the install.

    install_drivers.py [--pip-arg ARG]... TARGET DRIVER...

TARGET is what pip installs with the driver's extra: ``.`` or ``-e .`` style paths (``make
setup``) or ``dran-edge`` (the offline bundle, with ``--pip-arg=--no-index
--pip-arg=--find-links=WHEELS``). DRIVER is an extra of pyproject.toml: ``realsense``
(pyrealsense2) or ``oak`` (depthai). Run it with the venv's Python: pip installs into the
interpreter running this script.

PyPI publishes these drivers as binary wheels for some CPython versions and architectures only
(pyrealsense2 2.55 on aarch64: cp38, cp39, cp310, cp312 — no cp311). When a driver cannot be
installed, this prints which one, for which Python and architecture, and what to do instead,
and carries on; the exit status is 0 unless ``--strict``. dran-edge itself never needs a driver:
the frame source that uses one imports it lazily (docs/perception.md).
"""

from __future__ import annotations

import argparse
import platform
import subprocess
import sys

DRIVERS = {
    "realsense": (
        "pyrealsense2",
        "an Intel RealSense camera owned by the daemon (camera.source: realsense)",
    ),
    "oak": ("depthai", "a Luxonis OAK camera owned by the daemon (camera.source: oak)"),
}


def advice(driver: str) -> str:
    module, use = DRIVERS[driver]
    py = f"cp{sys.version_info.major}{sys.version_info.minor}"
    return (
        f"optional driver '{driver}' ({module}) is not available for Python "
        f"{platform.python_version()} ({py}) on {platform.machine()}: it is needed only for "
        f"{use}. Choices: (a) a venv with a Python version that {module} publishes a wheel "
        f"for on {platform.machine()} (install.sh --python /usr/bin/python3.10, or "
        f"PYTHON=python3.10 make setup); (b) build {module} from source on the robot; "
        f"(c) let ROS own the camera and forward frames to the daemon "
        f"(camera.source: forwarded, docs/perception.md) — needs no driver in this venv."
    )


def install(target: str, driver: str, pip_args: list[str]) -> tuple[bool, str]:
    """pip-install ``target[driver]``; returns (ok, the last lines of pip's output)."""
    spec = f"{target}[{driver}]"
    editable = []
    if target.startswith("-e "):
        editable, spec = ["-e"], f"{target[3:]}[{driver}]"
    cmd = [
        sys.executable,
        "-m",
        "pip",
        "install",
        "--disable-pip-version-check",
        "--only-binary",
        DRIVERS[driver][0],
        *pip_args,
        *editable,
        spec,
    ]
    proc = subprocess.run(cmd, capture_output=True, text=True, check=False)
    tail = "\n".join((proc.stdout + proc.stderr).strip().splitlines()[-3:])
    return proc.returncode == 0, tail


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("target", help="'.', '-e .' or 'dran-edge' (what pip installs the extra of)")
    ap.add_argument(
        "drivers",
        nargs="*",
        choices=sorted(DRIVERS),
        metavar="DRIVER",
        help=f"extras to try: {', '.join(sorted(DRIVERS))}",
    )
    ap.add_argument(
        "--pip-arg",
        action="append",
        default=[],
        help="extra argument for pip (repeatable), e.g. --pip-arg=--no-index",
    )
    ap.add_argument("--strict", action="store_true", help="exit 1 when a driver is missing")
    args = ap.parse_args(argv)
    missing = []
    for driver in args.drivers:
        ok, tail = install(args.target, driver, args.pip_arg)
        if ok:
            print(f"install_drivers: {driver} ({DRIVERS[driver][0]}) installed")
        else:
            missing.append(driver)
            print(
                f"install_drivers: NOTE: {advice(driver)}\n  pip said: "
                + tail.replace("\n", "\n  "),
                file=sys.stderr,
            )
    return 1 if missing and args.strict else 0


if __name__ == "__main__":
    sys.exit(main())
