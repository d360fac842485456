"""OpenBLAS thread count of this process, for the shells that already run one process per core.

Process set-up only (replay workers, the simulator's rendering workers, benchmarks); the core never
calls it. Linux only (reads /proc/self/maps); elsewhere a no-op.
"""

from __future__ import annotations

_BLAS_SET = (
    "openblas_set_num_threads",
    "openblas_set_num_threads64_",
    "scipy_openblas_set_num_threads64_",
    "scipy_openblas_set_num_threads",
)
_BLAS_GET = (
    "openblas_get_num_threads",
    "openblas_get_num_threads64_",
    "scipy_openblas_get_num_threads64_",
    "scipy_openblas_get_num_threads",
)


def set_blas_threads(n: int | None) -> dict[str, int]:
    """Set the thread count of every OpenBLAS loaded in this process (numpy's and scipy's
    bundled copies); returns the previous counts by library path (``n=None``: only read them).

    Why: the replay already runs one process per core. OpenBLAS's own threads on top of that
    oversubscribe the cores, and the small dense products of a DRAN round then spend their
    time in thread hand-offs — measured 8x slower per round on the 2-core reference machine
    (docs/benchmarks.md, "Replay"). Linux only (reads /proc/self/maps); elsewhere a no-op.
    """
    import ctypes

    previous: dict[str, int] = {}
    try:
        with open("/proc/self/maps", encoding="utf-8") as f:
            paths = sorted(
                {line.split()[-1] for line in f if "openblas" in line.lower() and ".so" in line}
            )
    except OSError:
        return previous
    for path in paths:
        try:
            lib = ctypes.CDLL(path)
        except OSError:
            continue
        getter = next((getattr(lib, name) for name in _BLAS_GET if hasattr(lib, name)), None)
        setter = next((getattr(lib, name) for name in _BLAS_SET if hasattr(lib, name)), None)
        if getter is not None:
            getter.restype = ctypes.c_int
            previous[path] = int(getter())
        if setter is not None and n is not None:
            setter.argtypes = [ctypes.c_int]
            setter(int(n))
    return previous


def restore_blas_threads(previous: dict[str, int]) -> None:
    """Undo :func:`set_blas_threads` (per library)."""
    import ctypes

    for path, n in previous.items():
        lib = ctypes.CDLL(path)
        setter = next((getattr(lib, name) for name in _BLAS_SET if hasattr(lib, name)), None)
        if setter is not None:
            setter.argtypes = [ctypes.c_int]
            setter(int(n))
