"""The docs name files that exist: every source, tool, test and document path mentioned in
README.md and docs/*.md (docs/notes/ is history and may name removed files).

Paths are recognised by their first folder: ``dran_edge/``, ``comms/``, ``perception/``,
``tools/``, ``tests/``, ``systemd/``, ``calib/`` and ``docs/`` from the repository root, and a
dran_edge subpackage (``solver/lm.py``, ``daemon/journal.py``) inside ``dran_edge/``. Brace lists
(``dran_edge/{errors,config}.py``) are expanded; paths with a placeholder (``<file>``, ``*``,
``DIR``) and pytest node ids' ``::name`` parts are left out.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
TOP = "dran_edge|comms|perception|tools|tests|systemd|calib|docs"
SUBPACKAGES = "solver|dran|robot|daemon|formats|evaluation|sim|replay|experiments|cli|geometry"
PATH = re.compile(rf"(?<![\w./-])((?:{TOP}|{SUBPACKAGES})/[\w./{{}},<>*-]*)")


def mentioned_paths(text: str) -> list[str]:
    """Repository paths named in ``text``, brace lists expanded, placeholders dropped."""
    out = []
    for m in PATH.finditer(text):
        path = m.group(1).split("::")[0].rstrip(".,:;")
        if any(c in path for c in "<>*") or path.endswith("/DIR"):
            continue
        brace = re.search(r"\{([^}]*)\}", path)
        if brace:
            out += [
                path[: brace.start()] + alt + path[brace.end() :]
                for alt in brace.group(1).split(",")
            ]
        else:
            out.append(path)
    return out


def resolve(path: str) -> Path:
    first = path.split("/", 1)[0]
    return ROOT / path if re.fullmatch(TOP, first) else ROOT / "dran_edge" / path


def test_the_pattern_finds_what_the_docs_write():
    text = (
        "see `dran_edge/solver/lm.py`, `comms/bus.py`. Also robot/core.py and "
        "dran_edge/{errors,config}.py, tests/test_lm.py::test_x, docs/<file>.md, "
        "not shared/data/g2o nor foo/dran_edge/x.py"
    )
    assert mentioned_paths(text) == [
        "dran_edge/solver/lm.py",
        "comms/bus.py",
        "robot/core.py",
        "dran_edge/errors.py",
        "dran_edge/config.py",
        "tests/test_lm.py",
    ]
    assert resolve("robot/core.py") == ROOT / "dran_edge" / "robot" / "core.py"


@pytest.mark.parametrize("doc", DOCS, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_path_a_doc_names_exists(doc):
    missing = sorted({p for p in mentioned_paths(doc.read_text()) if not resolve(p).exists()})
    assert not missing, f"{doc.relative_to(ROOT)} names paths that do not exist: {missing}"


def test_the_readme_command_table_points_at_existing_docs():
    readme = (ROOT / "README.md").read_text()
    table = readme[readme.index("## Commands") : readme.index("## On a robot")]
    docs = re.findall(r"`([\w/.-]+\.md)`", table)
    assert docs, "the README's command table names no doc"
    assert [d for d in docs if not (ROOT / d).exists()] == []
