"""Hostile files, round two: bombs that a reader used to decode before refusing (or accepting)
them, temporary outputs planted as links, file names that are not UTF-8, and cameras no sensor
has. Each file is read by `gsc` in a child process held to the fuzz policy's memory bound
(tests/bounded.py): decoding a bomb fails the test even when the message is right.

Numbered by the finding each reproduces: 1 SOG, 2 SPZ at SH degree 3, 3 compact map, 4 a frame
larger than its camera, 8 a planted temporary link, 9 a name that is not UTF-8, 10 a sparse file,
11 numpy warnings and implausible intrinsics. The valid files of each format are read under the
same bound (`test_valid_files_still_import_within_the_bound`).
"""

from __future__ import annotations

import io
import json
import os
import struct
import zipfile
from pathlib import Path

import numpy as np
import pytest
import zstandard
from bounded import Bounded, memory_bound, run_bounded
from PIL import Image

from gscompress.gaussians import random_map
from gscompress.io.compact import COMPACT_VERSION, CompactColumn, CompactGaussians
from gscompress.io.mcap_log import TOPIC_GAUSSIANS, LogMetadata, LogWriter
from gscompress.io.spz import MAGIC

TORCH = ("torch", "gscompress.pipeline.slam_run")
"""What `gsc slam` imports before it reads a frame (measured in the base, not the read)."""


def _refused(run: Bounded, match: str) -> None:
    """A one-line refusal naming `match`, a non-zero exit, and memory within the bound."""
    assert run.returncode != 0, run.stderr
    assert len(run.lines) == 1, run.stderr[-3000:]
    assert match in run.lines[0], run.lines[0]
    assert "out of memory" not in run.lines[0]
    assert 0 <= run.peak_above_base <= run.bound, (run.peak_above_base, run.bound)


def _read(tmp_path: Path, args: list[str | bytes], input_bytes: int, **options) -> Bounded:
    return run_bounded(args, memory_bound(input_bytes), cwd=tmp_path, **options)


# ------------------------------------------------------------------------------ 1: SOG


def _single_colour_webp(side: int, rgba: tuple[int, int, int, int]) -> bytes:
    out = io.BytesIO()
    Image.new("RGBA", (side, side), rgba).save(out, "WEBP", lossless=True, exact=True)
    return out.getvalue()


def _sog_bomb(count: int) -> bytes:
    """A bundle of single-colour lossless WebPs (a few dozen bytes each) declaring `count`
    Gaussians (a square image of `count` pixels)."""
    side = int(np.ceil(np.sqrt(count)))
    meta = {
        "version": 2,
        "count": count,
        "means": {"mins": [0, 0, 0], "maxs": [1, 1, 1], "files": ["m_l.webp", "m_u.webp"]},
        "quats": {"files": ["q.webp"]},
        "scales": {"codebook": [-4.0] * 256, "files": ["s.webp"]},
        "sh0": {"codebook": [0.0] * 256, "files": ["c.webp"]},
    }
    images = {
        "m_l.webp": (0, 0, 0, 255),
        "m_u.webp": (0, 0, 0, 255),
        "q.webp": (128, 128, 128, 252),
        "s.webp": (0, 0, 0, 255),
        "c.webp": (0, 0, 0, 255),
    }
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w", zipfile.ZIP_STORED) as bundle:
        bundle.writestr("meta.json", json.dumps(meta))
        for name, rgba in images.items():
            bundle.writestr(name, _single_colour_webp(side, rgba))
    return out.getvalue()


def test_1_a_sog_bundle_of_single_colour_images_declaring_a_million_gaussians_is_refused(
    tmp_path,
):
    path = tmp_path / "bomb.sog"
    path.write_bytes(_sog_bomb(1 << 20))
    assert path.stat().st_size < 8000
    run = _read(tmp_path, ["import-ply", str(path), "-o", "x.mcap"], path.stat().st_size)
    _refused(run, "declares 1048576 Gaussians")
    assert not (tmp_path / "x.mcap").exists()


# ------------------------------------------------------------------------------ 2: SPZ


def _zstd(data: bytes) -> bytes:
    return zstandard.ZstdCompressor(level=19).compress(data)


def _spz_bomb(count: int, degree: int = 3) -> bytes:
    """An SPZ v4 file whose streams are zstd frames of zeros for `count` Gaussians at `degree`
    (the positions stream starts with 8 kB of noise, so that the file is over the 9-bytes-a-
    Gaussian bound the reader used to check)."""
    k = {0: 0, 1: 3, 2: 8, 3: 15}[degree]
    sizes = [9 * count, count, 3 * count, 3 * count, 4 * count, 9 * k * count // 3]
    noise = np.random.default_rng(0).integers(0, 256, 9 * count // 1024 + 64, np.uint8)
    streams = [noise.tobytes() + bytes(sizes[0] - len(noise))] + [bytes(s) for s in sizes[1:]]
    packed = [_zstd(s) for s in streams if s]
    header = struct.pack("<IIIBBBBI12x", MAGIC, 4, count, degree, 12, 0, len(packed), 32)
    toc = b"".join(struct.pack("<QQ", len(p), len(s)) for p, s in zip(packed, streams, strict=True))
    return header + toc + b"".join(packed)


def test_2_an_spz_of_zero_streams_at_sh_degree_3_is_refused_before_inflating(tmp_path):
    path = tmp_path / "bomb.spz"
    path.write_bytes(_spz_bomb(1_000_000))
    assert path.stat().st_size < 12_000
    run = _read(tmp_path, ["import-ply", str(path), "-o", "x.mcap"], path.stat().st_size)
    _refused(run, "declares 1000000 Gaussians at SH degree 3")


# ------------------------------------------------------------------------------ 3: compact


def _compact_bomb(count: int) -> CompactGaussians:
    """A compact message declaring `count` isotropic Gaussians at SH degree 3, each column a
    zstd frame of zeros, padded (with letters, which chunks barely compress) to 1/16 of a byte
    per Gaussian: what the reader used to require."""
    columns = []
    for name, transform, dtype, components in (
        ("position", "morton-delta", "<u8", 1),
        ("log_scale", "linear", "u1", 1),
        ("opacity", "sigmoid-linear", "u1", 1),
        ("f_dc", "asinh-linear", "u1", 3),
        ("f_rest", "linear", "u1", 45),
    ):
        raw = count * components * np.dtype(dtype).itemsize
        bounds = {} if transform == "morton-delta" else {"low": [0.0] * components}
        bounds |= {"high": [1.0] * components} if bounds else {}
        columns.append(
            CompactColumn(
                name=name,
                transform=transform,
                dtype=dtype,
                components=components,
                bits=8 if bounds else 0,
                raw_bytes=raw,
                data=_zstd(bytes(raw)),
                **bounds,
            )
        )
    padding = np.random.default_rng(1).choice(list(b"abcdefghij"), count // 16 + 1)
    return CompactGaussians(
        version=COMPACT_VERSION,
        count=count,
        isotropic=True,
        sh_degree=3,
        origin=[0, 0, 0],
        step=0.01,
        position_bits=10,
        columns=columns,
        frame_id=bytes(padding).decode(),
    )


def test_3_a_compact_map_declaring_a_million_gaussians_at_degree_3_is_refused(tmp_path):
    path = tmp_path / "bomb.mcap"
    with LogWriter(path, LogMetadata()) as log:
        log.write_protobuf(TOPIC_GAUSSIANS, _compact_bomb(1 << 20), 0)
    size = path.stat().st_size
    assert size < 80_000
    run = _read(tmp_path, ["info", str(path)], size)
    _refused(run, "declares 1048576 Gaussians at SH degree 3")
    run = _read(tmp_path, ["export-ply", str(path), "-o", "x.ply"], size)
    _refused(run, "declares 1048576 Gaussians at SH degree 3")
    assert not (tmp_path / "x.ply").exists()


# ------------------------------------------------------------------------------ 4: frames


def _sequence(folder: Path, colour: Image.Image | None = None, depth=None, **camera) -> Path:
    """A TUM folder of two 160x120 frames (intrinsics.json from `camera`), frame 0's colour
    or depth image replaced by `colour` / `depth` when given."""
    (folder / "rgb").mkdir(parents=True)
    (folder / "depth").mkdir()
    for i in range(2):
        Image.new("RGB", (160, 120), (90, 120, 150)).save(folder / "rgb" / f"{i}.png")
        Image.fromarray(np.full((120, 160), 5000, np.uint16)).save(folder / "depth" / f"{i}.png")
    if colour is not None:
        colour.save(folder / "rgb" / "0.png")
    if depth is not None:
        depth.save(folder / "depth" / "0.png")
    for kind in ("rgb", "depth"):
        lines = [f"{i * 0.1:.6f} {kind}/{i}.png" for i in range(2)]
        (folder / f"{kind}.txt").write_text("\n".join(lines) + "\n")
    values = {"fx": 100.0, "fy": 100.0, "cx": 79.5, "cy": 59.5, "width": 160, "height": 120}
    values |= {"depth_scale": 5000.0} | camera
    (folder / "intrinsics.json").write_text(json.dumps(values))
    return folder


def _slam(tmp_path: Path, folder: Path) -> Bounded:
    size = sum(p.stat().st_size for p in folder.rglob("*") if p.is_file())
    args = ["--threads", "1", "slam", str(folder), "-o", str(tmp_path / "x.mcap")]
    return _read(tmp_path, args, size, preload=TORCH)


def test_4_a_frame_far_larger_than_its_camera_is_refused_from_its_header(tmp_path):
    big = Image.new("RGB", (9000, 9000), (90, 120, 150))
    run = _slam(tmp_path, _sequence(tmp_path / "colour", colour=big))
    _refused(run, "is 9000x9000 but the intrinsics are for 160x120")


def test_4_a_depth_frame_far_larger_than_its_camera_is_refused_from_its_header(tmp_path):
    big = Image.fromarray(np.zeros((9000, 9000), np.uint16))
    run = _slam(tmp_path, _sequence(tmp_path / "depth", depth=big))
    _refused(run, "is 9000x9000 but the intrinsics are for 160x120")


# ------------------------------------------------------------------------------ 8: links


def test_8_a_link_planted_at_the_temporary_name_is_never_written_through(tmp_path):
    from click.testing import CliRunner

    from gscompress.io.files import temporary_path
    from gscompress_cli.main import cli

    log = tmp_path / "m.mcap"
    with LogWriter(log, LogMetadata()) as writer:
        writer.write_gaussians(random_map(30), 0)
    victim = tmp_path / "victim.txt"
    victim.write_text("keep me")
    out = tmp_path / "out.ply"
    temporary_path(out, os.getpid()).symlink_to(victim)
    result = CliRunner().invoke(cli, ["export-ply", str(log), "-o", str(out)])
    assert result.exit_code == 0, result.output
    assert victim.read_text() == "keep me"
    assert out.is_file() and not out.is_symlink() and out.read_bytes().startswith(b"ply\n")


# ------------------------------------------------------------------------------ 9: names


@pytest.mark.parametrize(
    "command",
    [
        [b"import-ply", b"bad\xff.spz", b"-o", b"x\xfe.mcap"],
        [b"prune", b"bad\xff.mcap", b"--keep", b"0.5", b"-o", b"p\xfe.mcap"],
        [b"share", b"--budget", b"0.5", b"bad\xff.mcap", b"s\xfe.mcap"],
    ],
    ids=["import-ply", "prune", "share"],
)
def test_9_a_file_name_that_is_not_utf8_is_recorded_escaped(tmp_path, command):
    from gscompress.io.mcap_log import LogReader
    from gscompress.io.spz import write_spz

    g = random_map(200, seed=3)
    write_spz(g, tmp_path / "m.spz")
    os.rename(tmp_path / "m.spz", os.path.join(bytes(tmp_path), b"bad\xff.spz"))
    with LogWriter(os.fsdecode(os.path.join(bytes(tmp_path), b"bad\xff.mcap")), LogMetadata()) as w:
        w.write_gaussians(g, 0)
    run = _read(tmp_path, command, 20_000)
    assert run.returncode == 0, run.stderr[-3000:]
    assert 0 <= run.peak_above_base <= run.bound
    with LogReader(os.fsdecode(os.path.join(bytes(tmp_path), command[-1]))) as log:
        step = log.metadata.provenance[-1]
    assert step["parent"] == "bad\\xff" + (".spz" if command[0] == b"import-ply" else ".mcap")


# ------------------------------------------------------------------------------ 10: sparse


@pytest.mark.parametrize("gzipped", [False, True], ids=["zstd", "gzip"])
def test_10_a_sparse_gibibyte_with_an_spz_header_is_not_read_whole(tmp_path, gzipped):
    path = tmp_path / "sparse.spz"
    header = struct.pack("<IIIBBBBI12x", MAGIC, 4, 1000, 0, 12, 0, 5, 32)
    with open(path, "wb") as f:
        f.write(b"\x1f\x8b\x08\x00" + bytes(6) if gzipped else header)
        f.truncate(1 << 30)
    on_disk = path.stat().st_blocks * 512
    assert on_disk < 1 << 20
    # the policy's input bytes: what the file holds on disk, not its apparent size
    run = run_bounded(
        ["import-ply", str(path), "-o", "x.mcap"], memory_bound(on_disk), cwd=tmp_path
    )
    _refused(run, "sparse.spz")


# ------------------------------------------------------------------------------ 11: warnings


def _sog_edit(tmp_path: Path, edit) -> Path:
    from conftest import sog_bundle as _sog

    path = tmp_path / "m.sog"
    path.write_bytes(_sog(random_map(100, seed=1), edit))
    return path


@pytest.mark.parametrize(
    ("edit", "match"),
    [
        (lambda m: m["scales"].update(codebook=[1e300] * 128 + [-1e300] * 128), "codebook"),
        (lambda m: m["sh0"].update(codebook=[-1e300] * 256), "codebook"),
        (lambda m: m["means"].update(mins=[-1e308] * 3, maxs=[1e308] * 3), "means.mins"),
    ],
    ids=["scale-codebook", "colour-codebook", "means"],
)
def test_11_sog_values_beyond_float32_are_refused_without_warnings(tmp_path, edit, match):
    path = _sog_edit(tmp_path, edit)
    run = _read(tmp_path, ["import-ply", str(path), "-o", "x.mcap"], path.stat().st_size)
    _refused(run, match)


def test_11_an_spz_of_colours_beyond_its_codes_is_written_without_warnings(tmp_path):
    g = random_map(50, seed=2)
    g.sh_dc[:5] = 3.4e38
    log = tmp_path / "m.mcap"
    with LogWriter(log, LogMetadata()) as writer:
        writer.write_gaussians(g, 0)
    run = _read(tmp_path, ["export-ply", str(log), "-o", "x.spz"], log.stat().st_size)
    assert run.returncode == 0 and "Warning" not in run.stderr, run.stderr[-3000:]


@pytest.mark.parametrize(
    ("camera", "match"),
    [
        ({"depth_scale": 1e-320}, "depth_scale 1e-320 is not plausible"),
        ({"cx": 1e308}, "cx 1e+308 is not plausible"),
        ({"cy": -1e308}, "cy -1e+308 is not plausible"),
        ({"fx": 1e308}, "fx 1e+308 is not plausible"),
        ({"max_depth": 1e300}, "max_depth 1e+300 is not plausible"),
    ],
    ids=["depth_scale", "cx", "cy", "fx", "max_depth"],
)
def test_11_implausible_intrinsics_are_refused_when_the_sequence_opens(tmp_path, camera, match):
    run = _slam(tmp_path, _sequence(tmp_path / "seq", **camera))
    _refused(run, match)


# ------------------------------------------------------------------------------ valid files


def test_valid_files_still_import_within_the_bound(tmp_path):
    """fp32, fp16 and compact logs and SPZ v3/v4 at SH degree 3, read as the bombs are."""
    from gscompress.io.map_files import read_map_file
    from gscompress.io.mcap_log import read_map
    from gscompress.io.spz import write_spz

    g = random_map(3000, seed=4, isotropic=False, sh_degree=3)
    for codec in ("fp32", "fp16", "compact"):
        path = tmp_path / f"{codec}.mcap"
        with LogWriter(path, LogMetadata()) as writer:
            writer.write_gaussians(g, 0, codec)
        run = _read(tmp_path, ["export-ply", str(path), "-o", f"{codec}.ply"], path.stat().st_size)
        assert run.returncode == 0, run.stderr[-3000:]
        assert 0 <= run.peak_above_base <= run.bound
        assert len(read_map_file(tmp_path / f"{codec}.ply")) == len(read_map(path)) == 3000
    for version in (3, 4):
        path = write_spz(g, tmp_path / f"v{version}.spz", version=version)
        args = ["import-ply", str(path), "-o", f"v{version}.mcap"]
        run = _read(tmp_path, args, path.stat().st_size)
        assert run.returncode == 0, run.stderr[-3000:]
        assert read_map(tmp_path / f"v{version}.mcap").sh_degree == 3
