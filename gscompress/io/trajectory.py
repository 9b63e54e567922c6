"""TUM trajectory text files: `timestamp tx ty tz qx qy qz qw`, one pose per line.

The format that the TUM RGB-D benchmark, evo (`evo_ape tum GT EST`) and most SLAM systems read
and write. Poses are camera-to-world (`T_world_cam`). Reading is tolerant of `#` comments,
blank lines, surrounding whitespace and commas as separators, and strict on everything else: a
row that does not hold exactly eight finite numbers, or whose quaternion has zero length, is an
`InputError` that names the file and line.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gscompress.camera import is_zero_quaternion, pose_from_tum, pose_to_tum
from gscompress.errors import InputError, OutputError, clipped
from gscompress.io.files import check_output, read_text, write_text_atomic


@dataclass(frozen=True)
class Trajectory:
    """Timestamped camera-to-world poses.

    Attributes:
        timestamps: [N] float64 seconds, in file order.
        T_world_cam: [N, 4, 4] float64 camera-to-world transforms.
    """

    timestamps: np.ndarray
    T_world_cam: np.ndarray

    def __post_init__(self) -> None:
        n = len(self.timestamps)
        if np.shape(self.timestamps) != (n,) or np.shape(self.T_world_cam) != (n, 4, 4):
            raise InputError(
                f"trajectory needs timestamps [N] and poses [N, 4, 4], got "
                f"{np.shape(self.timestamps)} and {np.shape(self.T_world_cam)}"
            )

    def __len__(self) -> int:
        return len(self.timestamps)


def parse_tum_trajectory(text: str, source: str = "<text>") -> Trajectory:
    """Parse the text of a TUM trajectory file.

    Args:
        text: file content.
        source: the name used in error messages (usually the path).

    Returns:
        The trajectory (possibly empty).

    Raises:
        InputError: a row that is not eight finite numbers with a non-zero quaternion.
    """
    stamps: list[float] = []
    rows: list[list[float]] = []
    for lineno, raw in enumerate(text.splitlines(), start=1):
        line = raw.split("#", 1)[0].replace(",", " ").strip()
        if not line:
            continue
        fields = line.split()
        if len(fields) != 8:
            raise InputError(
                f"{source}:{lineno}: expected 8 numbers 'timestamp tx ty tz qx qy qz qw', "
                f"got {len(fields)}"
            )
        try:
            values = [float(f) for f in fields]
        except ValueError:
            raise InputError(f"{source}:{lineno}: not a number in {clipped(line, 80)}") from None
        if not all(math.isfinite(v) for v in values):
            raise InputError(f"{source}:{lineno}: non-finite value in {clipped(line, 80)}")
        if is_zero_quaternion(values[4:8]):
            raise InputError(f"{source}:{lineno}: zero-length quaternion")
        stamps.append(values[0])
        rows.append(values[1:])
    if not rows:
        return Trajectory(np.zeros(0), np.zeros((0, 4, 4)))
    return Trajectory(np.asarray(stamps, dtype=np.float64), pose_from_tum(np.asarray(rows)))


def nearest_times(
    query: np.ndarray, reference: np.ndarray, tolerance: float, *, strict: bool = False
) -> np.ndarray:
    """For each query time, the index into `reference` (in any order) of the nearest time, the
    earlier one on a tie; -1 where that is farther than `tolerance` (or exactly that far, if
    `strict`, as TUM's association tool has it). Seconds or integer nanoseconds alike.

    Returns:
        [M] int64 indices into `reference`.
    """
    query, reference = np.asarray(query), np.asarray(reference)
    if len(reference) == 0:
        return np.full(len(query), -1, dtype=np.int64)
    order = np.argsort(reference, kind="stable")
    ref = reference[order]
    right = np.clip(np.searchsorted(ref, query), 0, len(ref) - 1)
    left = np.clip(right - 1, 0, len(ref) - 1)
    k = np.where(np.abs(ref[left] - query) <= np.abs(ref[right] - query), left, right)
    gap = np.abs(ref[k] - query)
    return np.where(gap < tolerance if strict else gap <= tolerance, order[k], -1).astype(np.int64)


def read_tum_trajectory(path: str | Path) -> Trajectory:
    """Read a TUM trajectory file (see `parse_tum_trajectory`).

    Raises:
        InputError: the file is missing, unreadable, or has a malformed row.
    """
    path = Path(path)
    return parse_tum_trajectory(read_text(path, "trajectory"), source=str(path))


def read_transform(path: str | Path) -> np.ndarray:
    """A [4, 4] rigid transform from a text file: 16 numbers (row-major 4x4) or 7 numbers in
    TUM order `tx ty tz qx qy qz qw`; `#` starts a comment.

    Raises:
        InputError: missing file, another count of numbers, or non-finite values.
    """
    path = Path(path)
    words = [
        w for line in read_text(path, "transform").splitlines() for w in line.split("#")[0].split()
    ]
    try:
        values = np.array([float(w) for w in words])
    except ValueError:
        raise InputError(f"{path}: a transform file holds numbers only") from None
    if not np.all(np.isfinite(values)) or len(values) not in (7, 16):
        raise InputError(
            f"{path}: expected 16 numbers (a 4x4 matrix) or 7 (tx ty tz qx qy qz qw), "
            f"got {len(values)}{' with non-finite values' if len(values) in (7, 16) else ''}"
        )
    if len(values) == 7:
        if is_zero_quaternion(values[3:]):
            raise InputError(f"{path}: the quaternion qx qy qz qw is zero, not a rotation")
        return pose_from_tum(values)
    T = values.reshape(4, 4)
    if not np.allclose(T[3], [0, 0, 0, 1]):
        raise InputError(f"{path}: the last row of a rigid transform is 0 0 0 1")
    R = T[:3, :3]
    if not (np.allclose(R.T @ R, np.eye(3), atol=1e-3) and np.linalg.det(R) > 0):
        raise InputError(
            f"{path}: the upper-left 3x3 block is not a rotation (orthonormal, determinant +1); "
            "a rigid transform neither scales nor mirrors"
        )
    u, _, vt = np.linalg.svd(R)  # the nearest rotation: a matrix written to a few decimals is
    T[:3, :3] = u @ vt  # not orthonormal to float precision, as a TUM quaternion is normalised
    return T


def format_transform(T: np.ndarray, comments: Iterable[str] = ()) -> str:
    """`read_transform`'s text of the rigid [4, 4] `T`: the comment lines (each `# `), then the
    matrix as four rows of shortest round-trip numbers (read back bit for bit)."""
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise InputError("a transform to write must be a finite 4x4 matrix")
    lines = [f"# {c}" for c in comments]
    lines += [" ".join(repr(float(v)) for v in row) for row in T.tolist()]
    return "\n".join(lines) + "\n"


def format_tum_trajectory(
    timestamps: np.ndarray, T_world_cam: np.ndarray, comments: Iterable[str] = ()
) -> str:
    """TUM text for `timestamps` [N] (s) and camera-to-world poses `T_world_cam` [N, 4, 4].

    Numbers are written with Python's shortest round-trip representation, so reading the text
    back gives the same timestamps and translations bit for bit (rotations up to the
    matrix -> quaternion conversion, about 1e-15).
    """
    traj = Trajectory(np.asarray(timestamps, np.float64), np.asarray(T_world_cam, np.float64))
    lines = [f"# {c}" for c in comments]
    lines.append("# timestamp tx ty tz qx qy qz qw")
    if len(traj):
        tum = pose_to_tum(traj.T_world_cam)
        if not (np.all(np.isfinite(tum)) and np.all(np.isfinite(traj.timestamps))):
            raise InputError("trajectory has non-finite timestamps or poses")
        for t, row in zip(traj.timestamps.tolist(), tum.tolist(), strict=True):
            lines.append(" ".join(repr(float(v)) for v in (t, *row)))
    return "\n".join(lines) + "\n"


def write_tum_trajectory(
    path: str | Path,
    timestamps: np.ndarray,
    T_world_cam: np.ndarray,
    comments: Iterable[str] = (),
) -> None:
    """Write a TUM trajectory file that evo and `read_tum_trajectory` read.

    Args:
        path: output file (overwritten; not a link or a device, which the rename into place
            would replace).
        timestamps: [N] seconds.
        T_world_cam: [N, 4, 4] camera-to-world poses.
        comments: lines written first, each prefixed by `# `.
    """
    text = format_tum_trajectory(timestamps, T_world_cam, comments)
    check_output(path, force=True)  # (the rename into place would replace a link or a device)
    try:
        write_text_atomic(path, text)
    except OSError as exc:
        raise OutputError(f"cannot write trajectory file {path}: {exc}") from None
