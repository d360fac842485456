#!/usr/bin/env python3
"""deb-src twins of the distribution's own apt archive entries (for `apt-get source zeromq3`).

    deb_src_entries.py OUT_DIR      writes OUT_DIR/dran-deb-src.list (used by build_zmq_draft.sh)

Reads /etc/apt/sources.list, sources.list.d/*.list (one-line format) and *.sources (deb822).
Only entries of the distribution's own archive get a deb-src twin — not every line whose URL
happens to contain "debian" or "ubuntu": a ROS robot's ``http://packages.ros.org/ros/ubuntu
jammy main`` is a third-party repository (no zeromq3 source in it, and a deb-src line for it
makes ``apt-get update`` fail where the repository publishes no Sources index). An entry is the
distribution's archive when

1. apt itself says so: ``apt-cache policy`` lists the URI with a release whose origin (``o=``)
   is Debian or Ubuntu (this also covers mirrors such as ``mirrors.example.cn/ubuntu``); or
2. (apt has no lists yet) its host is one of Debian's or Ubuntu's archive hosts
   (``*.debian.org``, ``*.ubuntu.com``).
"""

from __future__ import annotations

import glob
import os
import re
import subprocess
import sys
from urllib.parse import urlparse

ORIGINS = ("debian", "ubuntu")
ARCHIVE_HOST = re.compile(r"(^|\.)(debian\.org|ubuntu\.com)$")


def apt_origins(policy_text: str) -> set[str]:
    """URIs whose release origin (``o=``) is Debian/Ubuntu, from ``apt-cache policy`` output."""
    official, uri = set(), None
    for line in policy_text.splitlines():
        m = re.match(r"^\s*-?\d+\s+(\S+://\S+)\s", line)
        if m:
            uri = m.group(1).rstrip("/")
            continue
        m = re.match(r"^\s+release\s+(.*)$", line)
        if m and uri:
            fields = dict(p.split("=", 1) for p in m.group(1).split(",") if "=" in p)
            if fields.get("o", "").lower() in ORIGINS:
                official.add(uri)
    return official


def is_archive(uri: str, official: set[str]) -> bool:
    """Whether ``uri`` is the distribution's own archive (see the module docstring)."""
    if uri.rstrip("/") in official:
        return True
    return bool(ARCHIVE_HOST.search(urlparse(uri).hostname or ""))


def _one_line(path: str, official: set[str]) -> list[str]:
    out = []
    for line in open(path, encoding="utf-8", errors="replace"):
        line = line.split("#", 1)[0].strip()
        m = re.match(r"^deb\s+(\[[^\]]*\]\s+)?(\S+)\s+(\S+)\s*(.*)$", line)
        if m and is_archive(m.group(2), official):
            out.append(f"deb-src {m.group(1) or ''}{m.group(2)} {m.group(3)} {m.group(4)}".strip())
    return out


def _deb822(path: str, official: set[str]) -> list[str]:
    out = []
    text = open(path, encoding="utf-8", errors="replace").read()
    for para in re.split(r"\n\s*\n", text):
        fields, key = {}, None
        for raw in para.splitlines():
            if raw.lstrip().startswith("#"):
                continue
            if raw[:1] in (" ", "\t") and key:
                fields[key] += "\n" + raw
                continue
            if ":" in raw:
                key, _, val = raw.partition(":")
                key = key.strip().lower()
                fields[key] = val.strip()
        if "deb" not in fields.get("types", "").split() or fields.get("enabled", "yes") == "no":
            continue
        uris = [u for u in fields.get("uris", "").split() if is_archive(u, official)]
        opts = ""
        if "signed-by" in fields and not fields["signed-by"].startswith("\n"):
            opts = f"[signed-by={fields['signed-by'].split()[0]}] "
        for uri in uris:
            for suite in fields.get("suites", "").split():
                out.append(f"deb-src {opts}{uri} {suite} {fields.get('components', '')}".strip())
    return out


def entries(etc_apt: str = "/etc/apt", official: set[str] | None = None) -> list[str]:
    """The deb-src lines for the archive entries configured under ``etc_apt``."""
    if official is None:
        try:
            policy = subprocess.run(
                ["apt-cache", "policy"], capture_output=True, text=True, check=False
            ).stdout
        except OSError:
            policy = ""
        official = apt_origins(policy)
    found = []
    for path in [f"{etc_apt}/sources.list"] + sorted(glob.glob(f"{etc_apt}/sources.list.d/*.list")):
        if os.path.exists(path):
            found += _one_line(path, official)
    for path in sorted(glob.glob(f"{etc_apt}/sources.list.d/*.sources")):
        found += _deb822(path, official)
    return list(dict.fromkeys(found))


def main(argv: list[str]) -> int:
    if len(argv) != 1:
        print(__doc__, file=sys.stderr)
        return 2
    found = entries()
    if not found:
        print("deb_src_entries: no Debian/Ubuntu archive entry in /etc/apt", file=sys.stderr)
        return 1
    os.makedirs(argv[0], exist_ok=True)
    with open(os.path.join(argv[0], "dran-deb-src.list"), "w", encoding="utf-8") as f:
        f.write("\n".join(found) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
