"""`gsc score`: PWAS scores for an existing map from a sequence's views (needs torch)."""

from __future__ import annotations

import itertools
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from gscompress.errors import InputError
from gscompress.gaussians import GaussianMap
from gscompress.io.files import check_output
from gscompress.io.mcap_log import (
    LogMetadata,
    LogWriter,
    seconds_to_ns,
)
from gscompress.io.ply import read_ply
from gscompress.pipeline.offline import rewrite_map


def score_file(
    src: str | Path,
    dst: str | Path,
    seq: str | Path,
    *,
    poses: str | Path | None = None,
    frames: str = "all",
    size: tuple[int, int] | None = None,
    sigma_d: float = 20.0,
    backend: str = "auto",
    command: str = "",
    force: bool = False,
    progress: Callable[[int, int], object] | None = None,
) -> dict[str, Any]:
    """PWAS-score the map in `src` (a log or a 3DGS PLY) from the views of sequence `seq`.

    The map is rendered, not optimised, from every selected frame at its ground-truth pose or
    at the pose `poses` (a TUM trajectory) gives for its timestamp. An MCAP input is copied with
    its map replaced by the scored one; a PLY input becomes a new log with calibration, the view
    poses and the scored map. Needs torch (the renderer). `progress(done, total)` is called
    after each view.
    """
    from gscompress.datasets import open_sequence
    from gscompress.importance import PwasConfig
    from gscompress.ops.score import score_map
    from gscompress.render import resolve_device

    check_output(dst, [p for p in (src, seq, poses) if p is not None], force, ".mcap")
    if not sigma_d > 0:
        raise InputError(f"--sigma-d must be positive, got {sigma_d}")
    sequence = open_sequence(seq, size=size, frames=frames)
    stamps, T_world_cams = view_poses(sequence, poses)
    config = PwasConfig(sigma_d=sigma_d)
    device = resolve_device("auto", backend)  # the GPU when there is one, as gsc slam

    views = itertools.count(1)
    on_view = None if progress is None else lambda _: progress(next(views), len(T_world_cams))

    def score(gaussians: GaussianMap) -> tuple[GaussianMap, dict[str, Any]]:
        scored = score_map(
            gaussians, T_world_cams, sequence.intrinsics, config, backend=backend, device=device,
            progress=on_view,
        )  # fmt: skip
        seen = int(np.count_nonzero(scored.importance_weight > 0))
        return scored, {"views": len(T_world_cams), "gaussians": len(scored), "scored": seen}

    operation = {
        "name": "score",
        "sequence": sequence.name,
        "frames": str(frames),
        "poses": Path(poses).name if poses else "ground truth",
        "sigma_d": sigma_d,
        "size": list(size) if size else None,
    }
    if Path(src).suffix.lower() != ".ply":
        return rewrite_map(src, dst, operation, score, command=command, force=force)
    scored, results = score(read_ply(src))
    meta = LogMetadata(sequence=sequence.name, frames=str(frames)).derive(operation, src, command)
    meta.results = results
    with LogWriter(dst, meta, inputs=[src], force=force) as out:
        out.write_calibration(sequence.intrinsics, 0)
        for stamp, T in zip(stamps, T_world_cams, strict=True):
            out.write_pose(T, seconds_to_ns(stamp))
        out.write_gaussians(scored, seconds_to_ns(stamps[-1]) if len(stamps) else 0)
    return {"output": str(dst), **results}


def view_poses(sequence: Any, poses: str | Path | None) -> tuple[np.ndarray, np.ndarray]:
    """(timestamps [M], camera-to-world [M, 4, 4]) of a sequence's selected frames.

    From the sequence's ground truth, or from the TUM trajectory `poses` associated to the
    frames by nearest timestamp (within 0.02 s).
    """
    from gscompress.errors import DatasetError
    from gscompress.io.trajectory import nearest_times, read_tum_trajectory

    if poses is None:
        if not sequence.has_ground_truth:
            raise DatasetError(
                f"{sequence.name} has no ground-truth poses; pass --poses TRAJ.txt (TUM format)"
            )
        stamps, T = sequence.ground_truth()
        return np.asarray(stamps), np.asarray(T)
    trajectory = read_tum_trajectory(poses)
    stamps = np.asarray(sequence.timestamps)
    if len(trajectory) == 0:
        raise DatasetError(f"{poses} holds no poses")
    index = nearest_times(stamps, trajectory.timestamps, 0.02)
    if np.any(index < 0):
        missing = float(stamps[int(np.argmax(index < 0))])
        raise DatasetError(f"{poses} has no pose within 0.02 s of frame time {missing:.6f}")
    return stamps, trajectory.T_world_cam[index]
