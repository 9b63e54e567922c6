"""`gsc align`: the rigid transform from one agent's world frame to another's, from their maps.

Reads the two logs' maps (the last snapshots) and camera centres, aligns them with
`gscompress.ops.align` and writes the transform as `--share-transform` reads it (a 4x4 matrix,
source world -> target world), so that `gsc merge --share-transform` and `gsc slam --inject`
take it as it is. `gsc share --align-to` uses `align_logs_transform` to cut a share already in
the target's frame.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from gscompress.io.files import check_output, sha256, write_text_atomic
from gscompress.io.mcap_log import LogReader
from gscompress.ops.align import (
    AlignmentError,
    AlignOptions,
    Cloud,
    align_clouds,
    map_cloud,
)


def log_cloud(path: str | Path) -> tuple[Cloud, str]:
    """What registration sees of a log's map (see `gscompress.ops.align.map_cloud`), with the
    camera centres of its estimated poses, and the log's recorded world frame."""
    from gscompress.camera import quat_to_rotmat

    with LogReader(path) as log:
        gaussians = log.read_map()
        world = log.metadata.world_frame
        _, poses = log.read_poses()
    rotations = None if gaussians.isotropic else quat_to_rotmat(gaussians.rotations())
    cloud = map_cloud(
        gaussians.means,
        gaussians.colors(),
        gaussians.opacities(),
        scales=gaussians.scales(),
        rotations=rotations,
        viewpoints=poses[:, :3, 3] if len(poses) else None,
    )
    return cloud, world


def align_logs_transform(
    source: str | Path,
    target: str | Path,
    init: str | Path | None = None,
    options: AlignOptions | None = None,
) -> tuple[np.ndarray, dict[str, Any]]:
    """The transform from `source`'s world frame to `target`'s and what to record of it.

    Raises:
        AlignmentError: the alignment cannot be trusted (the message names both logs).
    """
    from gscompress.io.trajectory import read_transform

    src_cloud, src_world = log_cloud(source)
    tgt_cloud, tgt_world = log_cloud(target)
    T0 = None if init is None else read_transform(init)
    try:
        alignment = align_clouds(src_cloud, tgt_cloud, options, init=T0)
    except AlignmentError as exc:
        raise AlignmentError(f"align {Path(source).name} to {Path(target).name}: {exc}") from None
    record = alignment.to_dict()
    record.pop("hypotheses")
    record.update(
        source=str(source),
        target=str(target),
        source_world_frame=src_world,
        target_world_frame=tgt_world,
        source_gaussians=len(src_cloud.points),
        target_gaussians=len(tgt_cloud.points),
    )
    return alignment.T_target_source, record


def align_logs(
    source: str | Path,
    target: str | Path,
    dst: str | Path,
    *,
    init: str | Path | None = None,
    options: AlignOptions | None = None,
    force: bool = False,
) -> dict[str, Any]:
    """Align `source`'s map to `target`'s and write the transform to `dst`.

    Args:
        source: the log whose world frame is mapped from (e.g. the sender of a share).
        target: the log whose world frame is mapped into (the receiver).
        dst: the transform file (text; 16 numbers, row-major 4x4, after `#` comment lines
            saying what it maps and how well).
        init: a transform file with an initial guess (skips the global step).
        options: alignment settings and refusal thresholds.
        force: overwrite `dst`.

    Returns:
        The transform (`T_target_source`, nested lists) with overlap, residual, inliers,
        ambiguity, conditioning, seconds, and both logs' names and world frames.

    Raises:
        AlignmentError: the result cannot be trusted; nothing is written.
    """
    inputs = [source, target] + ([init] if init is not None else [])
    check_output(dst, inputs, force, ".txt")
    T, record = align_logs_transform(source, target, init, options)
    write_transform_file(dst, T, record)
    record["output"] = str(dst)
    return record


def write_transform_file(dst: str | Path, T: np.ndarray, record: dict[str, Any]) -> None:
    """The transform file of an alignment: what it maps and how well, then the matrix."""
    from gscompress.io.trajectory import format_transform

    inliers = "" if record["inliers"] is None else f", {record['inliers']} feature inliers"
    comments = [
        f"gsc align: T_target_source maps points of {Path(record['source']).name}'s world frame "
        f"({record['source_world_frame'] or 'unknown'}) into {Path(record['target']).name}'s "
        f"({record['target_world_frame'] or 'unknown'})",
        f"overlap {record['overlap']:.3f}, residual {record['residual']:.4f} m{inliers}, "
        f"ambiguity {record['ambiguity']:.3f}, conditioning {record['conditioning']:.4f}",
        "use: gsc merge TARGET.mcap SHARE.mcap --share-transform THIS_FILE ...",
    ]
    write_text_atomic(dst, format_transform(T, comments))


def share_alignment(source: str | Path, target: str | Path) -> tuple[np.ndarray, dict[str, Any]]:
    """`gsc share --align-to`: the transform from `source`'s frame to `target`'s, and what the
    share records of it (target name, sha256, world frame, figures)."""
    T, record = align_logs_transform(source, target)
    keep = ("overlap", "residual", "inliers", "ambiguity", "conditioning", "target_world_frame")
    out = {k: record[k] for k in keep}
    out.update(target=Path(target).name, target_sha256=sha256(target),
               transform=np.round(T, 12).tolist())  # fmt: skip
    return T, out
