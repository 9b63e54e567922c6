"""What the viewer shows of a file: a log's map snapshots, poses, ground truth, keyframes and
camera, or the one map of a PLY / SPZ file. Snapshots are decoded when first shown.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from gscompress.camera import Intrinsics
from gscompress.gaussians import GaussianMap
from gscompress.io.map_files import read_map_file
from gscompress.io.mcap_log import (
    TOPIC_GAUSSIANS,
    TOPIC_POSE_GT,
    LogMetadata,
    LogReader,
)
from gscompress.pipeline.logs import keyframe_positions, recorded_keyframes


@dataclass
class MapSource:
    """A log or a map file, read for viewing.

    Attributes:
        path: the file.
        is_log: an MCAP log (else a PLY / SPZ map file: one snapshot, no poses).
        metadata: the log's metadata (empty for a map file).
        snapshot_times_ns: [S] log times of the `/gaussians` snapshots.
        poses: [P, 4, 4] estimated camera-to-world poses (empty without).
        poses_gt: [G, 4, 4] ground-truth camera-to-world poses (empty without).
        pose_ns: [P] log times of the estimated poses.
        pose_gt_ns: [G] log times of the ground-truth poses.
        recorded_keyframes: log times of the frames the log's stats mark as keyframes (None
            when they mark none: see `keyframes`).
        intrinsics: the log's camera, or None.
    """

    path: Path
    is_log: bool
    metadata: LogMetadata
    snapshot_times_ns: np.ndarray
    poses: np.ndarray
    poses_gt: np.ndarray
    pose_ns: np.ndarray
    pose_gt_ns: np.ndarray
    recorded_keyframes: set[int] | None
    intrinsics: Intrinsics | None
    _maps: dict[int, GaussianMap] = field(default_factory=dict, repr=False)

    @classmethod
    def open(cls, path: str | Path) -> MapSource:
        """Read a log's poses, camera and snapshot times (the last snapshot decoded), or a map
        file's map.

        Raises:
            LogFormatError, PlyFormatError, SpzFormatError: not a readable log or map file.
        """
        path = Path(path)
        empty = np.zeros((0, 4, 4))
        if path.suffix.lower() != ".mcap":
            gaussians = read_map_file(path)
            none = np.zeros(0, np.int64)
            return cls(
                path,
                False,
                LogMetadata(),
                np.zeros(1, np.int64),
                empty,
                empty,
                none,
                none,
                None,
                None,
                {0: gaussians},
            )
        with LogReader(path) as reader:
            count = reader.require_snapshots()
            times = np.array(
                [m.log_time for _s, _c, m in reader.iter_messages([TOPIC_GAUSSIANS])], np.int64
            )
            last = reader.read_map()
            found = reader.read_trajectory()
            pose_ns, poses = found.times_ns, found.T_world_cam
            gt_ns, poses_gt = reader.read_poses(TOPIC_POSE_GT)
            metadata = reader.metadata
            recorded = recorded_keyframes(reader)
            intrinsics = reader.read_intrinsics()
        return cls(
            path,
            True,
            metadata,
            times,
            poses,
            poses_gt,
            pose_ns,
            gt_ns,
            recorded,
            intrinsics,
            {count - 1: last},
        )

    def keyframes(self) -> list[int]:
        """Positions among `poses` of the log's keyframes (`KEYFRAME_RULE`; for a log whose
        stats mark none, by its SLAM config, which loads torch: seconds)."""
        return keyframe_positions(self.pose_ns, self.recorded_keyframes, self.metadata.config)

    def keyframe_truth(self, keyframes: list[int]) -> np.ndarray:
        """[K', 4, 4] the ground-truth poses at the log times of these keyframes (those that
        have one)."""
        at = {int(t): i for i, t in enumerate(self.pose_gt_ns)}
        found = [at[int(t)] for t in self.pose_ns[keyframes] if int(t) in at]
        return self.poses_gt[found]

    @property
    def snapshot_count(self) -> int:
        """How many map snapshots there are (1 for a map file)."""
        return len(self.snapshot_times_ns)

    def snapshot(self, index: int = -1) -> GaussianMap:
        """The map of snapshot `index` (-1: the last, "the map")."""
        index %= self.snapshot_count
        if index not in self._maps:
            with LogReader(self.path) as reader:
                self._maps[index] = reader.read_map(index)
        return self._maps[index]
