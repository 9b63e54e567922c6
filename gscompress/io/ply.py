"""3D Gaussian Splatting PLY files (the INRIA layout that 3DGS viewers and converters read).

Writes `binary_little_endian` vertices with the properties, in order:
x y z nx ny nz f_dc_0..2 f_rest_* opacity scale_0..2 rot_0..3, raw values (log scales, opacity
logit, w x y z quaternion), optionally followed by our extras importance, importance_sum,
importance_weight, alpha_t_sum (float) and id (uint). Viewers ignore properties they do not know.

Reads PLY maps of other 3DGS tools too: the INRIA layout with f_rest up to degree 3, the gsplat
layout without normals, either endianness, properties in any order, extra properties ignored,
and PlayCanvas's compressed layout (SuperSplat's `.compressed.ply`, decoded by `compressed_ply`).
Every file is untrusted: the header is parsed strictly and the vertex count is checked against
the file size before anything is allocated.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from gscompress import __version__
from gscompress.errors import MapError, OutputError, PlyFormatError, led_by
from gscompress.gaussians import SH_REST_COUNTS, GaussianMap
from gscompress.io.columns import (
    APPEARANCE,
    GEOMETRY,
    IMPORTANCE,
    column_dtypes,
    map_from_columns,
    map_to_columns,
    pack_records,
)
from gscompress.io.decode_budget import DecodeBudget
from gscompress.io.files import AtomicFile, check_input, check_output

_PLY_TYPES = {
    "char": "i1",
    "int8": "i1",
    "uchar": "u1",
    "uint8": "u1",
    "short": "i2",
    "int16": "i2",
    "ushort": "u2",
    "uint16": "u2",
    "int": "i4",
    "int32": "i4",
    "uint": "u4",
    "uint32": "u4",
    "float": "f4",
    "float32": "f4",
    "double": "f8",
    "float64": "f8",
}
_TYPE_NAMES = {"<f4": "float", "<u4": "uint"}
_MAX_HEADER_BYTES = 1 << 16


def write_ply(
    gaussians: GaussianMap,
    path: str | Path,
    *,
    importance: bool = True,
    inputs: tuple[str | Path, ...] = (),
    force: bool = False,
) -> Path:
    """Write a map as a 3DGS PLY file (atomically: temporary file, then rename).

    Args:
        gaussians: the map.
        path: output file.
        importance: also write importance, its sums, alpha_t_sum and id as extra properties.
        inputs: paths the output must not overwrite.
        force: overwrite an existing output.

    Returns:
        The output path.
    """
    path = check_output(path, inputs, force, suffix=".ply")
    cols = map_to_columns(gaussians, importance=importance)
    if not importance:
        del cols["id"]
    zeros = np.zeros(len(gaussians), np.float32)
    rest = [name for name in cols if name.startswith("f_rest_")]
    extras = [*IMPORTANCE, "id"] if importance else []
    order = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", *rest, "opacity"]
    order += [name for name in GEOMETRY if name.startswith(("scale", "rot"))] + extras
    cols.update(nx=zeros, ny=zeros, nz=zeros)
    dtypes = column_dtypes({name: cols[name] for name in order})
    header = [
        "ply",
        "format binary_little_endian 1.0",
        f"comment written by gscompress {__version__}",
        f"element vertex {len(gaussians)}",
        *(f"property {_TYPE_NAMES[dtypes[name].str]} {name}" for name in order),
        "end_header",
    ]
    records = pack_records(cols, dtypes)
    out = AtomicFile(path)
    try:
        out.file.write(("\n".join(header) + "\n").encode("ascii"))
        try:
            records.tofile(out.file)  # no extra copy of the records
        except OSError as exc:
            if exc.errno is not None:
                raise
            raise OutputError(f"{path}: short write ({exc}): is the disk full?") from None
        out.commit()
    except BaseException:
        out.discard()
        raise
    return path


def read_ply(path: str | Path) -> GaussianMap:
    """Read a 3DGS PLY map (ours or another tool's) into a validated GaussianMap.

    Opacity logits of +-inf (opacity exactly 1 or 0, as `splat-transform` writes them) and
    beyond +-`MAX_ABS_OPACITY_LOGIT` are read as +-that bound, with one warning.

    Raises:
        PlyFormatError: not a binary PLY, no vertex element, missing required
            properties, an element running past the end of the file, or invalid values.
    """
    path = check_input(path, PlyFormatError)
    with open(path, "rb") as f:
        head = f.read(_MAX_HEADER_BYTES)
    end = head.find(b"end_header")
    if not head.startswith((b"ply\n", b"ply\r\n")) or end < 0:
        raise PlyFormatError(f"{path}: not a PLY file (no 'ply' magic or no end_header)")
    header_end = head.index(b"\n", end) + 1 if b"\n" in head[end:] else -1
    if header_end < 0:
        raise PlyFormatError(f"{path}: header is not terminated")
    try:
        text = head[:header_end].decode("ascii")
    except UnicodeDecodeError:
        raise PlyFormatError(f"{path}: header is not ASCII") from None
    endian, elements = _parse_header(text.splitlines(), path)
    file_size = path.stat().st_size
    layout = [
        (name, count, props, np.dtype([(p, endian + t) for p, t in props]))
        for name, count, props in elements
    ]
    offset = header_end
    vertices: tuple[int, int, list[tuple[str, str]], np.dtype] | None = None
    for name, count, props, dtype in layout:  # every element checked before any is read
        if count and not props:
            raise PlyFormatError(f"{path}: element {name!r} has {count} rows but no properties")
        size = count * dtype.itemsize
        if size > file_size - offset:
            rows = "vertices" if name == "vertex" else f"rows of element {name!r}"
            raise PlyFormatError(
                f"{path}: truncated: {count} {rows} of {dtype.itemsize} bytes need "
                f"{offset + size} bytes, the file has {file_size}"
            )
        if name == "vertex" and vertices is None:
            vertices = (offset, count, props, dtype)
        offset += size
    extra = file_size - offset
    if extra > 0 and (extra > 16 or _tail(path, extra).strip(b" \t\r\n")):
        raise PlyFormatError(
            f"{path}: {extra} byte{'s' if extra != 1 else ''} after the elements the header "
            "declares (a wrong vertex count?)"
        )
    _check_budget(elements, file_size, path)
    if is_compressed_ply(elements):
        arrays, offset = {}, header_end
        for name, count, _props, dtype in layout:
            arrays[name] = np.fromfile(path, dtype=dtype, count=count, offset=offset)
            offset += count * dtype.itemsize
        from gscompress.io.compressed_ply import decompress  # (it reads with this module)

        return decompress(arrays, str(path))
    if vertices is None:
        raise PlyFormatError(f"{path}: no vertex element")
    start, count, props, dtype = vertices
    records = np.fromfile(path, dtype=dtype, count=count, offset=start)
    cols = {p: records[p] for p, _ in props}
    _check_required(cols, path)
    try:
        return map_from_columns(cols, str(path), infinite_opacity=True).validate()
    except MapError as exc:
        raise PlyFormatError(led_by(str(path), str(exc))) from None


def _check_budget(
    elements: list[tuple[str, int, list[tuple[str, str]]]], file_size: int, path: Path
) -> None:
    """Refuse a vertex count whose map is more than the file's bytes may decode to (a plain
    PLY's rows cannot make it so; a compressed one's are 16 bytes a Gaussian)."""
    for name, count, props in elements:
        if name == "vertex":
            rest = sum(prop.startswith("f_rest_") for prop, _ in props)
            sh = next((len(p) for n, _c, p in elements if n == "sh"), 0)
            degree = next((d for d, k in SH_REST_COUNTS.items() if 3 * k >= max(rest, sh)), 3)
            kind = "compressed-ply" if is_compressed_ply(elements) else "ply"
            DecodeBudget(kind, file_size, str(path), PlyFormatError).check_map(count, degree)
            return


COMPRESSED_MARK = "packed_position"
"""The vertex property that marks PlayCanvas's compressed PLY layout (SuperSplat's
`.compressed.ply`): quantised uint32 vertices, per-chunk bounds, an optional `sh` element."""


def is_compressed_ply(elements: list[tuple[str, int, list[tuple[str, str]]]]) -> bool:
    """Whether a PLY header's elements (name, count, [(property, type)]) are the compressed
    layout (a `vertex` element with `packed_position`) rather than 3DGS's plain one."""
    return any(
        name == "vertex" and any(prop == COMPRESSED_MARK for prop, _ in props)
        for name, _count, props in elements
    )


def _tail(path: Path, count: int) -> bytes:
    """The last `count` bytes of a file (a line end some writers leave is ignored)."""
    with open(path, "rb") as f:
        f.seek(-count, 2)
        return f.read()


def _parse_header(
    lines: list[str], path: Path
) -> tuple[str, list[tuple[str, int, list[tuple[str, str]]]]]:
    """(endianness prefix, [(element name, count, [(property, numpy type)])])."""
    endian = ""
    elements: list[tuple[str, int, list[tuple[str, str]]]] = []
    for number, line in enumerate(lines[1:], start=2):
        words = line.split()
        if not words or words[0] in ("comment", "obj_info", "end_header"):
            continue
        if words[0] == "format":
            if len(words) != 3 or words[1] not in ("binary_little_endian", "binary_big_endian"):
                raise PlyFormatError(
                    f"{path}: unsupported PLY format {' '.join(words[1:])!r}; "
                    "3DGS maps are binary (convert ASCII PLY first)"
                )
            endian = "<" if words[1] == "binary_little_endian" else ">"
        elif words[0] == "element":
            if len(words) != 3 or not re.fullmatch(r"[0-9]{1,19}", words[2]):
                raise PlyFormatError(f"{path}: line {number}: bad element line {line!r}")
            elements.append((words[1], int(words[2]), []))
        elif words[0] == "property":
            if not elements:
                raise PlyFormatError(f"{path}: line {number}: property before any element")
            if words[1:2] == ["list"]:
                raise PlyFormatError(
                    f"{path}: line {number}: list properties are not supported in a 3DGS map"
                )
            if len(words) != 3 or words[1] not in _PLY_TYPES:
                raise PlyFormatError(f"{path}: line {number}: bad property line {line!r}")
            elements[-1][2].append((words[2], _PLY_TYPES[words[1]]))
        else:
            raise PlyFormatError(f"{path}: line {number}: unknown header keyword {words[0]!r}")
    if not endian:
        raise PlyFormatError(f"{path}: header has no format line")
    for name, _count, props in elements:
        names = [p for p, _ in props]
        if len(set(names)) != len(names):
            raise PlyFormatError(f"{path}: element {name!r} repeats a property")
    return endian, elements


def _check_required(cols: dict[str, np.ndarray], path: Path) -> None:
    missing = [name for name in GEOMETRY + APPEARANCE if name not in cols]
    if missing:
        raise PlyFormatError(
            f"{path}: not a 3DGS map: missing vertex properties {', '.join(missing)}"
        )
