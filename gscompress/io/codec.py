"""The map codecs: how a `/gaussians` message stores a map, in one table.

Everything that names, offers, weighs, writes or reads a codec draws on `TABLE`: the CLI's
`--codec` choices (`CODECS`), the share solver's candidates and the viewer's (`sums_choices`),
the log writer (`Codec.encode`) and reader (`decoder`, by the message's schema). A new codec is
a new row here, with its schema file.

- `fp32`: a foxglove.PointCloud of float32 records (`gscompress.io.pointcloud`), which Foxglove
  draws as it is; exact.
- `fp16`: the same, with the bounded attributes as float16.
- `compact`: our own message gscompress.CompactGaussians (`gscompress.io.compact`), quantised
  and zstd-compressed column by column.

The two PointCloud codecs always carry every Gaussian's id and PWAS sums, exactly; a compact
message carries what its `CompactOptions` ask.

numpy + zstandard + protobuf only (no torch).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from google.protobuf.message import Message

from gscompress.errors import InputError, MapError
from gscompress.gaussians import GaussianMap
from gscompress.io.compact import (
    COMPACT_SCHEMA,
    CompactGaussians,
    CompactOptions,
    decode_compact,
    encode_compact,
)
from gscompress.io.compact import layout as layout
from gscompress.io.decode_budget import DecodeBudget
from gscompress.io.pointcloud import decode_pointcloud, encode_pointcloud

POINTCLOUD_SCHEMA = "foxglove.PointCloud"
"""Schema name of the PointCloud map message in a log."""

Encoder = Callable[[GaussianMap, int, CompactOptions, str], Message]
"""(map, timestamp_ns, options, frame id) -> the message."""

Decoder = Callable[[bytes, str, "DecodeBudget | None"], tuple[GaussianMap, str]]
"""(serialized message, source, budget) -> (the validated map, the codec it was stored in)."""


@dataclass(frozen=True)
class Codec:
    """One way a `/gaussians` message stores a map.

    Attributes:
        name: what the CLI, the logs' metadata and the viewer call it.
        schema: the protobuf schema name of its messages (two codecs may share one: their
            decoder tells them apart).
        carries_all: always carries every Gaussian's id and PWAS sums, exactly (a
            `CompactOptions` does not apply).
        lossless: the decoded map is the encoded one, bit for bit.
        encode: the message of a map.
        decode: the map of a message of its schema, and the codec it was stored in.
    """

    name: str
    schema: str
    carries_all: bool
    lossless: bool
    encode: Encoder
    decode: Decoder


def _pointcloud_encoder(half: bool) -> Encoder:
    """The encoder of a PointCloud codec (float16 bounded attributes if `half`)."""

    def encode(
        gaussians: GaussianMap, timestamp_ns: int, _options: CompactOptions, frame_id: str
    ) -> Message:
        return encode_pointcloud(gaussians, timestamp_ns, half, frame_id)

    return encode


def _decode_pointcloud(
    data: bytes, source: str, budget: DecodeBudget | None
) -> tuple[GaussianMap, str]:
    """A PointCloud map and its codec: fp16 where some attribute is float16."""
    gaussians, half = decode_pointcloud(data, source, budget)
    return gaussians, (FP16 if half else FP32).name


def _encode_compact(
    gaussians: GaussianMap, timestamp_ns: int, options: CompactOptions, frame_id: str
) -> Message:
    return encode_compact(gaussians, options, timestamp_ns=timestamp_ns, frame_id=frame_id)


def _decode_compact(
    data: bytes, source: str, budget: DecodeBudget | None
) -> tuple[GaussianMap, str]:
    """A compact map, its declared count checked against `budget` before decoding."""
    message = CompactGaussians.FromString(data)
    if budget is not None:
        budget.check_map(int(message.count), int(message.sh_degree))
    return decode_compact(message, len(data), source), COMPACT.name


FP32 = Codec("fp32", POINTCLOUD_SCHEMA, True, True, _pointcloud_encoder(False), _decode_pointcloud)
FP16 = Codec("fp16", POINTCLOUD_SCHEMA, True, False, _pointcloud_encoder(True), _decode_pointcloud)
COMPACT = Codec("compact", COMPACT_SCHEMA, False, False, _encode_compact, _decode_compact)

TABLE = (FP32, FP16, COMPACT)
"""Every map codec, from the largest to the smallest."""

CODECS = tuple(codec.name for codec in TABLE)
"""The codecs' names, from the largest to the smallest."""

PRECISIONS = tuple(codec.name for codec in TABLE if codec.schema == POINTCLOUD_SCHEMA)
"""The PointCloud codecs, named for their precision (`gsc share --precision`, an old name of
`--codec`)."""

MAP_SCHEMAS = tuple(dict.fromkeys(codec.schema for codec in TABLE))
"""The schema names a `/gaussians` message may have."""

DEFAULT_CODEC = FP32.name
"""The codec of a map written unless asked otherwise (a SLAM log's snapshots): exact, drawn by
Foxglove; also the size a `%bytes` budget is a fraction of."""

DEFAULT_SHARE_CODEC = COMPACT.name
"""The codec a share is sent in unless asked otherwise."""

SHARE_IDS = False
"""Whether a compact share carries the Gaussians' ids unless asked (`gsc share --ids`). A merge
numbers the share's Gaussians anew past the receiver's ids, so they would only trace a Gaussian
back to the sender's, at a cost in bytes (docs/codecs.md, "The compact message")."""

SHARE_DEFAULTS = CompactOptions(ids=SHARE_IDS)
"""What a compact share carries unless asked otherwise: the PWAS sums, no ids."""


def get_codec(name: str) -> Codec:
    """The codec called `name`.

    Raises:
        InputError: no codec is called so.
    """
    for codec in TABLE:
        if codec.name == name:
            return codec
    raise InputError(f"unknown codec {name!r}; choose one of {', '.join(CODECS)}")


def check_codec(name: str) -> str:
    """Return `name` if it is one of CODECS, else raise InputError."""
    return get_codec(name).name


def pointcloud_half(precision: str) -> bool:
    """Whether the PointCloud codec `precision` (fp32 or fp16) stores float16 attributes.

    Raises:
        InputError: not a PointCloud codec.
    """
    if precision not in PRECISIONS:
        raise InputError(f"unknown precision {precision!r}; choose one of {', '.join(PRECISIONS)}")
    return precision == FP16.name


def decoder(schema: str, source: str = "map") -> Decoder:
    """The decoder of `/gaussians` messages of `schema`.

    Raises:
        MapError: no codec writes that schema.
    """
    for codec in TABLE:
        if codec.schema == schema:
            return codec.decode
    raise MapError(f"{source}: a map message is {schema}, not {' or '.join(MAP_SCHEMAS)}")


def sums_choices(name: str) -> tuple[bool, ...]:
    """Whether a share in codec `name` may carry the PWAS sums: (True,) where it always does,
    (True, False) where they are an option."""
    return (True,) if get_codec(name).carries_all else (True, False)


def carries_ids(name: str, ids: bool) -> bool:
    """Whether a map in codec `name` asked to carry ids (`ids`) carries them."""
    return ids or get_codec(name).carries_all
