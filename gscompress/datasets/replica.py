"""Replica as rendered and laid out by NICE-SLAM (and used by SplaTAM).

A scene folder holds `results/frameNNNNNN.jpg`, `results/depthNNNNNN.png` (uint16, 6553.5 units
per metre) and `traj.txt`, one camera-to-world pose per line as 16 row-major numbers; line i is
the pose of frame i. Intrinsics are fx = fy = 600, cx = 599.5, cy = 339.5 at 1200x680 unless
the scene folder holds an `intrinsics.json` (as a TUM folder does), or a `cam_params.json`
(NICE-SLAM schema `{"camera": {"w", "h", "fx", "fy", "cx", "cy", "scale"}}`) sits in the scene
folder or its parent (the dataset root), in that order. Replica has no timestamps: frame i
gets i / 30 s. A missing traj.txt gives a sequence without poses; a traj.txt with fewer poses
than frames is an error.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from gscompress.camera import Intrinsics
from gscompress.datasets.base import (
    DepthCoding,
    FileSequence,
    FrameRecord,
    FrameSelection,
    read_intrinsics_file,
)
from gscompress.errors import DatasetError
from gscompress.io.files import read_text

REPLICA_INTRINSICS = Intrinsics(600.0, 600.0, 599.5, 339.5, 1200, 680)
REPLICA_DEPTH_SCALE = 6553.5
REPLICA_FPS = 30.0

_FRAME_RE = re.compile(r"^frame(\d+)\.(?:jpg|jpeg|png)$", re.IGNORECASE)


def find_replica_scene(path: Path) -> Path | None:
    """The scene folder: `path` itself, or its only child that is a scene; None if neither."""
    if (path / "results").is_dir():
        return path
    children = [c for c in sorted(path.iterdir()) if c.is_dir() and (c / "results").is_dir()]
    return children[0] if len(children) == 1 else None


def read_replica_traj(path: Path) -> np.ndarray:
    """[N, 4, 4] camera-to-world poses from a NICE-SLAM traj.txt (16 numbers per line)."""
    not_a_pose = "expected 16 finite numbers (a 4x4 pose)"
    rows: list[list[float]] = []
    linenos: list[int] = []
    lines = read_text(path, "trajectory", DatasetError).splitlines()
    for lineno, raw in enumerate(lines, start=1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        try:
            values = [float(v) for v in line.split()]
        except ValueError:
            raise DatasetError(f"{path}:{lineno}: not a number") from None
        if len(values) != 16:
            raise DatasetError(f"{path}:{lineno}: {not_a_pose}")
        rows.append(values)
        linenos.append(lineno)
    poses = np.array(rows, dtype=np.float64).reshape(-1, 4, 4)
    # Checked on the whole array at once: per line they were slow on a long trajectory
    # (docs/design-experiments.md, "Start-up").
    checks = (
        (np.isfinite(poses).all(axis=(1, 2)), not_a_pose),
        (
            np.isclose(poses[:, 3], [0.0, 0.0, 0.0, 1.0], atol=1e-6).all(axis=1),
            "last row of the pose is not 0 0 0 1",
        ),
    )
    for ok, message in checks:  # the first failing check, at its first line
        if not ok.all():
            raise DatasetError(f"{path}:{linenos[int(np.argmin(ok))]}: {message}")
    return poses


def open_replica(
    path: Path,
    selection: FrameSelection,
    size: tuple[int, int] | None = None,
    intrinsics: Intrinsics | Path | None = None,
) -> FileSequence:
    """Open a NICE-SLAM Replica scene folder (or a folder holding exactly one).

    Args:
        path: scene folder (with results/ and traj.txt) or its single-scene parent.
        selection: frame subset.
        size: working size (W, H), or None for 1200x680.
        intrinsics: explicit intrinsics or a JSON file; overrides the scene's files.
    """
    scene = find_replica_scene(path)
    if scene is None:
        raise DatasetError(f"{path} is not a Replica (NICE-SLAM) scene folder: no results/")
    results = scene / "results"
    frames: dict[int, Path] = {}
    for p in results.iterdir():
        m = _FRAME_RE.match(p.name)
        if m:
            frames[int(m.group(1))] = p
    if not frames:
        raise DatasetError(f"no results/frame*.jpg in {scene}")
    numbers = sorted(frames)
    records: list[FrameRecord] = []
    traj_file = scene / "traj.txt"
    poses = read_replica_traj(traj_file) if traj_file.is_file() else None
    if poses is not None and len(poses) <= numbers[-1]:
        raise DatasetError(f"{traj_file} has {len(poses)} poses but frame {numbers[-1]} needs one")
    for n in numbers:
        depth_path = results / f"depth{n:06d}.png"
        if not depth_path.is_file():
            raise DatasetError(f"depth image for {frames[n].name} not found: {depth_path}")
        records.append(
            FrameRecord(n / REPLICA_FPS, frames[n], depth_path, None if poses is None else poses[n])
        )

    depth = DepthCoding()
    if isinstance(intrinsics, Intrinsics):
        native = intrinsics
    elif intrinsics is not None:
        native, depth = read_intrinsics_file(Path(intrinsics))
    else:
        native = REPLICA_INTRINSICS
        candidates = ("intrinsics.json", "cam_params.json", "../cam_params.json")
        for cand in (scene / name for name in candidates):
            if cand.is_file():
                native, depth = read_intrinsics_file(cand)
                break
    name = scene.name if scene == path else f"{path.resolve().name}/{scene.name}"
    return FileSequence(
        name,
        records,
        native,
        depth.with_default_scale(REPLICA_DEPTH_SCALE),
        selection,
        size,
    )
