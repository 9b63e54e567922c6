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
        where = f"align {Path(source).name} to {Path(target).name}"
        raise AlignmentError(f"{where}: {exc}", exc.alignment) from None
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


def first_frames_transform(source: str | Path, target: str | Path) -> np.ndarray:
    """The true transform from `source`'s world frame to `target`'s for two agents each at the
    identity at its own first frame: from the ground-truth poses of those first frames.

    Raises:
        InputError: a log without ground-truth poses.
    """
    from gscompress.errors import InputError
    from gscompress.io.mcap_log import TOPIC_POSE_GT

    firsts = []
    for path in (source, target):
        with LogReader(path) as log:
            _, poses = log.read_poses(TOPIC_POSE_GT)
        if not len(poses):
            raise InputError(f"{path} has no ground-truth poses to compare an alignment with")
        firsts.append(poses[0])
    return np.linalg.inv(firsts[1]) @ firsts[0]


def align_agents(
    source: str | Path,
    target: str | Path,
    estimated: str | Path,
    true: str | Path,
    options: AlignOptions | None = None,
) -> dict[str, Any]:
    """Two agents' alignment against the truth (`gsc experiment --anchor own`).

    Writes the estimated transform to `estimated` and the one from the agents' ground-truth
    first-frame poses to `true`. An alignment that is refused still writes its estimate (so
    that what depends on it can run and be counted a miss) and says so in `refused`.

    Returns:
        `align_logs`'s figures, `refused` ("" when trusted), `error_cm` / `error_deg` of the
        estimate against the truth, and `drift_cm` / `drift_deg`: how far local refinement
        alone moves the true transform (the agents' own drift: their maps sit that far apart
        even when placed exactly).
    """
    from gscompress.io.trajectory import format_transform
    from gscompress.ops.align import refine_alignment, transform_error

    T_true = first_frames_transform(source, target)
    write_text_atomic(true, format_transform(T_true, ["from the agents' ground-truth first poses"]))
    try:
        T, record = align_logs_transform(source, target, options=options)
        record["refused"] = ""
    except AlignmentError as exc:
        if exc.alignment is None:  # (nothing found at all)
            raise
        T, record = exc.alignment.T_target_source, exc.alignment.to_dict()
        record.pop("hypotheses")
        record.update(source=str(source), target=str(target), source_world_frame="",
                      target_world_frame="", refused=str(exc))  # fmt: skip
    write_transform_file(estimated, T, record)
    src_cloud, _ = log_cloud(source)
    tgt_cloud, _ = log_cloud(target)
    drift = refine_alignment(src_cloud, tgt_cloud, T_true, options)
    dt, dr = transform_error(T, T_true)
    ot, orot = transform_error(drift.T_target_source, T_true)
    record.update(error_cm=100 * dt, error_deg=dr, drift_cm=100 * ot, drift_deg=orot,
                  T_true=T_true.tolist())  # fmt: skip
    return record
