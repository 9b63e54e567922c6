"""`gsc align`: the rigid transform from one agent's world frame to another's, from their maps.

Reads the two logs' maps (the last snapshots) and camera centres, aligns them with
`gscompress.ops.align` (`gscompress.pipeline.aligning.align_logs_transform`, which `gsc share
--align-to` uses too) and writes the transform as `--share-transform` reads it (a 4x4 matrix,
source world -> target world), so that `gsc merge --share-transform` and `gsc slam --inject`
take it as it is.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from gscompress.io.files import check_output, write_text_atomic
from gscompress.io.mcap_log import LogReader
from gscompress.ops.align import (
    AlignOptions,
)
from gscompress.pipeline.aligning import align_logs_transform, log_cloud, refined_on_frames


def align_logs(
    source: str | Path,
    target: str | Path,
    dst: str | Path,
    *,
    init: str | Path | None = None,
    options: AlignOptions | None = None,
    seq: str | Path | None = None,
    recording: Any = None,
    force: bool = False,
    phases: Callable[[str, int, int | None], object] | None = None,
) -> dict[str, Any]:
    """Align `source`'s map to `target`'s and write the transform to `dst`.

    Args:
        source: the log whose world frame is mapped from (e.g. the sender of a share).
        target: the log whose world frame is mapped into (the receiver).
        dst: the transform file (text; 16 numbers, row-major 4x4, after `#` comment lines
            saying what it maps and how well).
        init: a transform file with an initial guess (skips the global step).
        options: alignment settings and refusal thresholds.
        seq: the target's sequence: refine the registration on its frames (`refined_on_frames`).
        recording: a recording's topics, pairing and ground truth when `seq` is one
            (`gscompress.datasets.RecordingOptions`; None: those the target's run recorded).
        force: overwrite `dst`.
        phases: its progress (`align_logs_transform`).

    Returns:
        The transform (`T_target_source`, nested lists) with overlap, residual, inliers,
        ambiguity, conditioning, seconds, and both logs' names and world frames.

    Raises:
        AlignmentError: the result cannot be trusted; nothing is written.
    """
    inputs = [source, target] + ([init] if init is not None else [])
    check_output(dst, inputs, force, ".txt")
    T, record = align_logs_transform(
        source, target, init, options, seq, recording=recording, phases=phases
    )
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
    if on_frames := record.get("on_frames"):
        comments.insert(2, frames_text(on_frames))
    write_text_atomic(dst, format_transform(T, comments))


def frames_text(on_frames: dict[str, Any]) -> str:
    """One line on what the target's frames did to a transform (`align_logs_transform`)."""
    where = f"{on_frames['views']} frames of {Path(on_frames['seq']).name}"
    moved = f"{on_frames['change_cm']:.2f} cm, {on_frames['change_deg']:.2f} degrees"
    if on_frames.get("kept_registration"):
        return (
            f"kept the registration: refined on {where} the source would move {moved} and keep "
            f"only {on_frames['surface_kept']:.2f} of its overlap with the target's surfaces"
        )
    return f"then refined on {where}: moved {moved}"


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
    seq: str | Path | None = None,
) -> dict[str, Any]:
    """Two agents' alignment against the truth (`gsc experiment --anchor own`); with `seq`,
    refined on the target's frames (`align_logs_transform`).

    Writes the estimated transform to `estimated` and the one from the agents' ground-truth
    first-frame poses to `true`. An alignment that is refused still writes its estimate (so
    that what depends on it can run and be counted a miss) and says so in `refused`.

    Returns:
        `align_logs`'s figures, `refused` ("" when trusted), `error_cm` / `error_deg` of the
        estimate against the truth, and `drift_cm` / `drift_deg`: how far local refinement
        alone moves the true transform (the agents' own drift: their maps sit that far apart
        even when placed exactly). With `seq`, `on_frames` also holds the registration's error
        before the frames refined it and the drift as the frames see it (the true transform
        refined on them). A refused registration is refined on the frames too, and stays
        refused.
    """
    from gscompress.io.trajectory import format_transform
    from gscompress.ops.align import refine_alignment, transform_error

    T_true = first_frames_transform(source, target)
    write_text_atomic(true, format_transform(T_true, ["from the agents' ground-truth first poses"]))
    T, record = align_logs_transform(source, target, options=options, seq=seq, refuse=False)
    write_transform_file(estimated, T, record)
    src_cloud, _ = log_cloud(source)
    tgt_cloud, _ = log_cloud(target)
    drift = refine_alignment(src_cloud, tgt_cloud, T_true, options)
    dt, dr = transform_error(T, T_true)
    ot, orot = transform_error(drift.T_target_source, T_true)
    record.update(
        error_cm=100 * dt, error_deg=dr, drift_cm=100 * ot, drift_deg=orot, T_true=T_true.tolist()
    )
    if on_frames := record.get("on_frames"):  # (and the registration's, before the frames)
        rt, rr = transform_error(np.asarray(on_frames["T_registration"]), T_true)
        on_frames.update(registration_error_cm=100 * rt, registration_error_deg=rr)
        assert seq is not None
        T_drift, _ = refined_on_frames(source, target, seq, T_true)  # (the drift the frames see)
        ft, fr = transform_error(T_drift, T_true)
        on_frames.update(drift_cm=100 * ft, drift_deg=fr)
    return record
