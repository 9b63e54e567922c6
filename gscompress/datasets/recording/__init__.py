"""Robot recordings as RGB-D sequences: ROS 2 bags (MCAP or sqlite), ROS 1 bags, Foxglove MCAP.

`open_recording(path, ...)` returns a `RecordingSequence`, an `RGBDSequence` like a dataset
folder's: frames are decoded when the run reaches them (`frame(i)` reads two messages), so memory
does not grow with the recording's length; opening reads each chosen topic's messages once for
their stamps (a few dozen bytes kept per message).

Containers. A ROS 2 bag (a folder with `metadata.yaml`, or one `.mcap` / `.db3` file) and a
ROS 1 `.bag` are read with `rosbags` (pure Python, Apache-2.0), imported when a recording is
opened. An MCAP file whose header profile is not `ros2` is read as a Foxglove recording (schemas
`foxglove.RawImage`, `foxglove.CompressedImage`, `foxglove.CameraCalibration`,
`foxglove.FrameTransform(s)` in protobuf) through the project's bounded MCAP reader. Every MCAP
file is first checked as a log is (a summary, every chunk's declared size within
`MAX_CHUNK_RATIO` times its compressed size and `MAX_CHUNK_BYTES`), and a ROS 1 bag's chunks are
inflated within the same bounds; ROS 2 bags compressed per file or per message are refused.

Messages. Colour: `sensor_msgs/Image` rgb8, bgr8, rgba8, bgra8, mono8 (alpha dropped, grey
repeated), `CompressedImage` JPEG or PNG, and the Foxglove equivalents. Depth: 16UC1
(millimetres; 0 and 65535 read as no depth), 32FC1 (metres; 0, negative and non-finite read as no
depth), `compressedDepth` PNG (image_transport's 12-byte header, then a 16-bit PNG of
millimetres, or of quantised inverse depth for 32FC1) and a 16-bit PNG `foxglove.
CompressedImage` (millimetres). Intrinsics come from the colour camera's `CameraInfo` /
`CameraCalibration` (its `K`); images are used as recorded, so a distortion model with any
non-zero coefficient is refused (plumb_bob, rational_polynomial, equidistant or none with all
coefficients zero are fine): record rectified images (`image_rect_color`).

Topics. Taken from the options when given, else chosen when unambiguous: a known pair of a
RealSense, Azure Kinect, OpenNI, TUM RGB-D or Foxglove-style recording, else the only colour
and the only depth topic (a topic whose name says `depth` holds depth). image_transport's
`/compressed` and `/compressedDepth` topics stand for their base topic when it was not recorded.
Depth must be registered to colour: a topic named as aligned (`aligned_depth_to_color`,
`depth_to_rgb`, `depth_registered`, TUM's `/camera/depth/image`) or of the same frame id and size.

Pairing. Colour and depth are paired by their header stamps (the log time where a stamp is 0)
within `max_dt` by `gscompress.datasets.stamps.associate`, the TUM reader's rule; a frame without
a partner is skipped and counted. Ground truth: a TUM file (`gt`), or `/tf` and `/tf_static`
(`gt_frames` = (world, camera)), the chain between the two frames composed, each moving link
interpolated at the colour stamp (quaternion slerp, translation linear) between its two nearest
samples; a frame outside the samples of a link has no pose.

The package's modules: `options` (RecordingOptions), `messages` (what every container gives),
`containers` (rosbags and Foxglove MCAP) with `bounds` (what rosbags may inflate), `decode`
(images and camera infos), `topics` (the choice), `tf` (ground truth from /tf) and `sequence`
(the `RGBDSequence`, and what `gsc info` shows).
"""

from gscompress.datasets.recording.bounds import check_chunk_size
from gscompress.datasets.recording.containers import Container, Locator, open_container
from gscompress.datasets.recording.decode import (
    COLOR_ENCODINGS,
    DEPTH_ENCODINGS,
    MM_PER_METRE,
    UNDISTORTED_MODELS,
    decode_color,
    decode_depth,
    intrinsics_of,
    metres_depth,
)
from gscompress.datasets.recording.messages import (
    CAMERA_INFO,
    COMPRESSED,
    IMAGE,
    TF,
    CameraMessage,
    ImageMessage,
    TopicInfo,
    TransformMessage,
    ns_to_seconds,
    seconds_to_stamp_ns,
)
from gscompress.datasets.recording.options import (
    DEFAULT_MAX_DT,
    MAX_DT_GT,
    RECORDING_SUFFIXES,
    RecordingOptions,
    is_recording,
)
from gscompress.datasets.recording.sequence import (
    RecordingSequence,
    describe_recording,
    open_recording,
    with_topics,
)
from gscompress.datasets.recording.tf import tf_poses
from gscompress.datasets.recording.topics import (
    KNOWN_PAIRS,
    REGISTERED_MARKS,
    TopicChoice,
    choose_topics,
    image_topics,
    registered,
)

__all__ = [
    "CAMERA_INFO",
    "COLOR_ENCODINGS",
    "COMPRESSED",
    "DEFAULT_MAX_DT",
    "DEPTH_ENCODINGS",
    "IMAGE",
    "KNOWN_PAIRS",
    "MAX_DT_GT",
    "MM_PER_METRE",
    "RECORDING_SUFFIXES",
    "REGISTERED_MARKS",
    "TF",
    "UNDISTORTED_MODELS",
    "CameraMessage",
    "Container",
    "ImageMessage",
    "Locator",
    "RecordingOptions",
    "RecordingSequence",
    "TopicChoice",
    "TopicInfo",
    "TransformMessage",
    "check_chunk_size",
    "choose_topics",
    "decode_color",
    "decode_depth",
    "describe_recording",
    "image_topics",
    "intrinsics_of",
    "is_recording",
    "metres_depth",
    "ns_to_seconds",
    "open_container",
    "open_recording",
    "registered",
    "seconds_to_stamp_ns",
    "tf_poses",
    "with_topics",
]
