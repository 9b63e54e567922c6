"""The map-file fuzz targets: PLY (plain and compressed layouts), compact map messages, SPZ and
SOG, each a valid file edited structurally and read as `gsc import-ply` reads it."""

from __future__ import annotations

import io
import json
import struct
import tempfile
from pathlib import Path
from typing import Any

from fuzz_mutations import SPECIAL_FLOATS, Chooser, byte_mutation, edge_value, overwrite

# -------------------------------------------------------------------------------------- PLY


def valid_ply(c: Chooser) -> bytes:
    """A small 3DGS PLY: ours with or without scores, another tool's layout, big-endian, an
    extra element, or the compressed (packed) layout."""
    from gscompress.gaussians import random_map
    from gscompress.io.ply import write_ply

    kind = c.pick(("ours", "plain", "sh3", "big-endian", "extra", "packed"))
    if kind in _PLYS:
        return _PLYS[kind]
    if kind == "packed":
        header = (
            "ply\nformat binary_little_endian 1.0\nelement chunk 1\n"
            + "".join(f"property float {n}\n" for n in ("min_x", "min_y", "min_z"))
            + "element vertex 2\n"
            + "".join(
                f"property uint packed_{n}\n" for n in ("position", "rotation", "scale", "color")
            )
            + "end_header\n"
        )
        data = header.encode() + bytes(12 + 2 * 16)
    else:
        with tempfile.TemporaryDirectory() as tmp:
            g = random_map(5, seed=1, sh_degree=3 if kind == "sh3" else 0)
            path = write_ply(g, Path(tmp) / "m.ply", importance=kind != "plain")
            data = path.read_bytes()
        if kind == "big-endian":
            data = _to_big_endian(data)
        elif kind == "extra":
            end = data.index(b"end_header\n")
            data = data[:end] + b"element face 2\nproperty int a\n" + data[end:] + bytes(8)
    _PLYS[kind] = data
    return data


_PLYS: dict[str, bytes] = {}


def _to_big_endian(data: bytes) -> bytes:
    """Our little-endian PLY (float and uint properties only) as big-endian."""
    import numpy as np

    end = data.index(b"end_header\n") + len(b"end_header\n")
    header = data[:end].decode()
    names = [line.split() for line in header.splitlines() if line.startswith("property")]
    dtype = np.dtype([(n, "<f4" if t == "float" else "<u4") for _, t, n in names])
    body = np.frombuffer(data[end:], dtype=dtype).astype(dtype.newbyteorder(">"))
    return header.replace("binary_little_endian", "binary_big_endian").encode() + body.tobytes()


_HEADER_EDITS = (
    "property",
    "property float",
    "property list uchar int vertex_indices",
    "element",
    "element vertex",
    "element vertex -1",
    "element vertex 9223372036854775808",
    "element vertex 18446744073709551616",
    "element vertex \u0661",
    "element face 1000000000000",
    "element chunk 1",
    "property uint packed_position",
    "format ascii 1.0",
    "format binary_big_endian 1.0",
    "format",
    "comment \xff",
    "obj_info x",
    "end_header",
    "property double opacity",
    "property uchar x",
    "property float x",
    "bogus 1",
)


def mutate_ply(data: bytes, c: Chooser) -> bytes:
    """One to three edits of a PLY: a header line deleted, repeated, replaced or added, the
    vertex count changed, a value of the body replaced, or a raw edit."""
    end = data.find(b"end_header\n")
    if end < 0:
        return byte_mutation(data, c)
    end += len(b"end_header\n")
    lines, body = data[:end].decode("latin-1").split("\n")[:-1], data[end:]
    for _ in range(c.integer(1, 3)):
        kind = c.pick((0, 1, 2, 3, 4, 4, 4, 4, 5, 6))  # values of the body most often
        at = c.integer(1, max(len(lines) - 1, 1))
        if kind == 0 and len(lines) > 1:
            del lines[at]
        elif kind == 1:
            lines.insert(at, c.pick(_HEADER_EDITS))
        elif kind == 2 and at < len(lines):
            lines[at] = c.pick(_HEADER_EDITS)
        elif kind == 3:  # the vertex count
            counts = [i for i, line in enumerate(lines) if line.startswith("element vertex")]
            if counts:
                lines[counts[0]] = f"element vertex {edge_value(c, 8) if c.integer(0, 1) else 4}"
        elif kind == 4 and len(body) >= 4:  # a float of the body (the opacity of a row, often)
            at = 4 * c.integer(0, len(body) // 4 - 1)
            value = struct.pack("<f", c.pick(SPECIAL_FLOATS))
            body = body[:at] + value + body[at + 4 :]
        elif kind == 5:
            body = body[: c.integer(0, len(body))] if c.integer(0, 1) else body + bytes(64)
        else:
            body = byte_mutation(body, c)
    return ("\n".join(lines) + "\n").encode("utf-8") + body


def read_ply_map(path: Path) -> None:
    """What `gsc import-ply` and `gsc score` read of a PLY."""
    from gscompress.io.ply import read_ply

    read_ply(path).opacities()


# ------------------------------------------------------------------------ compact map and SPZ


def _random_map(c: Chooser, smallest: int = 0) -> Any:
    from gscompress.gaussians import random_map

    return random_map(
        c.integer(smallest, 60), c.integer(0, 999), bool(c.integer(0, 1)), c.pick((0, 0, 1, 3))
    )


def valid_compact(c: Chooser) -> bytes:
    """A compact map message: isotropic or not, with or without ids, sums or score."""
    from gscompress.io.compact import CompactOptions, encode_compact

    options = CompactOptions(ids=bool(c.integer(0, 1)), sums=bool(c.integer(0, 1)))
    return encode_compact(_random_map(c), options).SerializeToString()


def mutate_compact(data: bytes, c: Chooser) -> bytes:
    """A header field, a column's field or its compressed codes set to an edge value, a column
    dropped or repeated, or raw bytes edited."""
    import zstandard

    from gscompress.io.compact import CompactGaussians

    message = CompactGaussians.FromString(data)
    kind = c.integer(0, 6)
    if kind == 0:
        name = c.pick(("version", "count", "sh_degree", "position_bits"))
        setattr(message, name, edge_value(c, 4))
    elif kind == 1:
        message.step = c.pick(SPECIAL_FLOATS)
        if c.integer(0, 1) and message.origin:
            message.origin[c.integer(0, len(message.origin) - 1)] = c.pick(SPECIAL_FLOATS)
    elif kind <= 4 and message.columns:
        column = message.columns[c.integer(0, len(message.columns) - 1)]
        edit = c.integer(0, 5)
        if edit == 0:
            setattr(column, c.pick(("components", "bits")), edge_value(c, 4))
        elif edit == 1:
            column.raw_bytes = edge_value(c, 8)
        elif edit == 2:
            column.dtype = c.pick(("u1", "<u2", "<u4", "<u8", "<f4", "<f8", "", "O"))
        elif edit == 3 and (column.low or column.high):
            column.low[0] = c.pick(SPECIAL_FLOATS)
        elif edit == 4:
            raw = bytes(c.pick((0, 1, 7, 4096, 1 << 20)))
            column.data = zstandard.ZstdCompressor(
                write_content_size=bool(c.integer(0, 1))
            ).compress(raw)
        else:
            column.data = byte_mutation(column.data, c)
    elif kind == 5 and message.columns:
        at = c.integer(0, len(message.columns) - 1)
        if c.integer(0, 1):
            del message.columns[at]
        else:
            message.columns.add().CopyFrom(message.columns[at])
    else:
        return byte_mutation(message.SerializeToString(), c)
    return message.SerializeToString()


def read_compact(path: Path) -> None:
    """What a log reader does with a compact `/gaussians` message."""
    from gscompress.io.compact import decode_compact_bytes

    decode_compact_bytes(path.read_bytes(), str(path))[0].opacities()


def valid_spz(c: Chooser) -> bytes:
    """An SPZ file of version 3 (gzip) or 4 (zstd streams)."""
    from gscompress.io.spz import encode_bytes

    return encode_bytes(_random_map(c, 1), version=c.pick((3, 4)))  # (SPZ holds no empty map)


def mutate_spz(data: bytes, c: Chooser) -> bytes:
    """A header field (the first 32 bytes of a v4 file; of the inflated stream of a v3 one)
    set to an edge value, or raw bytes edited."""
    import gzip

    if data[:2] == b"\x1f\x8b" and c.integer(0, 1):  # v3: edit inside the gzip stream
        inner = gzip.decompress(data)
        return gzip.compress(
            overwrite(inner, c, 0, 16) if c.integer(0, 1) else byte_mutation(inner, c)
        )
    return overwrite(data, c, 0, 32) if c.integer(0, 1) else byte_mutation(data, c)


def read_spz_map(path: Path) -> None:
    """What `gsc import-ply` reads of an SPZ file."""
    from gscompress.io.spz import read_spz

    read_spz(path).opacities()


# -------------------------------------------------------------------------------------- SOG


def valid_sog(c: Chooser) -> bytes:
    """A small SOG bundle: without higher SH, or with a palette of SH sets (`shN`) of 1 to 3
    bands."""
    import zipfile

    from conftest import sog_bundle, webp_image

    key = (c.integer(0, 3), c.pick((0, 0, 1, 3)))
    if key in _SOGS:
        return _SOGS[key]
    import numpy as np

    from gscompress.gaussians import random_map

    data = sog_bundle(random_map(20 + 10 * key[0], seed=key[0], isotropic=False))
    bands = key[1]
    if bands:
        k = {1: 3, 2: 8, 3: 15}[bands]
        rng = np.random.default_rng(key[0])
        count = json.loads(zipfile.ZipFile(io.BytesIO(data)).read("meta.json"))["count"]
        centroids = rng.integers(0, 256, (4 * k, 4), np.uint8)  # 4 sets of k pixels
        labels = np.zeros((count, 4), np.uint8)
        labels[:, 0] = rng.integers(0, 5, count)  # (label 4: past the palette, read as 0)
        shn = {
            "bands": bands,
            "count": 4,
            "codebook": np.linspace(-1, 1, 256).tolist(),
            "files": ["n_c.webp", "n_l.webp"],
        }
        members = {"n_c.webp": webp_image(centroids, 64 * k), "n_l.webp": webp_image(labels, 32)}
        data = _rezip(data, lambda meta: meta.update(shN=shn), members)
    _SOGS[key] = data
    return data


_SOGS: dict[tuple[int, int], bytes] = {}


def _rezip(
    data: bytes,
    edit_meta: Any = None,
    members: dict[str, bytes] | None = None,
    drop: str | None = None,
    compression: int | None = None,
) -> bytes:
    """A bundle's members again, meta.json edited by `edit_meta(meta)` (JSON text with
    non-finite numbers allowed), `members` replaced or added, `drop` left out."""
    import zipfile

    with zipfile.ZipFile(io.BytesIO(data)) as bundle:
        found = {info.filename: bundle.read(info) for info in bundle.infolist()}
    if edit_meta is not None:
        meta = json.loads(found["meta.json"])
        edit_meta(meta)
        found["meta.json"] = json.dumps(meta).encode()
    found.update(members or {})
    found.pop(drop or "", None)
    out = io.BytesIO()
    method = zipfile.ZIP_STORED if compression is None else compression
    with zipfile.ZipFile(out, "w", method) as bundle:
        for name, member in found.items():
            bundle.writestr(name, member)
    return out.getvalue()


_META_VALUES = (
    0,
    1,
    -1,
    2,
    3,
    4,
    255,
    256,
    65536,
    2**20,
    2**26,
    2**26 + 1,
    2**40,
    1.5,
    1e300,
    -1e300,
    1e308,
    float("nan"),
    float("inf"),
    88.0,
    89.0,
    710.0,
    "x",
    "",
    None,
    True,
    [],
    {},
)
"""Values a meta.json field is set to: ints, floats (non-finite ones as Python writes them) and
other types."""


def _meta_edit(c: Chooser) -> Any:
    """An edit of one field of meta.json: a count, a version, a bound, a codebook entry, a
    file name or the shN fields, set to an edge value (or removed)."""
    key = c.pick(("count", "version", "means", "scales", "sh0", "quats", "shN"))
    new = c.pick(_META_VALUES)

    def edit(meta: dict[str, Any]) -> None:
        entry = meta.get(key)
        if not isinstance(entry, dict) or c.integer(0, 3) == 0:
            meta[key] = new
            return
        field = c.pick(sorted(entry) or ["files"])
        if isinstance(entry.get(field), list) and entry[field] and c.integer(0, 2):
            entry[field][c.integer(0, len(entry[field]) - 1)] = c.pick(
                (new, "missing.webp", "../meta.json", "meta.json")
            )
        else:
            entry[field] = new

    return edit


def _flat_image(c: Chooser) -> bytes:
    """A single-colour image of a chosen size and format (tiny on disk, large decoded)."""
    from PIL import Image

    side = c.pick((1, 2, 7, 8, 64, 1024, 2048))
    colour = (c.integer(0, 255), 128, 128, c.pick((252, 253, 255, 0)))
    out = io.BytesIO()
    kind = c.pick(("WEBP", "WEBP", "PNG"))
    options = {"lossless": True, "exact": True} if kind == "WEBP" else {}
    Image.new("RGBA", (side, side), colour).save(out, kind, **options)
    return out.getvalue()


def mutate_sog(data: bytes, c: Chooser) -> bytes:
    """One edit of a bundle: a meta.json field, an image replaced (by a single-colour image of
    another size or format, cut short or its bytes edited), a member dropped or stored
    compressed, a count raised with every image a single colour of its size (the bomb), or a
    raw edit of the zip."""
    import zipfile

    with zipfile.ZipFile(io.BytesIO(data)) as bundle:
        names = [info.filename for info in bundle.infolist()]
        images = [name for name in names if name != "meta.json"]
        pick = c.pick(images)
        image = bundle.read(pick)
    kind = c.integer(0, 6)
    if kind <= 1:
        return _rezip(data, _meta_edit(c))
    if kind == 2:
        replaced = c.pick(
            (_flat_image(c), image[: c.integer(0, len(image))], byte_mutation(image, c))
        )
        return _rezip(data, members={pick: replaced})
    if kind == 3:
        return _rezip(data, drop=c.pick(names))
    if kind == 4:  # a bomb: many Gaussians declared, every image a flat one of their size
        count = c.pick((4096, 65536, 1 << 20))
        side = int(count**0.5)
        flat = {name: _flat_sized(side) for name in images}
        return _rezip(data, lambda meta: meta.update(count=count), flat)
    if kind == 5:
        return _rezip(data, compression=zipfile.ZIP_DEFLATED)
    return byte_mutation(data, c)


def _flat_sized(side: int) -> bytes:
    """A single-colour lossless WebP of `side` x `side` pixels."""
    from PIL import Image

    out = io.BytesIO()
    Image.new("RGBA", (side, side), (0, 0, 0, 255)).save(out, "WEBP", lossless=True, exact=True)
    return out.getvalue()


def read_sog_map(path: Path) -> None:
    """What `gsc import-ply` reads of a SOG bundle."""
    from gscompress.io.sog import read_sog

    read_sog(path).opacities()
