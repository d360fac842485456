"""The daemon's live view: its estimate on a Foxglove WebSocket server (``daemon.foxglove``).

:class:`LiveView` starts a ``foxglove-sdk`` WebSocket server on the configured ``ip:port``
with the topics of :mod:`.messages` for this robot (``/<robot>/path``, ``/<robot>/objects``,
``/<robot>/stats``) and, each time :meth:`LiveView.publish` is called (the daemon calls it
after every round, at most every ``min_period_s``), logs the robot's latest estimate and its
round statistics with the neighbour links from its status. Foxglove (app or web) connects to
``ws://<robot>:<port>``. Nothing is sent while no client is connected (the SDK drops it).
"""

from __future__ import annotations

import json
import time
from typing import Any

import numpy as np

from dran_edge.errors import DependencyError
from dran_edge.viz import messages as vm


class LiveView:
    """See the module docstring. ``port`` is the port the server listens on."""

    def __init__(self, robot: str, host: str, port: int, min_period_s: float = 0.5):
        try:
            import foxglove
            from foxglove.channels import PosesInFrameChannel, SceneUpdateChannel
        except ImportError:
            raise DependencyError(
                "daemon.foxglove is set but the foxglove-sdk package is not "
                "installed (pip install 'dran-edge[viz]'); set "
                'daemon.foxglove: "" to run without the live view'
            ) from None
        self.robot = robot
        self.min_period_s = min_period_s
        self.ctx = foxglove.Context()
        self.server = foxglove.start_server(
            name=f"dran-edge {robot}", host=host, port=port, context=self.ctx
        )
        self.path = PosesInFrameChannel(f"/{robot}/path", context=self.ctx)
        self.objects = SceneUpdateChannel(f"/{robot}/objects", context=self.ctx)
        self.stats = foxglove.Channel(
            f"/{robot}/stats", message_encoding="json", schema=vm.STATS_SCHEMA, context=self.ctx
        )
        self.published = 0
        self._last = float("-inf")

    @property
    def port(self) -> int:
        return int(self.server.port)

    def publish(self, estimate: Any, status: dict, now_ns: int | None = None) -> bool:
        """Log the estimate (an ``EstimateUpdate`` or None) and the status' round statistics;
        False when skipped (rate limit)."""
        mono = time.monotonic()
        if mono - self._last < self.min_period_s:
            return False
        self._last = mono
        t = time.time_ns() if now_ns is None else int(now_ns)
        graph = status.get("graph") or {}
        stats = {
            "round": graph.get("round"),
            "cost": graph.get("cost"),
            "consensus_error": graph.get("consensus_error"),
            "converged": graph.get("converged"),
            "keyframes": graph.get("keyframes"),
            "objects": graph.get("objects"),
            "neighbours": {
                str(k): {
                    "last_heard_s_ago": v.get("last_heard_s_ago"),
                    "bytes_received": v.get("bytes_received"),
                }
                for k, v in (status.get("neighbours") or {}).items()
            },
        }
        self.stats.log(json.dumps(stats, default=_plain).encode(), log_time=t)
        if estimate is not None and len(estimate.keyframe_stamps_ns):
            order = np.argsort(np.asarray(estimate.keyframe_stamps_ns), kind="stable")
            self.path.log(vm.path_message(t, np.asarray(estimate.T_world_body)[order]), log_time=t)
            self.objects.log(
                vm.objects_message(t, self.robot, 0, estimate.object_ids, estimate.T_world_object),
                log_time=t,
            )
        self.published += 1
        return True

    def close(self) -> None:
        self.server.stop()


def _plain(x: Any) -> Any:
    if isinstance(x, np.generic):
        return x.item()
    return str(x)
