"""The architecture's layers (docs/architecture.md), enforced on every import statement.

Every module belongs to a layer, lowest first: the base (``dran_edge`` top-level modules errors,
config, events, messages, blas, and geometry); solver < dran < robot (the pure core); the
adapters comms and perception; formats (files and bags, which may use ingest records and image
decoding); evaluation and sim; viz; daemon; replay, experiments and the ROS bridge; rehearsal;
cli. A module may import from its own package and from packages of strictly lower layers, never
from a sibling of its own layer or from above. The pure core imports only numpy, scipy and the
standard library (``dran_edge.config``, the strict YAML loader, may also import yaml).

Every import counts: ``import dran_edge.x``, ``from dran_edge.x import y`` and
``from dran_edge import x`` (which imports module ``x``), at module level or inside a function.
Relative imports are not used. Imports under ``if TYPE_CHECKING:`` are annotations only and do
not count.
"""

from __future__ import annotations

import ast
import json
import pathlib
import subprocess
import sys
import tomllib

ROOT = pathlib.Path(__file__).resolve().parents[1]

# Lowest first. Packages in one tuple are one layer and must not import each other.
LAYERS: list[tuple[str, ...]] = [
    ("base",),  # dran_edge/*.py, config/ and geometry/: errors, config, events, messages, geometry
    ("solver",),
    ("dran",),
    ("robot",),
    ("comms", "perception"),
    ("formats",),
    ("evaluation", "sim"),
    ("viz",),
    ("daemon",),
    ("replay", "experiments", "ros"),
    ("rehearsal",),
    ("cli",),
]
LAYER_OF = {pkg: level for level, group in enumerate(LAYERS) for pkg in group}
CORE = {"base", "solver", "dran", "robot"}
CORE_THIRD_PARTY = {"numpy", "scipy"}
YAML_ALLOWED = {"dran_edge/config/loader.py"}
HARDWARE = {"pyrealsense2", "depthai", "zmq", "systemd"}
BASE_MODULES = {"errors", "config", "events", "messages", "geometry", "blas", "__version__"}


def _source_files() -> list[pathlib.Path]:
    return sorted(
        [
            *(ROOT / "dran_edge").rglob("*.py"),
            *(ROOT / "comms").glob("*.py"),
            *(ROOT / "perception").glob("*.py"),
        ]
    )


def _package_of_file(path: pathlib.Path) -> str:
    rel = path.relative_to(ROOT).parts
    if rel[0] in ("comms", "perception"):
        return rel[0]
    if len(rel) == 2 or rel[1] in ("geometry", "config"):
        return "base"
    return rel[1]


def _package_of_module(dotted: str) -> str | None:
    """The layer package of an imported ``dran_edge`` module, or None for a third-party one."""
    parts = dotted.split(".")
    if parts[0] != "dran_edge":
        return None
    if len(parts) == 1 or parts[1] in BASE_MODULES:
        return "base"
    if parts[1] not in LAYER_OF:
        raise AssertionError(f"{dotted}: dran_edge.{parts[1]} is in no layer of LAYERS")
    return parts[1]


def _is_type_checking(node: ast.If) -> bool:
    test = node.test
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"
    )


def _imports(path: pathlib.Path) -> list[tuple[int, str]]:
    """(line, dotted module) of every import in the file, TYPE_CHECKING blocks left out."""
    tree = ast.parse(path.read_text(), filename=str(path))
    skip = {
        id(n)
        for node in ast.walk(tree)
        if isinstance(node, ast.If) and _is_type_checking(node)
        for stmt in node.body
        for n in ast.walk(stmt)
    }
    found: list[tuple[int, str]] = []
    for node in ast.walk(tree):
        if id(node) in skip:
            continue
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                found.append((node.lineno, "." * node.level + (node.module or "")))
            elif node.module in (
                "dran_edge",
                "dran_edge.comms",
                "dran_edge.perception",
                *(f"dran_edge.{p}" for p in LAYER_OF),
            ):
                # ``from dran_edge import daemon`` imports the module dran_edge.daemon
                found += [(node.lineno, f"{node.module}.{alias.name}") for alias in node.names]
            else:
                found.append((node.lineno, node.module or ""))
    return found


def test_every_package_is_in_a_layer_and_installed():
    packages = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"][
        "packages"
    ]
    for init in sorted((ROOT / "dran_edge").rglob("__init__.py")):
        rel = init.parent.relative_to(ROOT)
        name = ".".join(rel.parts)
        assert name in packages, f"{name} is missing from pyproject's [tool.setuptools] packages"
        if len(rel.parts) > 1 and rel.parts[1] not in ("geometry", "config"):
            assert rel.parts[1] in LAYER_OF, f"{name} is in no layer of {__name__}.LAYERS"


def test_imports_respect_the_layers():
    bad = []
    for path in _source_files():
        src = _package_of_file(path)
        where = path.relative_to(ROOT)
        for lineno, name in _imports(path):
            if name.startswith("."):
                bad.append(f"{where}:{lineno} relative import {name} (write dran_edge.…)")
                continue
            dst = _package_of_module(name)
            if dst is None or dst == src:
                continue
            if LAYER_OF[dst] >= LAYER_OF[src]:
                bad.append(f"{where}:{lineno} {src} imports {name} ({dst} is not below {src})")
    assert not bad, "layer contract broken:\n" + "\n".join(bad)


def test_core_imports_only_numpy_scipy_and_the_standard_library():
    stdlib = set(sys.stdlib_module_names) | {"__future__"}
    bad = []
    for path in _source_files():
        if _package_of_file(path) not in CORE:
            continue
        where = path.relative_to(ROOT)
        for lineno, name in _imports(path):
            top = name.split(".")[0]
            if top in stdlib or top in CORE_THIRD_PARTY or top == "dran_edge":
                continue
            if top == "yaml" and str(where) in YAML_ALLOWED:
                continue
            bad.append(f"{where}:{lineno} imports {name}")
    assert not bad, "core modules must stay pure:\n" + "\n".join(bad)


def test_the_contract_catches_what_it_claims(tmp_path):
    """The checker itself: a core module importing a shell in each spelling is caught."""
    probe = tmp_path / "probe.py"
    probe.write_text(
        "from dran_edge import daemon\nimport dran_edge.replay.run\nfrom . import x\n"
        "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from dran_edge.cli import app\n"
    )
    names = [n for _, n in _imports(probe)]
    assert names == ["dran_edge.daemon", "dran_edge.replay.run", ".", "typing"]
    assert {_package_of_module(n) for n in names[:2]} == {"daemon", "replay"}


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
    from dran_edge.cli import app as cli

    out = subprocess.run(
        [
            sys.executable,
            "-c",
            "import sys; from dran_edge.cli.app import main; sys.exit(main(['--help']))",
        ],
        capture_output=True,
        text=True,
        timeout=60,
        cwd=ROOT,
    )
    assert out.returncode == 0
    for name in cli.COMMANDS:
        assert name in out.stdout
