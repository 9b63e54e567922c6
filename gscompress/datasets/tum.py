"""TUM RGB-D layout: read (with timestamp association) and write.

A TUM folder holds `rgb.txt` and `depth.txt` (`timestamp path` per line), the images they name,
and optionally `groundtruth.txt` (`timestamp tx ty tz qx qy qz qw`, camera-to-world).

Association follows TUM's `associate.py`: every colour/depth pair whose timestamps differ by less
than `max_dt` (default 0.02 s, associate.py's default) is a candidate; candidates are taken
greedily by increasing time difference, each image used at most once, and the pairs are ordered
by colour timestamp, which becomes the frame timestamp (`gscompress.datasets.stamps.associate`,
which recordings use too). Ground truth (often 100 Hz, or sparser
than the images) is associated separately: each frame takes the pose whose timestamp is nearest
to its colour timestamp, if that is within `max_dt_gt` (default 0.02 s); other frames have no
pose. When `rgb.txt`/`depth.txt` are absent but an `associations.txt`
(`t_rgb rgb_path t_depth depth_path`) is present, its pairs are used as they are.

Depth PNGs are uint16 with `depth_scale` units per metre: 5000 (TUM) unless `intrinsics.json`
says otherwise. Raw 0 and 65535 (the saturation value some sensors write for no measurement)
read as no depth; `intrinsics.json` may list other such values (`invalid_depth`) and a
`max_depth` in metres beyond which depth is dropped. Intrinsics come from, in order: the
`intrinsics` argument, `intrinsics.json` in the folder, the published freiburg1/2/3 values when
the folder name says `freiburg1`/`fr1` (etc.). The freiburg images are used undistorted-as-is,
as SplaTAM and most 3DGS SLAM do.
"""

from __future__ import annotations

import json
import re
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
from PIL import Image

from gscompress.camera import Intrinsics
from gscompress.datasets.base import (
    DepthCoding,
    FileSequence,
    FrameRecord,
    FrameSelection,
    RGBDSequence,
    read_intrinsics_file,
)
from gscompress.datasets.stamps import associate
from gscompress.errors import DatasetError, InputError, OutputError
from gscompress.io.files import read_text, write_atomic, write_text_atomic
from gscompress.io.trajectory import format_tum_trajectory, nearest_times, read_tum_trajectory

TUM_DEPTH_SCALE = 5000.0
DEFAULT_MAX_DT = 0.02
DEFAULT_MAX_DT_GT = 0.02

# Published calibration of the TUM RGB-D cameras (ROS default set, 640x480).
FREIBURG_INTRINSICS: dict[int, Intrinsics] = {
    1: Intrinsics(517.3, 516.5, 318.6, 255.3, 640, 480),
    2: Intrinsics(520.9, 521.0, 325.1, 249.7, 640, 480),
    3: Intrinsics(535.4, 539.2, 320.1, 247.6, 640, 480),
}
_FREIBURG_RE = re.compile(r"(?:^|[^a-z0-9])(?:freiburg|fr)([123])(?![0-9])")


def is_tum_folder(path: Path) -> bool:
    """True when `path` looks like a TUM RGB-D folder."""
    return (path / "rgb.txt").is_file() or (path / "associations.txt").is_file()


def freiburg_intrinsics(name: str) -> Intrinsics | None:
    """The published intrinsics for a folder named like `rgbd_dataset_freiburg1_desk`."""
    m = _FREIBURG_RE.search(name.lower())
    return FREIBURG_INTRINSICS[int(m.group(1))] if m else None


def read_file_list(path: Path) -> list[tuple[float, str]]:
    """`timestamp path` rows of rgb.txt / depth.txt; comments and blank lines skipped."""
    text = read_text(path, "file list", DatasetError)
    rows: list[tuple[float, str]] = []
    for lineno, raw in enumerate(text.splitlines(), start=1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        fields = line.replace(",", " ").split()
        if len(fields) < 2:
            raise DatasetError(f"{path}:{lineno}: expected 'timestamp filename'")
        try:
            stamp = float(fields[0])
        except ValueError:
            raise DatasetError(f"{path}:{lineno}: bad timestamp {fields[0]!r}") from None
        if not np.isfinite(stamp):
            raise DatasetError(f"{path}:{lineno}: bad timestamp {fields[0]!r}")
        rows.append((stamp, fields[1]))
    return rows


def _resolve(root: Path, rel: str, listed_in: Path) -> Path:
    """Path of a listed image; rejects absolute paths and paths escaping the folder."""
    p = Path(rel)
    if p.is_absolute() or ".." in p.parts:
        raise DatasetError(f"{listed_in}: image path {rel!r} must be relative to {root}")
    return root / p


def _tum_records(root: Path, max_dt: float, max_dt_gt: float) -> tuple[list[FrameRecord], bool]:
    """Associated frame records of a TUM folder, and whether groundtruth.txt was present."""
    rgb_txt, depth_txt = root / "rgb.txt", root / "depth.txt"
    if rgb_txt.is_file():
        if not depth_txt.is_file():
            raise DatasetError(f"TUM folder {root} has rgb.txt but no depth.txt")
        rgb = read_file_list(rgb_txt)
        depth = read_file_list(depth_txt)
        pairs = associate(
            np.array([t for t, _ in rgb], dtype=np.float64),
            np.array([t for t, _ in depth], dtype=np.float64),
            max_dt,
        )
        frames = [
            (rgb[i][0], _resolve(root, rgb[i][1], rgb_txt), _resolve(root, depth[j][1], depth_txt))
            for i, j in pairs
        ]
    else:
        frames = _read_associations(root / "associations.txt", root)
    if not frames:
        raise DatasetError(f"TUM folder {root}: no colour/depth pairs within {max_dt} s")
    for _, color_path, depth_path in frames:
        for p, what in ((color_path, "colour"), (depth_path, "depth")):
            if not p.is_file():
                raise DatasetError(f"{what} image listed in {root} not found: {p}")

    gt_file = root / "groundtruth.txt"
    poses: list[np.ndarray | None] = [None] * len(frames)
    if gt_file.is_file():
        try:
            gt = read_tum_trajectory(gt_file)
        except InputError as exc:
            raise DatasetError(str(exc)) from None
        k = nearest_times(np.array([f[0] for f in frames]), gt.timestamps, max_dt_gt, strict=True)
        poses = [gt.T_world_cam[j] if j >= 0 else None for j in k]
    records = [FrameRecord(t, c, d, pose) for (t, c, d), pose in zip(frames, poses, strict=True)]
    return records, gt_file.is_file()


def _read_associations(path: Path, root: Path) -> list[tuple[float, Path, Path]]:
    """Rows `t_rgb rgb_path t_depth depth_path` of associations.txt."""
    if not path.is_file():
        raise DatasetError(f"TUM folder {root} has neither rgb.txt nor associations.txt")
    rows: list[tuple[float, Path, Path]] = []
    lines = read_text(path, "associations", DatasetError).splitlines()
    for lineno, raw in enumerate(lines, start=1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        f = line.split()
        try:
            if len(f) != 4:
                raise ValueError
            stamp = float(f[0])
            float(f[2])
        except ValueError:
            raise DatasetError(
                f"{path}:{lineno}: expected 't_rgb rgb_path t_depth depth_path'"
            ) from None
        rows.append((stamp, _resolve(root, f[1], path), _resolve(root, f[3], path)))
    return sorted(rows, key=lambda r: r[0])


def open_tum(
    path: Path,
    selection: FrameSelection,
    size: tuple[int, int] | None = None,
    intrinsics: Intrinsics | Path | None = None,
    max_dt: float = DEFAULT_MAX_DT,
    max_dt_gt: float = DEFAULT_MAX_DT_GT,
) -> FileSequence:
    """Open a TUM RGB-D folder (see the module docstring for the rules).

    Args:
        path: the folder holding rgb.txt.
        selection: frame subset.
        size: working size (W, H), or None for the file size.
        intrinsics: explicit intrinsics, or a JSON file with them; overrides the folder's.
        max_dt: colour/depth association tolerance (s).
        max_dt_gt: frame/ground-truth association tolerance (s).
    """
    records, _ = _tum_records(path, max_dt, max_dt_gt)
    depth = DepthCoding()
    if isinstance(intrinsics, Intrinsics):
        native = intrinsics
    elif intrinsics is not None:
        native, depth = read_intrinsics_file(Path(intrinsics))
    elif (path / "intrinsics.json").is_file():
        native, depth = read_intrinsics_file(path / "intrinsics.json")
    else:
        found = freiburg_intrinsics(path.resolve().name)
        if found is None:
            raise DatasetError(
                f"no intrinsics for {path}: add an intrinsics.json (a JSON object of fx, fy, cx, "
                f"cy, width, height, optionally depth_scale) or name the folder after freiburg1/2/3"
            )
        native = found
    if depth.scale is None and (path / "intrinsics.json").is_file() and intrinsics is not None:
        depth = read_intrinsics_file(path / "intrinsics.json")[1]
    return FileSequence(
        path.resolve().name,
        records,
        native,
        depth.with_default_scale(TUM_DEPTH_SCALE),
        selection,
        size,
    )


TUM_ENTRIES = frozenset(
    {"rgb", "depth", "rgb.txt", "depth.txt", "groundtruth.txt", "intrinsics.json"}
)
"""Everything `write_tum_sequence` puts in its folder (what `gsc synth --force` may replace)."""


def write_tum_sequence(
    sequence: RGBDSequence,
    out_dir: Path,
    depth_scale: float = TUM_DEPTH_SCALE,
    extra: dict[str, object] | None = None,
    progress: Callable[[int], None] | None = None,
    workers: int = 1,
) -> None:
    """Write `sequence` into the empty or new folder `out_dir` in TUM layout.

    Writes rgb/NNNNNN.png (8-bit), depth/NNNNNN.png (uint16, `depth_scale` units per metre, 0 =
    invalid, at most 65534), rgb.txt, depth.txt, groundtruth.txt (when the sequence has poses) and
    intrinsics.json (fx fy cx cy width height depth_scale, plus `extra`). Timestamps are written
    with 6 decimals, as TUM does. The output is byte-identical for identical input.

    Args:
        progress: called with 1 after each frame is written.
        workers: frames read/rendered and encoded concurrently (threads).

    Raises:
        OutputError: depth beyond the uint16 range at this scale, or an unwritable folder.
    """
    max_depth = 65534.0 / depth_scale  # (65535, saturation, reads as no depth)
    (out_dir / "rgb").mkdir(parents=True, exist_ok=True)
    (out_dir / "depth").mkdir(exist_ok=True)

    def write_frame(i: int) -> tuple[str, str, np.ndarray | None]:
        f = sequence.frame(i)
        name = f"{f.index:06d}.png"
        rgb8 = np.clip(np.rint(f.color * 255.0), 0, 255).astype(np.uint8)
        if float(np.max(f.depth, initial=0.0)) > max_depth:
            raise OutputError(f"depth beyond {max_depth:.2f} m cannot be stored at this scale")
        d16 = np.rint(np.where(f.depth > 0, f.depth, 0.0) * depth_scale).astype(np.uint16)
        colour, depth = Image.fromarray(rgb8, mode="RGB"), Image.fromarray(d16)
        write_atomic(out_dir / "rgb" / name, lambda file: colour.save(file, format="PNG"))
        write_atomic(out_dir / "depth" / name, lambda file: depth.save(file, format="PNG"))
        return f"{f.timestamp:.6f}", name, f.T_world_cam

    rgb_lines = ["# color images", "# timestamp filename"]
    depth_lines = ["# depth maps", "# timestamp filename"]
    gt_stamps: list[float] = []
    gt_poses: list[np.ndarray] = []
    # Frames are independent; numpy and PIL release the GIL, so threads overlap them.
    with ThreadPoolExecutor(max_workers=max(1, workers)) as pool:
        for stamp, name, pose in pool.map(write_frame, range(len(sequence))):
            rgb_lines.append(f"{stamp} rgb/{name}")
            depth_lines.append(f"{stamp} depth/{name}")
            if pose is not None:
                gt_stamps.append(float(stamp))
                gt_poses.append(pose)
            if progress is not None:
                progress(1)
    write_text_atomic(out_dir / "rgb.txt", "\n".join(rgb_lines) + "\n")
    write_text_atomic(out_dir / "depth.txt", "\n".join(depth_lines) + "\n")
    if gt_poses:
        text = format_tum_trajectory(
            np.array(gt_stamps), np.array(gt_poses), ["ground truth trajectory (camera-to-world)"]
        )
        write_text_atomic(out_dir / "groundtruth.txt", text)
    k = sequence.intrinsics
    meta: dict[str, object] = {
        "fx": k.fx,
        "fy": k.fy,
        "cx": k.cx,
        "cy": k.cy,
        "width": k.width,
        "height": k.height,
        "depth_scale": depth_scale,
    }
    meta.update(extra or {})
    write_text_atomic(out_dir / "intrinsics.json", json.dumps(meta, indent=2) + "\n")
