"""The one exception hierarchy of dran-edge.

Messages say what was expected and what arrived. The CLI turns a ``DranError`` into one
clear line and an exit code; anything else is a bug and shows its traceback.
"""

from __future__ import annotations


class DranError(Exception):
    """Base of every error dran-edge raises on purpose."""

    exit_code = 1


class InputError(DranError):
    """A file or value given by the user is malformed (names the file, line and problem)."""

    exit_code = 2

    def __init__(self, message: str, *, path: str | None = None, line: int | None = None):
        where = ""
        if path is not None:
            where = f"{path}:{line}: " if line is not None else f"{path}: "
        super().__init__(where + message)
        self.path = path
        self.line = line


class ConfigError(InputError):
    """A configuration file is invalid (names the key path and the reason)."""

    #: The top-level section the problem is in ("comms", "neighbours", ...), where a report of
    #: several problems gives it (``config.load_config_report``); else None.
    section: str | None = None


class DecodeError(DranError):
    """Bytes that crossed a boundary (radio, ingest socket, recording) do not decode."""


class DependencyError(DranError):
    """An optional dependency (hardware library, draft ZeroMQ, ...) is missing or unusable."""

    exit_code = 3
