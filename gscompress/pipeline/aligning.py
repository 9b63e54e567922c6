"""Aligning one log's world frame to another's from their maps (and the target's frames).

What `gsc align` writes (`gscompress.pipeline.align`) and what `gsc share --align-to` cuts a
share in: the two logs' maps (the last snapshots) and camera centres registered with
`gscompress.ops.align` (`align_logs_transform`), refined on the target's frames when its
sequence is given (`refined_on_frames`).
"""

from __future__ import annotations

import itertools
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from gscompress.io.mcap_log import LogReader
from gscompress.ops.align import (
    AlignmentError,
    AlignOptions,
    Cloud,
    align_clouds,
    map_cloud,
    refusal,
    surface_fit,
)
from gscompress.pipeline.logs import spread_keyframes, trajectory


def log_cloud(path: str | Path) -> tuple[Cloud, str]:
    """What registration sees of a log's map (see `gscompress.ops.align.map_cloud`), with the
    camera centres of its estimated poses, and the log's recorded world frame."""
    from gscompress.camera import quat_to_rotmat

    with LogReader(path) as log:
        gaussians = log.read_map()
        world = log.metadata.world_frame
        poses = trajectory(log).T_world_cam
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


VIEWS = 8
"""How many of the target's keyframes (spread over its run) refine a transform on its frames."""


FRAMES_TRUST = 2.0
"""With the target's frames, a registration refused only because too few feature matches agree
is accepted when, refined on the frames, the source draws them with a mean tracking loss at most
this many times the target's own map's. On tabletop's agents (a flat scene whose features
agree poorly) the refined transform drew them well within this and the registration, far off,
well beyond it (docs/align.md, "Refined on the target's frames")."""


SURFACE_KEPT = 0.8
"""The frames may not pull the source off the target's surfaces: the refined transform must keep
at least this fraction of the registration's share of source Gaussians within half a voxel of
a target Gaussian (`surface_fit`), else the registration's transform is kept. On the agent
pairs of three scenes the refined transforms kept more than this; on the test suite's small
map, too coarse to draw its own frames well, the frames pulled a self-alignment off and kept
less (docs/align.md, "Refined on the target's frames")."""


REGISTRATION = "registration"
"""The phase of an alignment that registers the two maps (`align_logs_transform`'s `phases`)."""


ON_FRAMES = "aligning on frames"
"""The phase of an alignment that refines it on the target's frames (steps: iterations)."""


def refined_on_frames(
    source: str | Path,
    target: str | Path,
    seq: str | Path,
    T: np.ndarray,
    views: int = VIEWS,
    recording: Any = None,
    progress: Callable[[int], object] | None = None,
) -> tuple[np.ndarray, dict[str, Any]]:
    """`T` refined on the target's own frames (`gscompress.ops.align_views`): `source`'s map
    rendered at `views` of `target`'s keyframes (of `seq`, at `target`'s estimated poses; a
    recording read with `recording`'s topics, None: those the target's run recorded).
    Returns the transform and what to record: the refinement's figures, `loss` and
    `target_loss`, the mean tracking loss over those frames of the source at the refined
    transform and of the target's own map, and the `seconds` it all took. `progress`: called
    with 1 after each iteration. Needs torch."""
    from gscompress.io.mcap_log import read_map
    from gscompress.ops.align_views import refine_on_views, view_loss

    started = time.perf_counter()
    chosen = spread_keyframes(target, views, seq, "aligning on the target's frames", recording)
    assert chosen.frames is not None  # (with a sequence)
    frames, poses, camera = chosen.frames, chosen.poses, chosen.intrinsics
    source_map = read_map(source)
    result = refine_on_views(source_map, T, frames, poses, camera, progress=progress)
    found = result.T_target_source
    record = {**result.record(T), "seq": str(seq)}
    record["loss"] = view_loss(source_map, found, frames, poses, camera)
    record["target_loss"] = view_loss(read_map(target), np.eye(4), frames, poses, camera)
    record["seconds"] = time.perf_counter() - started
    return found, record


def frames_verdict(record: dict[str, Any], target: str | Path) -> str:
    """Why the frames do not bear out a transform refined on them (`refined_on_frames`'s
    record), "" when they do: the source draws the target's frames at most `FRAMES_TRUST`
    times as badly as the target's own map."""
    loss, own = record["loss"], record["target_loss"]
    if loss is None or own is None:
        return f"the source draws none of {Path(target).name}'s frames"
    if loss > FRAMES_TRUST * own:
        return (
            f"on {Path(target).name}'s frames the source, refined on them, draws {loss / own:.1f}"
            f" times as badly as {Path(target).name}'s own map (at most {FRAMES_TRUST:g} trusted)"
        )
    return ""


def _judged_on_frames(
    logs: tuple[str | Path, str | Path, str | Path, Any],
    alignment: Any,
    clouds: tuple[Any, Any],
    record: dict[str, Any],
    refusal_so_far: tuple[str, bool],
    phases: Callable[[str, int, int | None], object] | None,
) -> tuple[np.ndarray, str]:
    """`align_logs_transform`'s step on the target's frames: the registration refined on them
    (kept only when the source stays on the target's surfaces), recorded in `record`; and, for a
    registration refused only for its feature matches (`refusal_so_far`: the reason, and
    whether the frames may overrule it), the frames' verdict. Returns the transform and what
    refuses it ("" when nothing)."""
    source, target, seq, recording = logs
    step = None
    if phases is not None:
        from gscompress.ops.align_views import VIEW_ALIGN

        iters, done = VIEW_ALIGN.iters, itertools.count(1)
        phases(ON_FRAMES, 0, iters)

        def step(_: int) -> None:
            phases(ON_FRAMES, next(done), iters)

    T = alignment.T_target_source
    refined, on_frames = refined_on_frames(source, target, seq, T, VIEWS, recording, step)
    on_frames["T_registration"] = record["T_target_source"]
    before, after = surface_fit(*clouds, [T, refined], alignment.voxel / 2)
    on_frames["surface_kept"] = after / max(before, 1e-12)
    if on_frames["surface_kept"] >= SURFACE_KEPT:
        T = refined
    else:  # (off the surfaces: the frames are not trusted, the registration stays)
        on_frames["kept_registration"] = True
    record["on_frames"] = on_frames
    record["T_target_source"] = T.tolist()
    refused, overrulable = refusal_so_far
    if overrulable:
        verdict = frames_verdict(on_frames, target)
        if on_frames.get("kept_registration"):
            verdict = (
                f"refined on {Path(target).name}'s frames the source leaves its surfaces "
                f"({on_frames['surface_kept']:.2f} of the overlap kept)"
            )
        if verdict:
            refused = f"{refused}; {verdict}"
        else:
            on_frames["overruled"], refused = refused, ""
    return T, refused


def align_logs_transform(
    source: str | Path,
    target: str | Path,
    init: str | Path | None = None,
    options: AlignOptions | None = None,
    seq: str | Path | None = None,
    refuse: bool = True,
    recording: Any = None,
    phases: Callable[[str, int, int | None], object] | None = None,
) -> tuple[np.ndarray, dict[str, Any]]:
    """The transform from `source`'s world frame to `target`'s and what to record of it; with
    `seq` (the target's sequence, a recording read with `recording`), the registration refined
    on the target's frames (`refined_on_frames`, recorded under `on_frames`). The frames also
    judge a registration whose only fault is that too few feature matches agree: it is
    accepted when they bear it out (`frames_verdict`; the overruled reason is recorded as
    `on_frames.overruled`). A refinement that pulls the source off the target's surfaces
    (`SURFACE_KEPT`) is not taken: the registration's transform stays
    (`on_frames.kept_registration`), and cannot be vouched for by the frames.

    With `refuse` False, an alignment that cannot be trusted is returned all the same (refined
    on the frames as any other), `refused` saying why; else it raises. `phases` is called with
    (phase, steps done, steps in total) as it goes: `REGISTRATION` as it starts, `ON_FRAMES`
    after each iteration on the frames.

    Raises:
        AlignmentError: the alignment cannot be trusted (the message names both logs); or
            nothing was found at all, even with `refuse` False.
    """
    from gscompress.io.trajectory import read_transform

    o = options or AlignOptions()
    src_cloud, src_world = log_cloud(source)
    tgt_cloud, tgt_world = log_cloud(target)
    T0 = None if init is None else read_transform(init)
    if phases is not None:
        phases(REGISTRATION, 0, None)
    where = f"align {Path(source).name} to {Path(target).name}"
    refused = ""
    try:
        alignment = align_clouds(src_cloud, tgt_cloud, o, init=T0)
    except AlignmentError as exc:
        if exc.alignment is None:  # (nothing found at all)
            raise AlignmentError(f"{where}: {exc}") from None
        alignment, refused = exc.alignment, str(exc)
    # (the frames may judge a registration whose only fault is its feature matches)
    overrulable = seq is not None and bool(refused)
    overrulable = overrulable and not refusal(alignment, replace(o, min_inliers=0))
    if refused and refuse and not overrulable:
        raise AlignmentError(f"{where}: {refused}", alignment)
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
    T = alignment.T_target_source
    if seq is not None:
        T, refused = _judged_on_frames(
            (source, target, seq, recording),
            alignment,
            (src_cloud, tgt_cloud),
            record,
            (refused, overrulable),
            phases,
        )
    if refused and refuse:
        raise AlignmentError(
            f"{where}: {refused}", replace(alignment, T_target_source=T, refused=refused)
        )
    record["refused"] = f"{where}: {refused}" if refused else ""
    return T, record
