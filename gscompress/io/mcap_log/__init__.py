"""The gscompress MCAP log profile: writer and reader.

One profile serves SLAM logs, pruned logs and shares:

- `/gaussians`: foxglove.PointCloud, one message per map snapshot; the last one is "the map".
  Packed little-endian fields named as in 3DGS PLY (see `gscompress.io.columns`), plus the PWAS
  score `importance`, its sums and the uint32 `id`; float32, or at precision fp16 (profile 1.1)
  the bounded attributes as uint16 `<name>_f16` fields holding float16 bit patterns.
- `/camera/pose`, `/camera/pose_gt`: foxglove.PoseInFrame (camera-to-world, frame "world"):
  the pose each frame was tracked at, and its ground truth.
- `/camera/pose_refined`: foxglove.PosesInFrame, the trajectory as the mapping refined it (the
  first N frames' poses; the last message is the trajectory), in logs of runs that refine poses.
- `/tf`: foxglove.FrameTransform world -> camera for the estimated pose.
- `/camera/calibration`: foxglove.CameraCalibration.
- `/slam/stats`: JSON per frame, schema `schemas/slam_stats.v1.schema.json`.
- Metadata record `gscompress`: profile version, tool version, command line, config, sequence,
  frame subset, provenance chain and operation results (`LogMetadata`).

Files are chunked and zstd-compressed (a log without chunks shows no messages in the TypeScript
reader), always carry the metadata record, and are written to a temporary file that is renamed
into place only when complete. Readers treat every file as untrusted.

The profile is cut along its seams: `metadata` (names and the metadata record), `messages`
(maps and poses as messages, and back), `writer` and `reader`; everything is importable from
here as before.
"""

from gscompress.io.mcap_log.messages import (
    Snapshot,
    decode_map_message,
    decode_pose,
    decode_snapshot,
    decode_trajectory,
    decoded_map,
    encode_map,
    encoded_size,
    gaussians_to_pointcloud,
    pointcloud_bytes,
    pose_message,
    record_size,
    trajectory_message,
)
from gscompress.io.mcap_log.metadata import (
    CAMERA_FRAME,
    METADATA_NAME,
    POSES_ESTIMATED,
    POSES_GROUND_TRUTH,
    STATS_SCHEMA,
    TOPIC_CALIBRATION,
    TOPIC_GAUSSIANS,
    TOPIC_POSE,
    TOPIC_POSE_GT,
    TOPIC_POSE_REFINED,
    TOPIC_STATS,
    TOPIC_TF,
    WORLD_FRAME,
    LogMetadata,
    seconds_to_ns,
)
from gscompress.io.mcap_log.reader import (
    MAGIC,
    ChannelInfo,
    LogReader,
    Trajectory,
    closed_properly,
    is_read_error,
    read_map,
)
from gscompress.io.mcap_log.writer import LogWriter
from gscompress.io.pointcloud import pointcloud_to_gaussians

__all__ = [
    "CAMERA_FRAME",
    "MAGIC",
    "METADATA_NAME",
    "POSES_ESTIMATED",
    "POSES_GROUND_TRUTH",
    "STATS_SCHEMA",
    "TOPIC_CALIBRATION",
    "TOPIC_GAUSSIANS",
    "TOPIC_POSE",
    "TOPIC_POSE_GT",
    "TOPIC_POSE_REFINED",
    "TOPIC_STATS",
    "TOPIC_TF",
    "WORLD_FRAME",
    "ChannelInfo",
    "LogMetadata",
    "LogReader",
    "LogWriter",
    "Snapshot",
    "Trajectory",
    "closed_properly",
    "decode_map_message",
    "decode_pose",
    "decode_snapshot",
    "decode_trajectory",
    "decoded_map",
    "encode_map",
    "encoded_size",
    "gaussians_to_pointcloud",
    "is_read_error",
    "pointcloud_bytes",
    "pointcloud_to_gaussians",
    "pose_message",
    "read_map",
    "record_size",
    "seconds_to_ns",
    "trajectory_message",
]
