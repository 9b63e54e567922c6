"""Which topics a recording is read from: given, else chosen by known driver names or as the
only colour and depth topics, with the camera info beside the colour topic; and whether depth
is registered to colour."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from gscompress.datasets.recording.messages import (
    CAMERA_INFO,
    COMPRESSED,
    IMAGE,
    ImageMessage,
    TopicInfo,
)
from gscompress.datasets.recording.options import RecordingOptions
from gscompress.errors import DatasetError, clipped

KNOWN_PAIRS: tuple[tuple[str, str, str], ...] = (
    # (source, colour, depth registered to it)
    ("RealSense", "/camera/color/image_raw", "/camera/aligned_depth_to_color/image_raw"),
    (
        "RealSense",
        "/camera/camera/color/image_raw",
        "/camera/camera/aligned_depth_to_color/image_raw",
    ),
    ("Azure Kinect", "/rgb/image_raw", "/depth_to_rgb/image_raw"),
    ("OpenNI", "/camera/rgb/image_color", "/camera/depth_registered/image_raw"),
    ("OpenNI", "/camera/rgb/image_rect_color", "/camera/depth_registered/image_raw"),
    ("TUM RGB-D", "/camera/rgb/image_color", "/camera/depth/image"),
    ("Foxglove", "/camera/color", "/camera/depth"),
    ("Foxglove", "/camera/image", "/camera/depth"),
)
"""Topic pairs chosen by name when both are in a recording (the first that is, in this order)."""
REGISTERED_MARKS = ("aligned_depth_to_color", "depth_to_rgb", "depth_registered")
"""A depth topic whose name holds one of these is registered to colour by its driver."""
_TRANSPORTS = ("/compressed", "/compressedDepth")


@dataclass(frozen=True)
class TopicChoice:
    """The topics a sequence is read from, and why (`reason`)."""

    rgb: str
    depth: str
    camera_info: str
    reason: str


def _base(topic: str) -> str:
    """A topic without image_transport's suffix."""
    for suffix in _TRANSPORTS:
        if topic.endswith(suffix):
            return topic[: -len(suffix)]
    return topic


def _is_depth_name(topic: str) -> bool:
    return "depth" in topic.lower()


def image_topics(topics: Sequence[TopicInfo]) -> dict[str, str]:
    """{base topic: the topic read for it} of the image topics, raw preferred to compressed."""
    chosen: dict[str, str] = {}
    for t in sorted(topics, key=lambda t: (t.kind != IMAGE, t.name)):
        if t.kind in (IMAGE, COMPRESSED) and t.count > 0:
            chosen.setdefault(_base(t.name), t.name)
    return chosen


def choose_topics(
    topics: Sequence[TopicInfo], options: RecordingOptions, source: str
) -> TopicChoice:
    """The colour, depth and camera-info topics (see `gscompress.datasets.recording`).

    Raises:
        DatasetError: a named topic is missing, or the choice is ambiguous (the message names
            the candidates and the options that settle it).
    """
    by_name = {t.name: t for t in topics}
    for name, topic in (
        ("rgb", options.rgb),
        ("depth", options.depth),
        ("camera_info", options.camera_info),
    ):
        if topic is not None and topic not in by_name:
            raise DatasetError(
                f"{source} has no topic {clipped(topic)} (`{name}`)", options=(name,)
            )
    images = image_topics(topics)
    colours = sorted(v for k, v in images.items() if not _is_depth_name(k))
    depths = sorted(v for k, v in images.items() if _is_depth_name(k))
    rgb, depth, reason = options.rgb, options.depth, "given"
    if rgb is None or depth is None:
        known = [
            (name, c, d)
            for name, c, d in KNOWN_PAIRS
            if c in images
            and d in images
            and rgb in (None, images[c])
            and depth in (None, images[d])
        ]
        if known:
            name, c, d = known[0]
            rgb, depth, reason = images[c], images[d], f"{name} topic names"
        else:
            rgb = rgb or _only(colours, "colour", "rgb", source)
            depth = depth or _only(depths, "depth", "depth", source)
            reason = "the only colour and depth topics"
    infos = sorted(t.name for t in topics if t.kind == CAMERA_INFO and t.count > 0)
    info = options.camera_info
    if info is None:
        namespace = _base(rgb).rsplit("/", 1)[0]
        siblings = [t for t in infos if t.rsplit("/", 1)[0] == namespace]
        if len(siblings) == 1:
            info = siblings[0]
        elif len(infos) == 1:
            info = infos[0]
        elif not infos:
            raise DatasetError(
                f"{source} has no camera info (CameraInfo / CameraCalibration) for {rgb}: the "
                "intrinsics are unknown"
            )
        else:
            info = _only([], "camera info", "camera_info", source, infos)
    for topic, kind in ((rgb, "colour"), (depth, "depth")):
        if by_name[topic].kind not in (IMAGE, COMPRESSED):
            raise DatasetError(f"{source}: {topic} is {by_name[topic].msgtype}, not a {kind} image")
    if by_name[info].kind != CAMERA_INFO:
        raise DatasetError(f"{source}: {info} is {by_name[info].msgtype}, not a camera info")
    return TopicChoice(rgb, depth, info, reason)


def _only(
    candidates: Sequence[str], what: str, option: str, source: str, listed: Sequence[str] = ()
) -> str:
    """The one candidate; else a DatasetError naming them (or saying there are none) and the
    option that chooses one."""
    if len(candidates) == 1:
        return candidates[0]
    shown = list(listed or candidates)
    if not shown:
        raise DatasetError(f"{source} has no {what} image topic")
    raise DatasetError(
        f"{source}: which {what} topic? candidates: {', '.join(shown)}; pass `{option}` TOPIC",
        options=(option,),
    )


def registered(
    depth_topic: str, depth: ImageMessage, color: ImageMessage, size: tuple[int, int] | None
) -> bool:
    """Whether depth is registered to colour: by its topic's name, or by the same frame id
    and size (`size` the depth image's, None when compressed and not yet known)."""
    if any(mark in depth_topic for mark in REGISTERED_MARKS) or _base(depth_topic) in (
        d for _, _, d in KNOWN_PAIRS
    ):
        return True
    same_size = size is None or color.compressed or size == (color.width, color.height)
    return bool(depth.frame_id) and depth.frame_id == color.frame_id and same_size
