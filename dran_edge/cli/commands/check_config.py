"""``dran-edge check-config FILE``: load a robot config and everything it names, as ``run`` does.

Reports every problem, not only the first: the file's own (unknown keys, types, ranges, with
file, line and key path), then what ``dran-edge run`` would load from it: the key file (its mode
and its kind for ``comms.auth``), the fleet's public keys, the camera calibration and the tag
map, a recording, and whether the state directory can be written. Hardware (the camera, the
radio's port) is not opened.
"""

from __future__ import annotations

import argparse
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

from dran_edge.errors import ConfigError, DranError

if TYPE_CHECKING:
    from dran_edge.config import RobotConfig

_T = TypeVar("_T")

HELP = "load a robot config and everything it names (keys, calibration, tags), as 'run' does"


def build_parser(prog: str) -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog=prog,
        description="Load FILE as 'dran-edge run' does: the file itself (strict: unknown keys, "
        "types, ranges) and what it names: the key file and its mode, the fleet's "
        "public keys (comms.auth ed25519 or pairwise), the camera calibration, the tag map, a "
        "recording, a writable state directory. Prints every problem (file, line, "
        "key path, reason) and exits 2, or a one-line summary and exits 0. The "
        "camera and the radio are not opened.",
    )
    p.add_argument("file", metavar="FILE", help="the robot's YAML config (docs/config.md)")
    p.add_argument(
        "--show", action="store_true", help="print the full config with every default filled in"
    )
    p.add_argument(
        "--no-keys",
        action="store_true",
        help="do not open the key files (comms.key_file, the fleet's public keys): for an "
        "install before the fleet's keys are copied in; everything else is checked",
    )
    return p


def _collect(errors: list[DranError], check: Callable[..., _T], *args: Any) -> _T | None:
    """Run one check; a DranError it raises is recorded, and None returned."""
    try:
        return check(*args)
    except DranError as exc:
        errors.append(exc)
        return None


def _comms_errors(cfg, open_keys: bool = True) -> list[DranError]:
    from dran_edge.comms import keys

    errors: list[DranError] = []
    if cfg.comms.transport == "none":
        return errors
    key_path = cfg.resolve(cfg.comms.key_file)
    where = cfg.source_path or None
    if key_path is None:
        return [ConfigError("comms.key_file: not set, but comms.transport is 'udp'", path=where)]
    if not open_keys:
        return errors
    if cfg.comms.auth == "hmac":
        _collect(errors, keys.load_fleet_key, key_path)
        return errors
    secret = _collect(errors, keys.load_robot_key, key_path)
    public = _collect(errors, keys.fleet_public_keys, cfg)
    if public is None:
        return errors
    missing = sorted(
        ({n.id for n in cfg.neighbours} | set(cfg.comms.allow_relay_from)) - set(public)
    )
    if missing:
        errors.append(
            ConfigError(
                f"comms.auth {cfg.comms.auth}: no public key for robot(s) {missing} (add them to "
                "comms.public_keys_file, or neighbours[].public_keys)",
                path=where,
            )
        )
    if secret is not None:
        own = public.get(cfg.robot.id)
        mine = _collect(errors, keys.public_key_of, secret)
        if own is None:
            errors.append(
                ConfigError(
                    f"comms.public_keys_file: no public key for this robot ({cfg.robot.id}); its "
                    "neighbours cannot verify it (export the fleet's keys again)",
                    path=where,
                )
            )
        elif mine is not None and mine not in own:
            errors.append(
                ConfigError(
                    f"comms.key_file's public key is not robot {cfg.robot.id}'s in the fleet's "
                    "public keys (a key of another robot, or keys not exported again)",
                    path=str(key_path),
                )
            )
    return errors


def _camera_errors(cfg) -> list[DranError]:
    errors: list[DranError] = []
    cam = cfg.camera
    if cam.source == "none":
        return errors
    if cam.source == "recorded":
        rec = cfg.resolve(cam.recording)
        if rec is None or not rec.exists():
            errors.append(
                ConfigError(
                    f"camera.recording: expected a frames folder or a recording, got "
                    f"{str(rec) if rec else 'nothing'}",
                    path=cfg.source_path or None,
                )
            )
    try:
        from dran_edge.perception.calib import load_camera, load_tag_map
        from dran_edge.perception.pipeline import _camera_file
    except ImportError as exc:
        return errors + [
            DranError(
                f"camera.source {cam.source!r}: the perception pipeline does not import ({exc})"
            )
        ]
    camera_path = _collect(errors, _camera_file, cfg)
    camera = _collect(errors, load_camera, camera_path) if camera_path else None
    if camera is not None and (camera.width, camera.height) != (cam.width, cam.height):
        errors.append(
            ConfigError(
                f"camera.width/height: {cam.width}x{cam.height}, but {camera_path} is calibrated "
                f"for {camera.width}x{camera.height}",
                path=cfg.source_path or None,
            )
        )
    tags = cfg.resolve(cam.tags_file)
    if tags is None and camera_path is not None:
        tags = camera_path.parent.parent / "tags.yaml"
    if tags is None:
        errors.append(
            ConfigError(
                "camera.tags_file: not set and no calibration directory to "
                "look for tags.yaml next to",
                path=cfg.source_path or None,
            )
        )
    else:
        _collect(errors, load_tag_map, tags)
    return errors


def _state_errors(cfg) -> list[DranError]:
    from dran_edge.daemon.service import resolve_dirs

    state, _ = resolve_dirs(cfg)
    probe = state
    while not probe.exists() and probe.parent != probe:
        probe = probe.parent
    what = "the state directory" if probe == state else f"{probe} (to create {state} in it)"
    try:
        # a real write, not os.access: root passes access() on read-only file systems too
        with tempfile.TemporaryFile(dir=probe, prefix=".dran-edge-check-"):
            pass
    except OSError as exc:
        return [
            ConfigError(
                f"daemon.state_dir: cannot write {what}: {exc.strerror}",
                path=cfg.source_path or None,
            )
        ]
    return []


def check_config_file(
    path: str | Path, open_keys: bool = True
) -> tuple[RobotConfig | None, list[DranError]]:
    """(config or None, every problem found): the file's own problems, then those of what it
    names, for each section that loaded cleanly (the key files only with ``open_keys``)."""
    from dran_edge.config import load_config_report

    cfg, errors = load_config_report(path)
    if cfg is None:
        return None, list(errors)
    bad = {getattr(e, "section", "") for e in errors}
    found: list[DranError] = list(errors)
    if not bad & {"comms", "neighbours", "robot"}:
        found += _comms_errors(cfg, open_keys)
    if not bad & {"camera", "robot"}:
        found += _camera_errors(cfg)
    if "daemon" not in bad:
        found += _state_errors(cfg)
    return cfg, found


def run(args: argparse.Namespace) -> int:
    import sys

    cfg, errors = check_config_file(args.file, open_keys=not args.no_keys)
    if errors:
        for e in errors:
            print(f"dran-edge check-config: error: {e}", file=sys.stderr)
        print(f"{args.file}: {len(errors)} problem{'s' * (len(errors) != 1)}", file=sys.stderr)
        return 2
    assert cfg is not None  # no config comes with the errors that say why
    g = cfg.agent.graph
    auth = f"{cfg.comms.auth} key" if cfg.comms.transport != "none" else "no key"
    if args.no_keys and cfg.comms.transport != "none":
        auth += ", not opened: --no-keys"
    print(
        f"{args.file}: ok: robot {cfg.robot.name} (id {cfg.robot.id}) in fleet "
        f"{cfg.robot.fleet}; {len(cfg.neighbours)} neighbours; transport "
        f"{cfg.comms.transport} ({auth}); camera {cfg.camera.source}; ingest "
        f"{'on' if cfg.ingest.enabled else 'off'}; graph <= {g.max_nodes} nodes / "
        f"{g.max_edges} edges"
    )
    if args.show:
        import yaml

        from dran_edge.config import config_to_dict

        print(yaml.safe_dump(config_to_dict(cfg), sort_keys=False), end="")
    return 0
