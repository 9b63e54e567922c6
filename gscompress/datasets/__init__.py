"""RGB-D sequences: one interface over TUM, Replica (NICE-SLAM layout), synthetic scenes and
robot recordings (ROS 1 / ROS 2 bags, Foxglove MCAP).

`open_sequence(path)` recognises the folder layout or recording and returns an `RGBDSequence`;
frames come
out as colour [H, W, 3] float32 in [0, 1], depth [H, W] float32 metres (0 = invalid), a
timestamp and, when the dataset has one, the ground-truth camera-to-world pose.
"""

from __future__ import annotations

from pathlib import Path

from gscompress.camera import Intrinsics
from gscompress.datasets.base import (
    DepthCoding,
    FileSequence,
    Frame,
    FrameSelection,
    RGBDSequence,
    check_size,
    iter_frames,
    parse_frames,
    read_intrinsics_file,
)
from gscompress.datasets.recording import RecordingOptions, is_recording, open_recording
from gscompress.datasets.replica import find_replica_scene, open_replica
from gscompress.datasets.tum import is_tum_folder, open_tum, write_tum_sequence
from gscompress.errors import DatasetError

__all__ = [
    "DepthCoding",
    "FileSequence",
    "Frame",
    "FrameSelection",
    "RGBDSequence",
    "RecordingOptions",
    "iter_frames",
    "open_sequence",
    "parse_frames",
    "read_intrinsics_file",
    "write_tum_sequence",
]


def open_sequence(
    path: str | Path,
    size: tuple[int, int] | None = None,
    frames: str | FrameSelection = "all",
    intrinsics: Intrinsics | str | Path | None = None,
    recording: RecordingOptions | None = None,
) -> RGBDSequence:
    """Open an RGB-D sequence folder or recording, recognising its layout.

    Layouts: TUM RGB-D (`rgb.txt`, `depth.txt`, optional `groundtruth.txt`, or
    `associations.txt`) and Replica as preprocessed by NICE-SLAM (`results/`, `traj.txt`, either
    the scene folder or a folder holding exactly one scene). Recordings: a ROS 2 bag (a folder
    with `metadata.yaml`, or one `.mcap` / `.db3` file), a ROS 1 `.bag`, a Foxglove-schema
    `.mcap`. See `gscompress.datasets.tum`, `gscompress.datasets.replica` and
    `gscompress.datasets.recording` for association, depth-scale and intrinsics rules.

    Args:
        path: the sequence folder or recording.
        size: working size (W, H); colour is area-averaged (bilinear when enlarging), depth
            nearest-neighbour, intrinsics scaled. None keeps the file size.
        frames: `all`, `odd`, `even` or `START:STOP:STEP` on the 0-based index of the
            associated frames (odd-indexed frames go to agent A, even-indexed to agent B).
        intrinsics: explicit intrinsics, or a JSON file (`fx fy cx cy width height
            [depth_scale]`, or NICE-SLAM cam_params.json); overrides what the folder provides.
        recording: a recording's topics, pairing tolerance and ground truth (None: chosen;
            see `RecordingOptions`); a folder takes none.

    Raises:
        DatasetError: not a known layout, missing or unreadable files, no intrinsics.
        InputError: a bad `size` or `frames` value.
    """
    root = Path(path)
    selection = parse_frames(frames)
    size = check_size(size)
    if is_recording(root):
        if root.exists():
            if isinstance(intrinsics, Intrinsics) or intrinsics is None:
                known = intrinsics
            else:
                known = read_intrinsics_file(Path(intrinsics))[0]
            return open_recording(root, selection, size, known, recording)
    elif recording is not None and not recording.is_default:
        raise DatasetError(
            f"{root} is a sequence folder: topics and `gt` are for recordings", options=("gt",)
        )
    if not root.is_dir():
        raise DatasetError(f"sequence folder or recording not found: {root}")
    explicit = intrinsics if isinstance(intrinsics, Intrinsics | None) else Path(intrinsics)
    if is_tum_folder(root):
        return open_tum(root, selection, size, explicit)
    if find_replica_scene(root) is not None:
        return open_replica(root, selection, size, explicit)
    raise DatasetError(
        f"{root} is not a known RGB-D layout: expected TUM (rgb.txt, depth.txt), "
        f"Replica/NICE-SLAM (results/, traj.txt) or a recording (a ROS 2 bag folder, .bag, "
        f".mcap, .db3)"
    )
