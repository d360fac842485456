"""tools/deb_src_entries.py: deb-src lines for the distribution's archive only (not ROS's)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
spec = importlib.util.spec_from_file_location(
    "deb_src_entries", ROOT / "tools" / "deb_src_entries.py"
)
dse = importlib.util.module_from_spec(spec)
spec.loader.exec_module(dse)

POLICY = """Package files:
 100 /var/lib/dpkg/status
     release a=now
 500 http://packages.ros.org/ros/ubuntu jammy/main arm64 Packages
     release v=22.04,o=ROS,a=jammy,n=jammy,l=ROS,c=main,b=arm64
     origin packages.ros.org
 500 http://mirrors.example.cn/ubuntu-ports jammy/universe arm64 Packages
     release v=22.04,o=Ubuntu,a=jammy,n=jammy,l=Ubuntu,c=universe,b=arm64
     origin mirrors.example.cn
"""


def _etc(tmp_path: Path) -> Path:
    etc = tmp_path / "apt"
    (etc / "sources.list.d").mkdir(parents=True)
    (etc / "sources.list").write_text(
        "deb http://ports.ubuntu.com/ubuntu-ports jammy main universe  # archive\n"
        "deb http://mirrors.example.cn/ubuntu-ports jammy main universe\n"
        "# deb http://ports.ubuntu.com/ubuntu-ports jammy-backports main\n"
    )
    (etc / "sources.list.d" / "ros-latest.list").write_text(
        "deb [signed-by=/usr/share/keyrings/ros.gpg] "
        "http://packages.ros.org/ros/ubuntu jammy main\n"
    )
    (etc / "sources.list.d" / "debian.sources").write_text(
        "Types: deb\nURIs: http://deb.debian.org/debian\nSuites: bookworm bookworm-updates\n"
        "Components: main\nSigned-By: /usr/share/keyrings/debian-archive-keyring.gpg\n\n"
        "Types: deb\nURIs: https://packages.ros.org/ros2/ubuntu\nSuites: jammy\nComponents: main\n"
    )
    return etc


def test_archive_lines_only_ros_left_out(tmp_path):
    lines = dse.entries(str(_etc(tmp_path)), official=dse.apt_origins(POLICY))
    assert lines == [
        "deb-src http://ports.ubuntu.com/ubuntu-ports jammy main universe",
        "deb-src http://mirrors.example.cn/ubuntu-ports jammy main universe",
        "deb-src [signed-by=/usr/share/keyrings/debian-archive-keyring.gpg] "
        "http://deb.debian.org/debian bookworm main",
        "deb-src [signed-by=/usr/share/keyrings/debian-archive-keyring.gpg] "
        "http://deb.debian.org/debian bookworm-updates main",
    ]
    assert not any("ros" in line for line in lines)


def test_without_apt_lists_a_mirror_is_not_guessed(tmp_path):
    lines = dse.entries(str(_etc(tmp_path)), official=set())
    assert not any("example.cn" in line or "ros" in line for line in lines)
    assert any("ports.ubuntu.com" in line for line in lines)
