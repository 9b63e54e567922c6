"""The PointCloud map codecs: a map as a foxglove.PointCloud of packed little-endian records,
one per Gaussian (`gscompress.io.columns`), which Foxglove draws as it is; float32 throughout, or
with the bounded attributes as float16 (`half`). `gscompress.io.codec` names them in its table.

Decoding treats every message as untrusted: the layout, sizes and values are checked before a
map is built.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable
from typing import Any

import numpy as np
from foxglove_schemas_protobuf.PackedElementField_pb2 import PackedElementField
from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud

from gscompress.errors import MapError
from gscompress.gaussians import SH_REST_COUNTS, GaussianMap
from gscompress.io.columns import (
    column_dtypes,
    decode_columns,
    encode_columns,
    has_half_columns,
    map_from_columns,
    map_to_columns,
    pack_records,
)
from gscompress.io.decode_budget import DecodeBudget

# foxglove.PackedElementField.NumericType values and their numpy equivalents
_NUMERIC_TYPES: dict[int, np.dtype] = {
    1: np.dtype("u1"),
    2: np.dtype("i1"),
    3: np.dtype("<u2"),
    4: np.dtype("<i2"),
    5: np.dtype("<u4"),
    6: np.dtype("<i4"),
    7: np.dtype("<f4"),
    8: np.dtype("<f8"),
}
_NUMERIC_CODES = {dtype: code for code, dtype in _NUMERIC_TYPES.items()}


def encode_pointcloud(
    gaussians: GaussianMap, timestamp_ns: int, half: bool, frame_id: str
) -> PointCloud:
    """A foxglove.PointCloud holding every field of a map as packed little-endian records.

    Args:
        gaussians: the map.
        timestamp_ns: the cloud's timestamp.
        half: store the bounded attributes as float16 (positions, scores and sums stay
            float32; see `gscompress.io.columns`).
        frame_id: the frame the cloud is in.

    Raises:
        MapError: with `half`, a value beyond the float16 range.
    """
    cols = encode_columns(map_to_columns(gaussians), half)
    records = pack_records(cols, column_dtypes(cols))
    layout: dict[str, Any] = dict(records.dtype.fields or {})
    fields = [
        PackedElementField(name=name, offset=spec[1], type=_NUMERIC_CODES[spec[0]])  # type: ignore[arg-type]
        for name, spec in layout.items()
    ]
    msg = PointCloud(
        frame_id=frame_id,
        point_stride=records.dtype.itemsize,
        fields=fields,
        data=records.tobytes(),
    )
    msg.timestamp.FromNanoseconds(timestamp_ns)
    msg.pose.orientation.w = 1.0
    return msg


def record_bytes(gaussians: GaussianMap, half: bool) -> int:
    """Bytes per Gaussian in a PointCloud of this map (its point_stride)."""
    cols = encode_columns(map_to_columns(gaussians.select(slice(0, 0))), half)
    return sum(dtype.itemsize for dtype in column_dtypes(cols).values())


def pointcloud_size(
    gaussians: GaussianMap, half: bool, timestamp_ns: int, frame_id: str
) -> Callable[[int], int]:
    """Exact serialized size of the PointCloud holding K Gaussians of this map's layout.

    The message is a header that depends only on the layout (fields, stride, frame, pose,
    timestamp) plus the `data` bytes field: its tag, the varint of its length, and K records.

    Returns:
        A function K -> bytes of `encode_pointcloud(m, timestamp_ns, half, frame_id)` for any
        map m of K Gaussians with this layout (SH degree, score columns).
    """
    header = encode_pointcloud(gaussians.select(slice(0, 0)), timestamp_ns, half, frame_id)
    header_bytes = header.ByteSize()  # proto3 leaves an empty `data` out
    stride = header.point_stride
    tag_bytes = _varint_size(PointCloud.DESCRIPTOR.fields_by_name["data"].number << 3 | 2)

    def size(count: int) -> int:
        n = count * stride
        return header_bytes + (tag_bytes + _varint_size(n) + n if n else 0)

    return size


def _varint_size(value: int) -> int:
    return max(1, (value.bit_length() + 6) // 7)


def decode_pointcloud(
    data: bytes, source: str, budget: DecodeBudget | None
) -> tuple[GaussianMap, bool]:
    """The validated map of a serialized PointCloud, and whether it is at half precision.

    Args:
        budget: what the file holding the message may decode to (None: the message's own
            bounds only); the map its header declares is checked against it before decoding.

    Raises:
        DecodeError: not a PointCloud.
        MapError: a malformed map, or one over `budget`.
    """
    cloud = PointCloud.FromString(data)
    if budget is not None and cloud.point_stride > 0:
        rest = sum(f.name.startswith("f_rest_") for f in cloud.fields) // 3
        degree = next((d for d, k in SH_REST_COUNTS.items() if k >= rest), 3)
        budget.check_map(len(cloud.data) // cloud.point_stride, degree)
    return pointcloud_to_gaussians(cloud, source), has_half_columns(f.name for f in cloud.fields)


def pointcloud_to_gaussians(cloud: PointCloud, source: str = "point cloud") -> GaussianMap:
    """Decode a PointCloud written by `gaussians_to_pointcloud` (or any compatible writer).

    Checks the stride (the packed fields' span), every field's type and extent, that no two
    fields overlap, and the data length before reading, and
    the decoded map's finiteness and id uniqueness. Fields `<name>_f16` (uint16 float16 bit
    patterns) are returned as float32 `<name>`.

    Raises:
        MapError: inconsistent layout or invalid values.
    """
    stride = cloud.point_stride
    data = cloud.data
    if stride <= 0:
        raise MapError(f"{source}: point_stride is {stride}")
    if len(data) % stride:
        raise MapError(
            f"{source}: data length {len(data)} is not a multiple of point_stride {stride}"
        )
    names: list[str] = []
    formats: list[np.dtype] = []
    offsets: list[int] = []
    for f in cloud.fields:
        dtype = _NUMERIC_TYPES.get(f.type)
        if dtype is None:
            raise MapError(f"{source}: field {f.name!r} has unknown numeric type {f.type}")
        if f.offset < 0 or f.offset + dtype.itemsize > stride:
            raise MapError(f"{source}: field {f.name!r} lies outside the {stride}-byte stride")
        if f.name in names:
            raise MapError(f"{source}: field {f.name!r} appears twice")
        names.append(f.name)
        formats.append(dtype)
        offsets.append(f.offset)
    spans = sorted(
        (offset, offset + dtype.itemsize, name)
        for name, dtype, offset in zip(names, formats, offsets, strict=True)
    )
    for (_start, end, name), (start, _end, other) in itertools.pairwise(spans):
        if start < end:
            raise MapError(f"{source}: fields {name!r} and {other!r} overlap")
    span = max((end for _start, end, _name in spans), default=0)
    if stride != span:
        raise MapError(
            f"{source}: point_stride {stride} is not the {span} bytes its fields span "
            "(the records are packed)"
        )
    records = np.frombuffer(
        data,
        dtype=np.dtype(
            {"names": names, "formats": formats, "offsets": offsets, "itemsize": stride}
        ),
    )
    cols = decode_columns({name: records[name] for name in names}, source)
    return map_from_columns(cols, source).validate()
