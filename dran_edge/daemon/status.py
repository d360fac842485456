"""Client of the daemon's status socket: one JSON document per connection."""

from __future__ import annotations

import json
import socket
from pathlib import Path

from dran_edge.errors import DranError


def query_status(path: str | Path, timeout_s: float = 2.0) -> dict:
    """The daemon's status document; DranError when nothing answers at ``path``."""
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.settimeout(timeout_s)
    try:
        s.connect(str(path))
        chunks = []
        while True:
            data = s.recv(65536)
            if not data:
                break
            chunks.append(data)
    except OSError as exc:
        raise DranError(f"no daemon answers at {path}: {exc.strerror or exc}") from None
    finally:
        s.close()
    try:
        return json.loads(b"".join(chunks))
    except ValueError:
        raise DranError(f"the daemon at {path} sent an unreadable status") from None
