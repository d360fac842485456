#!/usr/bin/env python3
"""Bag import throughput and memory: `dran-edge import-bag` vs plain `rosbags` iteration.

Writes a synthetic one-robot recording of the size asked for (what a Dingo with a D435i and
VINS records: 640x480 mono8 colour + 16UC1 aligned depth at 15 Hz as raw sensor_msgs/Image,
200 Hz odometry, 2 Hz keyframes, 120 Hz mocap of two rigid bodies), then, each in its own
process (peak RSS from getrusage):

- baseline: `rosbags` AnyReader over every message, each deserialised (what any script that
  reads the bag does);
- import: `import_bags` with frames kept at 2 Hz (`max_rate_hz: 2`, as the simulator records;
  the other frames are skipped before decoding), stored as PGM (`encode: pnm`, default) or
  PNG (`--encode png`: ~90 ms per 640x480 image here, the bottleneck).

Prints MB/s of bag and peak RSS of both and their ratio. The bag is in the page cache after
writing (23 GB RAM here), so this measures CPU, not the disk.

    .venv/bin/python tools/bench/bench_bags.py [--quick] [--size-gb 2] [--format ros1|sqlite3|mcap]
"""

from __future__ import annotations

import argparse
import json
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
T0 = 1_767_225_600_000_000_000


ENCODE = "pnm"


def write_bag(path: Path, fmt: str, size_bytes: int) -> dict:
    """Synthetic recording of about ``size_bytes``; returns the mapping (docs/bags.md)."""
    sys.path.insert(0, str(ROOT))
    from dran_edge.formats import run_bag

    ts = run_bag._typestore(fmt)
    msgs = run_bag._Msgs(ts)
    out = run_bag._BagOut(path, fmt, ts)
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:480, 0:640]
    base = (96 + 60 * np.sin(xx / 37.0) * np.cos(yy / 23.0)).astype(np.float32)
    depth_base = (1500 + 400 * np.sin(xx / 90.0) + yy).astype(np.float32)
    frame_bytes = 640 * 480 * 3
    seconds = max(2, int(size_bytes / (15 * frame_bytes)))
    written = 0
    k = 0
    for sec in range(seconds):
        for j in range(200):  # odometry, keyframes and mocap of this second, in time order
            s = T0 + sec * 1_000_000_000 + j * 5_000_000
            th = (sec + j / 200) * 0.3
            v = (np.cos(th), np.sin(th), 0.0, 0.0, 0.0, np.sin(th / 2), np.cos(th / 2))
            out.write(
                "/vins_estimator/odometry",
                "nav_msgs/msg/Odometry",
                s + 2_000_000,
                msgs.odometry(s, v),
            )
            if j % 100 == 0:
                out.write(
                    "/vins_estimator/keyframe_pose",
                    "nav_msgs/msg/Odometry",
                    s + 30_000_000,
                    msgs.odometry(s, v),
                )
            if j % 5 < 3:  # 120 Hz
                for body in ("dingo1", "box0"):
                    out.write(
                        f"/vrpn_client_node/{body}/pose",
                        "geometry_msgs/msg/PoseStamped",
                        s + 1_000_000,
                        msgs.pose_stamped(s, v),
                    )
        for f in range(15):
            s = T0 + sec * 1_000_000_000 + f * 66_666_666
            noise = rng.normal(0, 2.0, (480, 640)).astype(np.float32)
            colour = np.clip(base + noise + (k % 50), 0, 255).astype(np.uint8)
            depth = np.clip(depth_base + 3 * noise, 0, 65535).astype(np.uint16)
            out.write(
                "/camera/color/image_raw",
                "sensor_msgs/msg/Image",
                s + 20_000_000,
                msgs.image(s, colour, "mono8"),
            )
            out.write(
                "/camera/aligned_depth_to_color/image_raw",
                "sensor_msgs/msg/Image",
                s + 21_000_000,
                msgs.image(s, depth, "16UC1"),
            )
            written += frame_bytes
            k += 1
        if sec == 0:
            info = msgs.camera_info(
                T0,
                {
                    "width": 640,
                    "height": 480,
                    "intrinsics": {"fx": 615.0, "fy": 615.0, "cx": 320.0, "cy": 240.0},
                },
            )
            out.write("/camera/color/camera_info", "sensor_msgs/msg/CameraInfo", T0, info)
    out.close()
    return {
        "format": "dran-edge-bag-map/1",
        "fleet": "bench",
        "robots": [
            {
                "id": 1,
                "name": "dingo1",
                "odometry": "/vins_estimator/odometry",
                "keyframes": "/vins_estimator/keyframe_pose",
                "mocap_body": "dingo1",
                "image": {
                    "topic": "/camera/color/image_raw",
                    "camera_info": "/camera/color/camera_info",
                    "depth": "/camera/aligned_depth_to_color/image_raw",
                    "max_rate_hz": 2.0,
                    "encode": ENCODE,
                    "T_body_camera": {"xyz": [0.1, 0, 0.1], "quat_xyzw": [-0.5, 0.5, -0.5, 0.5]},
                },
            }
        ],
        "mocap": {
            "bodies": {
                "dingo1": "/vrpn_client_node/dingo1/pose",
                "box0": "/vrpn_client_node/box0/pose",
            }
        },
    }


BASELINE = """
import sys, time
from pathlib import Path
from rosbags.highlevel import AnyReader
t = time.perf_counter(); n = 0
with AnyReader([Path(sys.argv[1])]) as r:
    for c, ts, raw in r.messages():
        r.deserialize(raw, c.msgtype); n += 1
print(time.perf_counter() - t, n)
"""

IMPORT = """
import sys, time
from dran_edge.formats.bag_map import read_mapping
from dran_edge.formats.bags import import_bags
t = time.perf_counter()
s = import_bags([sys.argv[1]], read_mapping(sys.argv[2]), sys.argv[3])
print(time.perf_counter() - t, s["messages"])
"""


def _measure(code: str, *args: str) -> tuple[float, int, float]:
    """(seconds, messages, peak RSS MB) of ``code`` run in a fresh process."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    p = subprocess.run(
        [sys.executable, "-c", code, *args], capture_output=True, text=True, cwd=ROOT, check=False
    )
    if p.returncode:
        sys.exit(p.stderr)
    rss = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    secs, n = p.stdout.split()
    return float(secs), int(n), max(rss, before) / 1024.0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="a 0.2 GB bag instead of 2 GB")
    ap.add_argument("--size-gb", type=float, default=2.0, help="bag size (default 2)")
    ap.add_argument("--format", choices=("ros1", "sqlite3", "mcap"), default="ros1")
    ap.add_argument("--dir", help="working folder (default: a temporary one, removed)")
    ap.add_argument(
        "--encode",
        choices=("pnm", "png"),
        default="pnm",
        help="how kept raw frames are stored (image.encode of the mapping)",
    )
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    size = int((0.2 if args.quick else args.size_gb) * 1e9)
    global ENCODE
    ENCODE = args.encode
    tmp = Path(args.dir) if args.dir else Path(tempfile.mkdtemp(prefix="bench_bags_"))
    tmp.mkdir(parents=True, exist_ok=True)
    try:
        bag = tmp / ("b.bag" if args.format == "ros1" else "b")
        t = time.perf_counter()
        mapping = write_bag(bag, args.format, size)
        t_write = time.perf_counter() - t
        import yaml

        (tmp / "map.yaml").write_text(yaml.safe_dump(mapping))
        nbytes = (
            bag.stat().st_size if bag.is_file() else sum(f.stat().st_size for f in bag.iterdir())
        )
        # RUSAGE_CHILDREN keeps the maximum over all children: baseline first, import second
        # (its RSS is only reported when larger than the baseline's).
        b_s, b_n, b_rss = _measure(BASELINE, str(bag))
        i_s, i_n, i_rss = _measure(IMPORT, str(bag), str(tmp / "map.yaml"), str(tmp / "run"))
        frames = json.loads((tmp / "run" / "import.json").read_text())["robots"]["dingo1"]
        res = {
            "format": args.format,
            "bag_mb": nbytes / 1e6,
            "write_s": t_write,
            "baseline_s": b_s,
            "baseline_mb_s": nbytes / 1e6 / b_s,
            "baseline_rss_mb": b_rss,
            "import_s": i_s,
            "import_mb_s": nbytes / 1e6 / i_s,
            "import_rss_mb": i_rss,
            "messages": i_n,
            "frames_written": frames["written"].get("frames", 0),
            "time_ratio": i_s / b_s,
        }
        if args.json:
            print(json.dumps(res, indent=2))
        else:
            print(
                f"bag: {args.format}, {res['bag_mb']:.0f} MB, {i_n} messages, written in "
                f"{t_write:.0f} s; {res['frames_written']} frames kept (2 Hz, {args.encode})"
            )
            print(f"{'':<26}{'seconds':>9}{'MB/s':>9}{'peak RSS MB':>13}")
            print(
                f"{'rosbags iterate+deser.':<26}{b_s:>9.1f}{res['baseline_mb_s']:>9.0f}"
                f"{b_rss:>13.0f}"
            )
            print(
                f"{'dran-edge import-bag':<26}{i_s:>9.1f}{res['import_mb_s']:>9.0f}"
                f"{i_rss:>13.0f}   (x{res['time_ratio']:.2f} the baseline's time)"
            )
    finally:
        if not args.dir:
            shutil.rmtree(tmp, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
