"""Helpers the command modules share for reading a log: its camera trajectory.

A `gsc slam` run that refines poses (`PoseConfig`) logs both the pose each frame was tracked at
(`/camera/pose`) and the trajectory as the mapping refined it (`/camera/pose_refined`); the
commands use the refined one (`trajectory`) and say so. Logs without it, including every log
written before refined trajectories existed, give their tracked poses.
"""

from __future__ import annotations

import logging
from pathlib import Path

from gscompress.io.mcap_log import LogReader, Trajectory

log = logging.getLogger(__name__)


def trajectory(reader: LogReader) -> Trajectory:
    """The log's camera trajectory (refined where it has one), logged as such when refined."""
    found = reader.read_trajectory()
    if found.refined:
        log.debug("%s: the %s trajectory", Path(reader.path).name, found.source)
    return found
