"""PlayCanvas SOG (version 2): read a `.sog` bundle (a zip) or its unbundled `meta.json`.

A SOG map is a `meta.json` beside lossless WebP images, one RGBA pixel per Gaussian (row-major,
the first `count` pixels):

- `means`: two images, the low and high bytes of 16-bit codes t of each axis; the position is
  s^-1(min + (max - min) t / 65535) per axis with s(x) = sign(x) ln(1 + |x|);
- `quats`: r g b the three smaller components of the unit quaternion (w x y z, the largest
  made positive) as codes of (q sqrt(2) + 1) / 2, alpha 252 + the index of the largest;
- `scales`: r g b index a 256-entry codebook of log scales;
- `sh0`: r g b index a 256-entry codebook of the SH DC term, alpha the opacity (8 bits);
- `shN` (optional): a palette of `count` SH sets (an image 64 sets wide, each set `K` pixels
  whose r g b index a 256-entry codebook) and a labels image (16-bit palette index).

Read with Pillow (already a dependency). SOG's codebooks and palette come from k-means
clustering; `write_sog` has `@playcanvas/splat-transform` (node) write the file, on the CPU.
Every file is untrusted: sizes of the bundle's members, of meta.json and of each image (from its
header, before decoding) are checked against the declared count and stated ceilings.
"""

from __future__ import annotations

import io
import json
import math
import os
import shutil
import subprocess
import tempfile
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

from gscompress.errors import MapError, MissingDependencyError, OutputError, SogFormatError
from gscompress.gaussians import SH_REST_COUNTS, GaussianMap
from gscompress.io.columns import f_rest_names, map_from_columns
from gscompress.io.decode_budget import DecodeBudget
from gscompress.io.files import check_input, write_atomic
from gscompress.io.ply import write_ply
from gscompress.io.quantise import FLOAT32_MAX
from gscompress.io.spz import opacity_logits

MAX_SOG_GAUSSIANS = 1 << 26
"""Largest Gaussian count read."""

MAX_META_BYTES = 16 << 20
"""Largest meta.json read."""

SPLAT_TRANSFORM_ENV = "GSC_SPLAT_TRANSFORM"
"""Environment variable naming the splat-transform command to use."""

SPLAT_TRANSFORM_TIMEOUT_S = 3600
"""How long one splat-transform conversion may take."""


def splat_transform() -> str | None:
    """The `splat-transform` command: $GSC_SPLAT_TRANSFORM, else one on the PATH, else the one
    `make js-deps` installs in a source checkout (tests/js); None when there is none or node is
    missing."""
    named = os.environ.get(SPLAT_TRANSFORM_ENV)
    if named:  # (as asked, or nothing)
        found = shutil.which(named)
    else:
        local = Path(__file__).resolve().parents[2] / "tests/js/node_modules/.bin/splat-transform"
        found = shutil.which("splat-transform") or shutil.which(local)
    return found if found and shutil.which("node") else None


def write_sog(gaussians: GaussianMap, path: str | Path) -> int:
    """Write a map as a SOG bundle with splat-transform (from a 3DGS PLY, k-means on the CPU);
    the file's bytes.

    Raises:
        MissingDependencyError: no node or splat-transform (`make js-deps` installs it).
        OutputError: splat-transform failed (its last line of output).
    """
    command = splat_transform()
    if command is None:
        raise MissingDependencyError(
            "writing SOG needs node and @playcanvas/splat-transform: run `make js-deps`, or set "
            f"{SPLAT_TRANSFORM_ENV} to its command"
        )
    path = Path(path)
    with tempfile.TemporaryDirectory() as tmp:
        ply = write_ply(gaussians, Path(tmp) / "map.ply", importance=False)
        out = Path(tmp) / "map.sog"
        done = subprocess.run(
            [command, "-w", "-g", "cpu", str(ply), str(out)],
            capture_output=True,
            text=True,
            timeout=SPLAT_TRANSFORM_TIMEOUT_S,
        )
        if done.returncode != 0 or not out.is_file():
            last = (done.stderr or done.stdout).strip().splitlines()[-1:] or ["no output"]
            raise OutputError(f"{path}: splat-transform failed: {last[0]}")
        with open(out, "rb") as made:
            write_atomic(path, lambda file: shutil.copyfileobj(made, file))
    return path.stat().st_size


_QUAT_SLOTS = {0: (1, 2, 3), 1: (0, 2, 3), 2: (0, 1, 3), 3: (0, 1, 2)}

_IMAGES = ("means", "quats", "scales", "sh0", "shN")
"""The meta.json entries that name images."""

MAX_LOG_POSITION = math.log(float(np.finfo(np.float32).max))
"""Largest |s(x)| of `means.mins` / `means.maxs` (s(x) = sign(x) ln(1 + |x|)): beyond it a
position is not a finite float32."""
"""Where the three stored components go (w x y z indices) for each largest component."""


def read_sog(path: str | Path) -> GaussianMap:
    """Read a SOG map (a `.sog` zip, or the `meta.json` of an unbundled one), validated.

    Ids are 0..N-1 and the map is unscored (SOG stores neither). The declared count is checked
    against what the bundle's bytes (or those of meta.json and the images it names) may decode
    to (`gscompress.io.decode_budget`) before any image is read.

    Raises:
        SogFormatError: naming the file: not a SOG bundle, version 1 or unknown, a count over
            the ceiling or the input's budget, a missing or oversized member, an image smaller
            than the count.
    """
    path = check_input(path, SogFormatError)
    if zipfile.is_zipfile(path):
        try:
            with zipfile.ZipFile(path) as bundle:
                return _decode(_Bundle(bundle, str(path)), path.stat().st_size, str(path))
        except (zipfile.BadZipFile, zipfile.LargeZipFile, OSError, EOFError) as exc:
            raise SogFormatError(f"{path}: corrupt SOG bundle ({exc})") from None
    if path.name != "meta.json":
        raise SogFormatError(
            f"{path}: not a SOG bundle (not a readable zip archive; truncated?) nor a meta.json"
        )
    return _decode(_Folder(path), None, str(path))


ZIP_METHODS = (zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED)
"""The zip compression methods a SOG bundle's files are read with (what SOG writers use)."""

ZIP_ENCRYPTED = 0x1
"""The zip flag bit of an encrypted member."""


class _Bundle:
    """The members of a `.sog` zip, each read with a bound."""

    def __init__(self, bundle: zipfile.ZipFile, source: str):
        self.bundle, self.source = bundle, source
        self.members = {info.filename: info for info in bundle.infolist()}

    def size(self, name: str) -> int:
        """The bytes a member declares it inflates to."""
        return self._info(name).file_size

    def load(self, name: str, limit: int) -> bytes:
        """A member's bytes, refused over `limit` (inflated no further than `limit` + 1)."""
        info = self._info(name)
        if info.file_size > limit:
            raise SogFormatError(f"{self.source}: {name} is over {limit} bytes")
        if info.compress_type not in ZIP_METHODS or info.flag_bits & ZIP_ENCRYPTED:
            raise SogFormatError(
                f"{self.source}: {name} is encrypted or compressed by zip method "
                f"{info.compress_type}; a SOG bundle stores or deflates its files"
            )
        with self.bundle.open(info) as member:
            data = member.read(limit + 1)
        if len(data) > limit:
            raise SogFormatError(f"{self.source}: {name} is over {limit} bytes")
        return data

    def _info(self, name: str) -> zipfile.ZipInfo:
        info = self.members.get(name)
        if info is None:
            raise SogFormatError(f"{self.source}: the bundle has no {name}")
        return info


class _Folder:
    """The files beside an unbundled SOG's meta.json."""

    def __init__(self, meta: Path):
        self.meta, self.folder = meta, meta.parent

    def _file(self, name: str) -> Path:
        member = self.folder / name
        if Path(name).name != name or not member.is_file():
            raise SogFormatError(f"{self.meta}: no file {name!r} beside it")
        return member

    def size(self, name: str) -> int:
        """A file's bytes."""
        return self._file(name).stat().st_size

    def load(self, name: str, limit: int) -> bytes:
        """A file's bytes, refused over `limit` (no more than `limit` + 1 of them read)."""
        member = self._file(name)
        with open(member, "rb") as f:
            data = f.read(limit + 1)
        if len(data) > limit:
            raise SogFormatError(f"{member}: over {limit} bytes")
        return data


def _decode(members: _Bundle | _Folder, input_bytes: int | None, source: str) -> GaussianMap:
    """The map of a SOG's members; `input_bytes`: the bundle's size (None: the sum of meta.json
    and the files it names)."""
    meta = _meta(members.load("meta.json", MAX_META_BYTES), source)
    count = meta["count"]
    shn = meta.get("shN")
    degree = shn["bands"] if shn is not None else 0
    if input_bytes is None:
        names = ["meta.json", *(name for key in _IMAGES for name in _images(meta, key))]
        input_bytes = sum(members.size(name) for name in dict.fromkeys(names))
    DecodeBudget("sog", input_bytes, source, SogFormatError).check_map(count, degree)
    image_limit = 64 * count + (1 << 20)  # lossless WebP of 4-byte pixels: far below this

    def image(name: str, at_least: int, width: int | None = None) -> np.ndarray:
        return _rgba(members.load(name, image_limit), at_least, width, f"{source}: {name}")

    files = {key: meta[key]["files"] for key in ("means", "quats", "scales", "sh0")}
    low = image(files["means"][0], count)[:count].astype(np.int64)
    high = image(files["means"][1], count)[:count].astype(np.int64)
    mins, maxs = np.array(meta["means"]["mins"]), np.array(meta["means"]["maxs"])
    span = np.where(maxs - mins != 0, maxs - mins, 1.0)
    logged = mins + span * ((low[:, :3] | high[:, :3] << 8) / 65535)
    means = np.sign(logged) * np.expm1(np.abs(logged))
    quats = _quats(image(files["quats"][0], count)[:count])
    scale_codes = image(files["scales"][0], count)[:count]
    log_scales = np.asarray(meta["scales"]["codebook"], np.float32)[scale_codes[:, :3]]
    sh0 = image(files["sh0"][0], count)[:count]
    sh_dc = np.asarray(meta["sh0"]["codebook"], np.float32)[sh0[:, :3]]
    cols: dict[str, np.ndarray] = {"x": means[:, 0], "y": means[:, 1], "z": means[:, 2]}
    cols.update({f"scale_{i}": log_scales[:, i] for i in range(3)})
    cols.update({f"rot_{i}": quats[:, i] for i in range(4)})
    cols.update({f"f_dc_{i}": sh_dc[:, i] for i in range(3)})
    cols["opacity"] = opacity_logits(sh0[:, 3].astype(np.float32) / 255)
    if shn is not None and SH_REST_COUNTS[degree]:
        k = SH_REST_COUNTS[degree]
        labels = image(shn["files"][1], count)[:count].astype(np.int64)
        centroids = image(shn["files"][0], 0, width=64 * k)
        rest = _sh_rest(labels[:, 0] | labels[:, 1] << 8, centroids, shn, k)
        by_channel = rest.transpose(0, 2, 1).reshape(count, 3 * k)
        cols.update({name: by_channel[:, i] for i, name in enumerate(f_rest_names(k))})
    try:
        return map_from_columns(cols, source).validate()
    except MapError as exc:
        raise SogFormatError(f"{source}: {exc}") from None


def _sh_rest(label: np.ndarray, centroids: np.ndarray, shn: dict[str, Any], k: int) -> np.ndarray:
    """[N, K, 3] SH rest coefficients of palette labels [N]: a label past the palette is zero."""
    codebook = np.asarray(shn["codebook"], np.float32)
    palette = centroids.reshape(-1, k, 4)[:, :, :3]  # [sets, K, rgb]
    known = label < min(shn["count"], len(palette))
    rest = np.zeros((len(label), k, 3), np.float32)
    rest[known] = codebook[palette[label[known]]]
    return rest


def _images(meta: dict[str, Any], key: str) -> list[str]:
    """The image files meta.json names for `key` (none for an absent `shN`)."""
    entry = meta.get(key)
    return list(entry["files"][: 2 if key in ("means", "shN") else 1]) if entry else []


def _meta(text: bytes, source: str) -> dict[str, Any]:
    """meta.json, checked field by field."""
    if len(text) > MAX_META_BYTES:
        raise SogFormatError(f"{source}: meta.json is over {MAX_META_BYTES >> 20} MiB")
    try:
        meta = json.loads(text)
    except (ValueError, RecursionError) as exc:
        raise SogFormatError(f"{source}: meta.json is not JSON ({exc})") from None
    if not isinstance(meta, dict):
        raise SogFormatError(f"{source}: meta.json is not an object")
    if meta.get("version") != 2:
        raise SogFormatError(
            f"{source}: SOG meta version {meta.get('version', '1 (none given)')!r} is not read "
            "(version 2 is)"
        )
    count = meta.get("count")
    if not isinstance(count, int) or isinstance(count, bool) or not 0 <= count <= MAX_SOG_GAUSSIANS:
        raise SogFormatError(f"{source}: count must be a whole number in 0..{MAX_SOG_GAUSSIANS}")
    for key, files in (("means", 2), ("quats", 1), ("scales", 1), ("sh0", 1)):
        _files(meta, key, files, source)
    for key in ("mins", "maxs"):
        _numbers(meta["means"].get(key), 3, f"means.{key}", source, MAX_LOG_POSITION)
    for key in ("scales", "sh0"):
        _numbers(meta[key].get("codebook"), 256, f"{key}.codebook", source)
    shn = meta.get("shN")
    if shn is not None:
        _files(meta, "shN", 2, source)
        if shn.get("bands") not in (1, 2, 3):
            raise SogFormatError(f"{source}: shN.bands must be 1, 2 or 3")
        _numbers(shn.get("codebook"), 256, "shN.codebook", source)
        palette = shn.get("count")
        if not isinstance(palette, int) or not 0 <= palette <= 1 << 16:
            raise SogFormatError(f"{source}: shN.count must be a whole number in 0..65536")
    return meta


def _files(meta: dict[str, Any], key: str, count: int, source: str) -> None:
    entry = meta.get(key)
    files = entry.get("files") if isinstance(entry, dict) else None
    if not isinstance(files, list) or len(files) < count:
        raise SogFormatError(f"{source}: {key}.files must name {count} image(s)")
    if not all(isinstance(name, str) for name in files[:count]):
        raise SogFormatError(f"{source}: {key}.files must be file names")


def _numbers(values: Any, count: int, what: str, source: str, bound: float = FLOAT32_MAX) -> None:
    """Refuse anything but `count` numbers within +-`bound` (float32's range by default: a
    codebook holds float32 values)."""
    ok = isinstance(values, list) and len(values) == count
    if not ok or not all(
        isinstance(v, int | float) and not isinstance(v, bool) and abs(v) <= bound for v in values
    ):
        raise SogFormatError(
            f"{source}: {what} must be {count} finite numbers within +-{bound:.6g}"
        )


def _rgba(data: bytes, at_least: int, width: int | None, what: str) -> np.ndarray:
    """[W*H, 4] uint8 pixels of an image, its size checked from the header before decoding."""
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(io.BytesIO(data)) as picture:
            w, h = picture.size
            if w * h < at_least or w * h > 4 * at_least + (1 << 20):
                raise SogFormatError(f"{what} is {w}x{h}, not sized for {at_least} Gaussians")
            if width is not None and w != width:
                raise SogFormatError(f"{what} is {w} wide, expected {width}")
            if picture.format != "WEBP":
                raise SogFormatError(f"{what} is not a WebP image")
            pixels = np.asarray(picture.convert("RGBA"), np.uint8)
    except (UnidentifiedImageError, OSError, ValueError, Image.DecompressionBombError) as exc:
        raise SogFormatError(f"{what} is not a readable image ({exc})") from None
    return pixels.reshape(-1, 4)


def _quats(pixels: np.ndarray) -> np.ndarray:
    """[N, 4] float32 quaternions (w x y z) of quats.webp pixels (an unknown tag: identity)."""
    n = len(pixels)
    stored = (pixels[:, :3].astype(np.float32) / 255 * 2 - 1) / np.float32(math.sqrt(2))
    tag = pixels[:, 3].astype(np.int64) - 252
    q = np.zeros((n, 4), np.float32)
    for largest, slots in _QUAT_SLOTS.items():
        rows = tag == largest
        q[np.ix_(rows, slots)] = stored[rows]
        q[rows, largest] = np.sqrt(np.maximum(0, 1 - np.square(stored[rows]).sum(axis=1)))
    q[(tag < 0) | (tag > 3), 0] = 1
    return q
