"""`gsc merge`: inject another agent's share into a receiver's map and refine it there.

The receiver's log is copied with its map (the last snapshot) replaced by receiver + share,
refined on the receiver's own frames (all of them, or its keyframes only) at the receiver's
estimated poses (see `gscompress.ops.merge`). Both inputs are in the output's provenance: the
receiver as the parent, the share (name, sha256, id offset) in the merge operation. Maps are
merged only when their world frames agree (`LogMetadata.world_frame`).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from gscompress.errors import LogFormatError, OptionError
from gscompress.gaussians import GaussianMap
from gscompress.io.files import check_output, sha256
from gscompress.io.mcap_log import TOPIC_POSE, LogReader
from gscompress.ops.merge import REFINE_VIEWS, check_same_world
from gscompress.ops.select import is_fraction
from gscompress.pipeline.offline import rewrite_map

DEFAULT_REFINE_VIEWS = "frames"
"""What a merge refines on unless told (`REFINE_VIEWS`): every frame of the receiver's subset.
Keyframes alone are few (5 of tabletop's 25 even frames), and 200 iterations on them lowered
the receiver's PSNR on its other frames; every frame raises it."""
DEFAULT_LR_FINAL = 0.3
"""A merge's learning rates decay to this fraction over its refinement. Its optimizer is fresh,
so at constant rates its first steps are as large as the last ones and leave a finished map
little better (tabletop's unpruned Table 3 map, 200 iterations on every frame: 26.63 -> 26.61
dB; decaying to 0.1: 27.34 dB). In the Table 4 merges of five sequences (README), 0.3 lifted
every merge on tabletop, office and ICL by 0.29-0.43 dB against constant rates and was ahead of
0.5 and 0.1 there (tied with 0.1 once); on the synthetic room and replica the merged shares
ended 0.01-0.13 dB below constant rates and 0.00-0.08 dB below 0.5."""


def read_share(
    share: str | Path, receiver_world: str, what: str, transform: str | Path | None = None
) -> tuple[GaussianMap, dict[str, Any]]:
    """A share's map in the receiver's world frame, and what to record of it.

    Without `transform` the share's recorded world frame must be the receiver's; with it, the
    share is moved by the transform in the file (share frame -> receiver frame) instead.

    Raises:
        MapError: world frames unknown or different (without a transform).
    """
    from gscompress.io.trajectory import read_transform
    from gscompress.ops.merge import transform_map

    with LogReader(share) as share_log:
        shared = share_log.read_map()
        world = share_log.metadata.world_frame
    record: dict[str, Any] = {"share": Path(share).name, "share_sha256": sha256(share)}
    if transform is None:
        check_same_world(receiver_world, world, what)
    else:
        T = read_transform(transform)
        shared = transform_map(shared, T)
        record.update(share_world_frame=world, transform=np.round(T, 12).tolist())
    return shared, record


def merge_logs(
    receiver: str | Path,
    share: str | Path | None,
    dst: str | Path,
    *,
    seq: str | Path | None = None,
    frames: str | None = None,
    size: tuple[int, int] | None = None,
    iters: int = 200,
    views: str = DEFAULT_REFINE_VIEWS,
    lr_final: float = DEFAULT_LR_FINAL,
    device: str = "auto",
    backend: str | None = None,
    seed: int = 0,
    share_transform: str | Path | None = None,
    codec: str | None = None,
    command: str = "",
    force: bool = False,
    progress: Callable[[int, int], object] | None = None,
) -> dict[str, Any]:
    """Merge the share log `share` into the receiver log `receiver` and write `dst`.

    Args:
        receiver: the receiving agent's SLAM log (map, poses, config).
        share: a share (`gsc share`) or any log whose last snapshot is the map to inject;
            None refines the receiver's map alone (the control of a merge: the same refinement
            without a share).
        dst: the output log.
        seq: the receiver's sequence (needed when `iters` > 0).
        frames: the receiver's frame subset (default: the one recorded in its log).
        size: working size (default: the receiver's config).
        iters: refinement iterations on the receiver's views (0: concatenate only).
        views: "frames" (every frame of the receiver's subset) or "keyframes" (its keyframes).
        lr_final: the refinement's learning rates decay geometrically to this fraction of
            their starting value (the receiver's mapping rates); 1 keeps them constant.
        device: torch device, or "auto".
        backend: render backend of the refinement (default: the receiver's config's).
        seed: seed of the view order.
        share_transform: a file with the rigid transform from the share's world frame to the
            receiver's (4x4 or TUM `tx ty tz qx qy qz qw`), for maps whose frames differ.
        codec: how the merged map is stored (None: as the receiver's map).
        command: the command line, for the metadata.
        force: overwrite `dst`.
        progress: called with (iterations done, iterations) during refinement.

    Returns:
        Output path, Gaussian counts (receiver, share, merged), the id offset given to the
        share, and the refinement's first/last loss, views and render backend.
    """
    from gscompress.ops.merge import merge_maps

    if iters < 0:
        raise OptionError(f"--iters must be >= 0, got {iters}")
    if views not in REFINE_VIEWS:
        raise OptionError(f"--views is one of {', '.join(REFINE_VIEWS)}, got {views!r}")
    if not is_fraction(lr_final):
        raise OptionError(f"--lr-final must be in (0, 1], got {lr_final}")
    if iters > 0 and seq is None:
        raise OptionError("refining needs the receiver's sequence: pass --seq (or --iters 0)")
    inputs = [receiver] + [p for p in (share, seq, share_transform) if p is not None]
    check_output(dst, inputs, force, ".mcap")
    if share is not None and Path(share).exists() and Path(share).samefile(receiver):
        raise OptionError(f"{share} is the receiver log itself: merging it would double its map")
    with LogReader(receiver) as receiver_log:
        meta = receiver_log.metadata
        receiver_log.require_snapshots()
        pose_ns, poses = receiver_log.read_poses(TOPIC_POSE) if iters > 0 else (None, None)
    shared: GaussianMap | None = None
    share_record: dict[str, Any] = {"share": None}
    if share is not None:
        shared, share_record = read_share(share, meta.world_frame, "merge", share_transform)

    def merge(own: GaussianMap) -> tuple[GaussianMap, dict[str, Any]]:
        received = shared if shared is not None else GaussianMap.empty(own.isotropic, own.sh_degree)
        merged, offset = merge_maps(own, received)
        results: dict[str, Any] = {
            "receiver": len(own),
            "share": len(received),
            "gaussians": len(merged),
            "id_offset": offset,
        }
        if iters > 0:
            assert seq is not None
            assert pose_ns is not None and poses is not None
            merged, stats = _refine(
                merged, receiver, meta, pose_ns, poses, seq, frames, size, iters, views,
                lr_final, device, backend, seed, progress,
            )  # fmt: skip
            results.update({f"refine_{k}": v for k, v in stats.items()})
        return merged, results

    operation = {"name": "merge", **share_record, "iters": iters, "views": views,
                 "lr_final": lr_final, "seed": seed, "backend": backend}  # fmt: skip
    out = rewrite_map(receiver, dst, operation, merge, codec=codec, command=command, force=force)
    return out


def _refine(
    merged: GaussianMap,
    receiver: str | Path,
    meta: Any,
    pose_ns: np.ndarray,
    poses: np.ndarray,
    seq: str | Path,
    frames: str | None,
    size: tuple[int, int] | None,
    iters: int,
    views: str,
    lr_final: float,
    device: str,
    backend: str | None,
    seed: int,
    progress: Callable[[int, int], object] | None,
) -> tuple[GaussianMap, dict[str, Any]]:
    """Refine `merged` on the receiver's frames or keyframes (`views`) at its estimated poses
    (log times, poses)."""
    from gscompress.ops.merge import refine
    from gscompress.pipeline.evaluate import frames_with_poses, open_log_sequence
    from gscompress.render import resolve_backend, resolve_device
    from gscompress.slam.config import DEFAULT_PRESET, SlamConfig, preset
    from gscompress.slam.keyframes import View, in_views

    config = SlamConfig.from_dict(meta.config) if meta.config else preset(DEFAULT_PRESET)
    if backend is not None:
        config = config.with_overrides(backend=backend)
    sequence = open_log_sequence(seq, receiver, meta, frames, size or config.size)
    if len(pose_ns) == 0:
        raise LogFormatError(f"{receiver} has no {TOPIC_POSE}: refinement needs its poses")
    positions, pose_index = frames_with_poses(sequence, pose_ns, receiver)
    torch_device = resolve_device(device, config.backend)
    chosen = [
        View.from_frame(k, sequence.frame(int(p)), poses[i], torch_device)
        for k, (p, i) in enumerate(zip(positions, pose_index, strict=True))
        if in_views(k, views, config.keyframes)
    ]
    done = 0

    def step(n: int) -> None:
        nonlocal done
        done += n
        if progress is not None:
            progress(done, iters)

    refined, stats = refine(
        merged, chosen, sequence.intrinsics, config, iters, device=torch_device, seed=seed,
        lr_final_fraction=lr_final, progress=step,
    )  # fmt: skip
    stats["views"] = len(chosen)
    stats["backend"] = resolve_backend(config.backend, torch_device)
    return refined, stats
