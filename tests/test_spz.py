"""SPZ and PlayCanvas compressed PLY: round trips within the formats' quantisation, hostile files
refused with one line, and cross-checks with splat-transform (skipped without node)."""

import gzip
import io
import shutil
import struct
import subprocess
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp
from scipy.spatial import cKDTree

from gscompress.errors import MapError, PlyFormatError, SpzFormatError
from gscompress.gaussians import SH_C0, SH_REST_COUNTS, GaussianMap, random_map
from gscompress.io import spz
from gscompress.io.compressed_ply import decompress
from gscompress.io.map_files import read_map_file
from gscompress.io.mcap_log import LogMetadata, LogWriter, read_map
from gscompress.io.ply import read_ply, write_ply
from gscompress_cli.main import cli

JS = Path(__file__).parent / "js"
TOOL = JS / "node_modules" / ".bin" / "splat-transform"


# ------------------------------------------------------------------ quantisation bounds


def _unit(quats: np.ndarray) -> np.ndarray:
    q = quats.astype(np.float64)
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def assert_spz_quantised(h: GaussianMap, g: GaussianMap, fractional_bits: int = 12) -> None:
    """`h` is `g` as SPZ stores it: each value within half a code step of the original (after
    clipping to the format's range)."""
    assert len(h) == len(g) and h.sh_degree == g.sh_degree
    assert h.isotropic or not g.isotropic  # (three equal codes read as one scale)
    step = 2.0**-fractional_bits
    assert np.abs(h.means.astype(np.float64) - g.means).max() <= step / 2 * 1.001 + 1e-6
    wanted = np.clip(_log3(g), -10, 15.9375 - 10)
    assert np.abs(_log3(h) - wanted).max() <= 1 / 32 + 1e-5
    alpha = 0.5 + 0.5 * np.tanh(0.5 * g.opacity_logits.astype(np.float64))
    assert np.abs(h.opacities() - alpha).max() <= 0.5 / 255 + 1e-5
    reach = 127.5 / (0.15 * 255)
    assert np.abs(h.sh_dc - np.clip(g.sh_dc, -reach, reach)).max() <= 0.5 / (0.15 * 255) + 1e-5
    dot = np.abs(np.sum(_unit(h.quats) * _unit(g.quats), axis=1))
    assert (1 - dot).max() <= 1e-5  # 9-bit components of |q| <= sqrt(1/2): under 0.3 degrees
    if g.sh_degree:
        rest = np.clip(g.sh_rest, -1, 127 / 128)
        bound = np.full(g.sh_rest.shape[1], 8.5 / 128)  # codes rounded to multiples of 16 ...
        bound[:3] = 4.5 / 128  # ... and of 8 for degree 1
        assert np.all(np.abs(h.sh_rest - rest) <= bound[None, :, None] + 1e-5)


def _log3(g: GaussianMap) -> np.ndarray:
    return np.broadcast_to(g.log_scales, (len(g), 3))


def _extreme_maps(draw, n: int, isotropic: bool, degree: int) -> GaussianMap:
    """A valid map with values up to the limits a GaussianMap allows (and SPZ's position reach)."""

    def floats(shape, low, high):
        return draw(
            hnp.arrays(
                np.float32,
                shape,
                elements=st.floats(float(np.float32(low)), float(np.float32(high)), width=32),
            )
        )

    quats = floats((n, 4), -1e18, 1e18)
    quats[np.all(quats == 0, axis=1), 0] = 1  # (all-zero rotations are not valid)
    return GaussianMap.new(
        means=floats((n, 3), -2047.0, 2047.0),
        log_scales=floats((n, 1 if isotropic else 3), -40.0, 40.0),
        quats=quats,
        opacity_logits=floats((n,), -1e30, 1e30),
        sh_dc=floats((n, 3), -1e6, 1e6),
        sh_rest=floats((n, SH_REST_COUNTS[degree], 3), -100.0, 100.0),
    ).validate()


@st.composite
def extreme_maps(draw):
    n = draw(st.integers(1, 40))
    return _extreme_maps(draw, n, draw(st.booleans()), draw(st.sampled_from([0, 1, 2, 3])))


# ------------------------------------------------------------------ round trips


@pytest.mark.parametrize("version", [3, 4])
@pytest.mark.parametrize("isotropic", [True, False])
@pytest.mark.parametrize("degree", [0, 1, 3])
def test_round_trip_of_random_maps_is_within_quantisation(version, isotropic, degree):
    g = random_map(300, seed=degree, isotropic=isotropic, sh_degree=degree)
    data = spz.encode_bytes(g, version=version, ordered=False)
    assert data[:2] == b"\x1f\x8b" if version == 3 else data[:4] == b"NGSP"
    h = spz.decode_bytes(data)
    assert_spz_quantised(h, g)
    assert np.array_equal(h.ids, np.arange(len(g))) and not h.has_importance  # SPZ has neither
    again = spz.encode_bytes(h, version=version, ordered=False)
    again = spz._unpack_streams(io.BytesIO(again), "")[0].data
    first = spz._unpack_streams(io.BytesIO(data), "")[0].data
    for i in (0, 1, 2, 3, 5):  # decoded values sit on their codes (rotations: up to float error)
        assert np.array_equal(again[i], first[i])


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(g=extreme_maps(), version=st.sampled_from([3, 4]))
def test_round_trip_of_extreme_maps_is_within_quantisation(g, version):
    h = spz.decode_bytes(spz.encode_bytes(g, version=version, ordered=False))
    assert_spz_quantised(h, g)
    ordered = spz.decode_bytes(spz.encode_bytes(g, version=version))
    permuted = h.select(spz.storage_order(g.means))
    for name in ("means", "log_scales", "quats", "opacity_logits", "sh_dc", "sh_rest"):
        assert np.array_equal(getattr(ordered, name), getattr(permuted, name))


def test_positions_beyond_2048_m_get_fewer_fraction_bits_and_beyond_24_bits_are_refused():
    g = random_map(50, seed=2)
    g.means[0] = [5000.0, -3.0, 1.0]
    data = spz.encode_bytes(g, ordered=False)
    assert data[13] == 10  # 5000 * 2^10 < 2^23 <= 5000 * 2^11
    assert_spz_quantised(spz.decode_bytes(data), g, fractional_bits=10)
    g.means[0] = [9e6, 0, 0]
    with pytest.raises(MapError, match="beyond the range of SPZ's 24-bit positions"):
        spz.encode_bytes(g)


def test_an_empty_map_is_refused_by_the_writer():
    with pytest.raises(MapError, match="empty map"):
        spz.encode_bytes(GaussianMap.empty())


def test_ordered_storage_follows_a_morton_curve_and_compresses_better():
    rng = np.random.default_rng(0)
    g = random_map(4000, seed=5)
    g.means = (rng.normal(size=(4000, 3)) * [2, 1, 0.5]).astype(np.float32)
    order = spz.storage_order(g.means)
    assert sorted(order.tolist()) == list(range(4000))
    steps = np.linalg.norm(np.diff(g.means[order], axis=0), axis=1)
    assert np.median(steps) < np.median(np.linalg.norm(np.diff(g.means, axis=0), axis=1)) / 5
    assert len(spz.encode_bytes(g)) < len(spz.encode_bytes(g, ordered=False))


def test_version_2_rotations_read(tmp_path):
    g = random_map(64, seed=4)
    quats = _unit(g.quats)[:, [1, 2, 3, 0]]
    quats *= np.where(quats[:, 3:] < 0, -1, 1)  # w >= 0, left out
    xyz = np.clip(np.round(quats[:, :3] * 127.5 + 127.5), 0, 255).astype(np.uint8)
    v4 = spz._unpack_streams(io.BytesIO(spz.encode_bytes(g, ordered=False)), "x")[0].data
    body = [v4[0], v4[1], v4[2], v4[3], xyz.reshape(-1)]
    raw = struct.pack("<IIIBBBB", spz.MAGIC, 2, 64, 0, 12, 0, 0) + b"".join(
        a.tobytes() for a in body
    )
    h = spz.decode_bytes(gzip.compress(raw))
    assert np.abs(np.sum(_unit(h.quats) * _unit(g.quats), axis=1)).min() > 0.999


# ------------------------------------------------------------------ hostile files


def _one_line_refusal(data: bytes, match: str) -> None:
    with pytest.raises(SpzFormatError, match=match) as info:
        spz.decode_bytes(data, "m.spz")
    assert "\n" not in str(info.value) and str(info.value).startswith("m.spz: ")


@pytest.mark.parametrize("version", [3, 4])
def test_every_truncation_is_refused_with_one_line(version):
    data = spz.encode_bytes(random_map(200, seed=1, sh_degree=1), version=version)
    for cut in [0, 1, 3, 10, 16, 31, 40, 100, len(data) // 2, len(data) - 9, len(data) - 1]:
        _one_line_refusal(data[:cut], "truncated|not an SPZ|corrupt|runs past")


@pytest.mark.parametrize("version", [3, 4])
def test_absurd_counts_are_refused_before_allocating(version):
    data = spz.encode_bytes(random_map(20, seed=1), version=version)
    for count in (2**32 - 1, spz.MAX_SPZ_GAUSSIANS + 1, 10_000_000):
        raw = _with_count(data, version, count)
        _one_line_refusal(raw, "declares")


def _with_count(data: bytes, version: int, count: int) -> bytes:
    if version == 4:
        return data[:8] + struct.pack("<I", count) + data[12:]
    raw = gzip.decompress(data)
    return gzip.compress(raw[:8] + struct.pack("<I", count) + raw[12:])


def test_a_count_that_disagrees_with_the_streams_is_refused():
    data = spz.encode_bytes(random_map(20, seed=1), version=4)
    _one_line_refusal(_with_count(data, 4, 21), "stream 0 holds 180 bytes, 21 Gaussians need 189")
    data = spz.encode_bytes(random_map(20, seed=1), version=3)
    _one_line_refusal(_with_count(data, 3, 21), "truncated")
    _one_line_refusal(_with_count(data, 3, 19), "data after the 19 Gaussians")


@pytest.mark.parametrize(
    ("edit", "match"),
    [
        (lambda d: b"NGSQ" + d[4:], "not an SPZ file"),
        (lambda d: d[:4] + struct.pack("<I", 5) + d[8:], "version 5 is not supported"),
        (lambda d: d[:12] + b"\x04" + d[13:], "SH degree 4 is not supported"),
        (lambda d: d[:15] + b"\x07" + d[16:], "7 streams, expected 5"),
        (lambda d: d[:16] + struct.pack("<I", 1 << 30) + d[20:], "stream table lies outside"),
        (lambda d: d + b"\0", "1 bytes after the last stream"),
        (lambda d: d[:112] + bytes(4) + d[116:], "stream 0 is not a zstd frame"),
        (lambda d: d[:120] + bytes(30) + d[150:], "stream 0 is corrupt|stream 0 decompresses to"),
        (lambda d: d[:48] + struct.pack("<Q", 1 << 62) + d[56:], "runs past the end"),
    ],
)
def test_corrupt_version_4_files_are_refused(edit, match):
    _one_line_refusal(edit(spz.encode_bytes(random_map(30, seed=3))), match)


def test_corrupt_gzip_is_refused():
    data = bytearray(spz.encode_bytes(random_map(300, seed=3), version=3))
    data[40:60] = bytes(20)
    _one_line_refusal(bytes(data), "corrupt gzip|truncated")
    _one_line_refusal(gzip.compress(b"hello, world, not a map"), "not an SPZ file")


def test_read_spz_names_the_file(tmp_path):
    with pytest.raises(SpzFormatError, match="no such file"):
        spz.read_spz(tmp_path / "none.spz")
    (tmp_path / "bad.spz").write_bytes(b"junk")
    with pytest.raises(SpzFormatError, match=r"bad\.spz: not an SPZ file"):
        read_map_file(tmp_path / "bad.spz")


# ------------------------------------------------------------------ compressed PLY


def _compressed_ply(g: GaussianMap, sh: bool, chunk_colours: bool = True) -> bytes:
    """A PlayCanvas compressed PLY of `g` (an encoder written from the layout, for tests)."""
    n = len(g)
    owner = np.arange(n) // 256
    chunks = int(owner[-1]) + 1

    def ranges(values):  # per-chunk min / max and each value's fraction of its chunk's range
        low = np.array([values[owner == c].min() for c in range(chunks)], np.float32)
        high = np.array([values[owner == c].max() for c in range(chunks)], np.float32)
        span = np.where(high > low, high - low, 1)
        return low, high, (values - low[owner]) / span[owner]

    def unorm(t, bits):
        return np.clip(np.floor(t * ((1 << bits) - 1) + 0.5), 0, (1 << bits) - 1).astype(np.uint32)

    chunk_cols, packed = {}, {}
    for name, values in (("position", g.means), ("scale", _log3(g))):
        words = np.zeros(n, np.uint32)
        for axis, (bits, shift) in enumerate(((11, 21), (10, 11), (11, 0))):
            low, high, t = ranges(values[:, axis])
            key = "xyz"[axis] if name == "position" else f"scale_{'xyz'[axis]}"
            chunk_cols[f"min_{key}"], chunk_cols[f"max_{key}"] = low, high
            words |= unorm(t, bits) << shift
        packed[f"packed_{name}"] = words
    rgb = 0.5 + SH_C0 * g.sh_dc.astype(np.float64)
    colour = unorm(0.5 + 0.5 * np.tanh(0.5 * g.opacity_logits.astype(np.float64)), 8)
    for axis, shift in enumerate((24, 16, 8)):
        t = rgb[:, axis]
        if chunk_colours:
            low, high, t = ranges(rgb[:, axis])
            chunk_cols[f"min_{'rgb'[axis]}"], chunk_cols[f"max_{'rgb'[axis]}"] = low, high
        colour |= unorm(t, 8) << shift
    packed["packed_color"] = colour
    q = _unit(g.quats)
    largest = np.argmax(np.abs(q), axis=1)
    q *= np.where(q[np.arange(n), largest] < 0, -1, 1)[:, None]
    words = largest.astype(np.uint32)
    for i in range(4):
        words = np.where(largest != i, words << 10 | unorm(q[:, i] * np.sqrt(0.5) + 0.5, 10), words)
    packed["packed_rotation"] = words
    order = ["min_x", "min_y", "min_z", "max_x", "max_y", "max_z"]
    order += [f"{s}_scale_{a}" for s in ("min", "max") for a in "xyz"]
    order += [f"{s}_{c}" for s in ("min", "max") for c in "rgb"] if chunk_colours else []
    header = ["ply", "format binary_little_endian 1.0", f"element chunk {chunks}"]
    header += [f"property float {name}" for name in order]
    header += [f"element vertex {n}"] + [f"property uint {p}" for p in packed]
    body = np.stack([chunk_cols[k] for k in order], axis=1).astype("<f4").tobytes()
    body += np.stack(list(packed.values()), axis=1).astype("<u4").tobytes()
    if sh:
        k = g.sh_rest.shape[1]
        rest = g.sh_rest.transpose(0, 2, 1).reshape(n, 3 * k)
        header += [f"element sh {n}"] + [f"property uchar f_rest_{i}" for i in range(3 * k)]
        body += np.clip(np.floor((rest / 8 + 0.5) * 256), 0, 255).astype(np.uint8).tobytes()
    return ("\n".join([*header, "end_header"]) + "\n").encode() + body


def assert_compressed_quantised(h: GaussianMap, g: GaussianMap, sh_tolerance: float) -> None:
    """`h` is `g` within the compressed PLY's steps (over ranges no wider than the map's)."""
    for ours, theirs in ((h.means, g.means), (_log3(h), _log3(g))):
        extent = theirs.max(axis=0) - theirs.min(axis=0)
        assert np.all(
            np.abs(ours - theirs) <= extent * np.array([1 / 2047, 1 / 1023, 1 / 2047]) / 2 + 1e-5
        )
    colour_extent = (g.sh_dc.max(axis=0) - g.sh_dc.min(axis=0)).max()
    assert np.abs(h.sh_dc - g.sh_dc).max() <= colour_extent / 255 / 2 + 1e-4
    alpha = 0.5 + 0.5 * np.tanh(0.5 * g.opacity_logits.astype(np.float64))
    assert np.abs(h.opacities() - alpha).max() <= 0.5 / 255 + 1e-5
    dot = np.abs(np.sum(_unit(h.quats) * _unit(g.quats), axis=1))
    assert (1 - dot).max() <= 1e-5
    if g.sh_degree:
        assert np.abs(h.sh_rest - g.sh_rest).max() <= sh_tolerance


@pytest.mark.parametrize(("degree", "chunk_colours"), [(0, True), (1, False), (3, True)])
def test_compressed_ply_is_read_whatever_its_name(tmp_path, degree, chunk_colours):
    g = random_map(700, seed=6, isotropic=False, sh_degree=degree)  # 3 chunks, the last partial
    path = tmp_path / "scene.ply"  # not called .compressed.ply: found by its header
    path.write_bytes(_compressed_ply(g, sh=degree > 0, chunk_colours=chunk_colours))
    h = read_ply(path)
    assert_compressed_quantised(h, g, sh_tolerance=8 / 256)


def test_malformed_compressed_ply_files_are_refused_with_one_line(tmp_path):
    path = tmp_path / "c.compressed.ply"
    good = _compressed_ply(random_map(700, seed=1, sh_degree=1), sh=True)
    for text, match in [
        (good.replace(b"uint packed_scale", b"float packed_scale"), "packed_scale must be uint32"),
        (good[:-5], "truncated"),
        (good.replace(b"element chunk 3", b"element chunk 2"), "bytes after the elements"),
    ]:
        path.write_bytes(text)
        with pytest.raises(PlyFormatError, match=match) as info:
            read_map_file(path)
        assert "\n" not in str(info.value) and str(path) in str(info.value)


def test_compressed_elements_that_disagree_are_refused():
    path = Path("c.ply")
    path_bytes = _compressed_ply(random_map(700, seed=1, sh_degree=1), sh=True)
    elements = _elements(path_bytes)
    with pytest.raises(PlyFormatError, match=r"c\.ply: 2 chunk rows for 700 vertices"):
        decompress({**elements, "chunk": elements["chunk"][:2]}, str(path))
    with pytest.raises(PlyFormatError, match="'sh' has 699 rows, not 700"):
        decompress({**elements, "sh": elements["sh"][:699]}, str(path))
    without = elements["chunk"][[n for n in elements["chunk"].dtype.names if n != "min_scale_y"]]
    with pytest.raises(PlyFormatError, match="'chunk' element lacks min_scale_y"):
        decompress({**elements, "chunk": without}, str(path))
    with pytest.raises(PlyFormatError, match="without a 'vertex' element"):
        decompress({"chunk": elements["chunk"]}, str(path))


def _elements(text: bytes) -> dict[str, np.ndarray]:
    """The element records of a little-endian PLY of float, uint and uchar properties."""
    header, body = text.split(b"end_header\n")
    types = {"float": "<f4", "uint": "<u4", "uchar": "u1"}
    layout: list[tuple[str, int, list[tuple[str, str]]]] = []
    for line in header.decode().splitlines():
        words = line.split()
        if words[0] == "element":
            layout.append((words[1], int(words[2]), []))
        elif words[0] == "property":
            layout[-1][2].append((words[2], types[words[1]]))
    out, offset = {}, 0
    for name, count, props in layout:
        out[name] = np.frombuffer(body, np.dtype(props), count, offset)
        offset += count * np.dtype(props).itemsize
    return out


# ------------------------------------------------------------------ commands


def test_export_spz_and_import_it_and_a_compressed_ply(tmp_path):
    g = random_map(400, seed=8, isotropic=False, sh_degree=1)
    log = tmp_path / "run.mcap"
    with LogWriter(log, LogMetadata(command="test")) as out:
        out.write_gaussians(g, 0)
    runner = CliRunner()
    r = runner.invoke(cli, ["export-ply", str(log), "-o", str(tmp_path / "map.spz")])
    assert r.exit_code == 0, r.output
    assert (tmp_path / "map.spz").read_bytes()[:4] == b"NGSP"
    r = runner.invoke(
        cli, ["import-ply", str(tmp_path / "map.spz"), "-o", str(tmp_path / "b.mcap")]
    )
    assert r.exit_code == 0 and "400 Gaussians" in r.output
    assert_spz_quantised(read_map(tmp_path / "b.mcap"), g.select(spz.storage_order(g.means)))
    (tmp_path / "c.compressed.ply").write_bytes(_compressed_ply(g, sh=True))
    r = runner.invoke(
        cli, ["import-ply", str(tmp_path / "c.compressed.ply"), "-o", str(tmp_path / "c.mcap")]
    )
    assert r.exit_code == 0, r.output
    assert_compressed_quantised(read_map(tmp_path / "c.mcap"), g, sh_tolerance=8 / 256)
    (tmp_path / "bad.spz").write_bytes(b"NGSP" + bytes(40))
    r = runner.invoke(
        cli, ["import-ply", str(tmp_path / "bad.spz"), "-o", str(tmp_path / "d.mcap")]
    )
    assert r.exit_code == 1 and r.output.count("\n") == 1 and "bad.spz: " in r.output
    assert not (tmp_path / "d.mcap").exists()


def test_a_log_command_given_an_spz_says_how_to_import_it(tmp_path):
    path = tmp_path / "map.mcap"
    path.write_bytes(spz.encode_bytes(random_map(10)))
    r = CliRunner().invoke(cli, ["info", str(path)])
    assert r.exit_code == 1 and "`gsc import-ply` makes a log of it" in r.output


# ------------------------------------------------------------------ splat-transform


needs_splat_transform = pytest.mark.skipif(
    shutil.which("node") is None or not TOOL.exists(),
    reason="node or tests/js/node_modules (make js-deps) missing: splat-transform cannot run",
)


def _convert(src: Path, dst: Path) -> None:
    subprocess.run(
        [str(TOOL), "-w", str(src), str(dst)], check=True, capture_output=True, timeout=120
    )


def _matched(h: GaussianMap, g: GaussianMap, tolerance: float) -> GaussianMap:
    """`h` reordered to `g`'s order by nearest centres (converters may reorder Gaussians)."""
    dist, idx = cKDTree(h.means).query(g.means)
    assert dist.max() <= tolerance and len(np.unique(idx)) == len(g)
    return h.select(idx)


@needs_splat_transform
@pytest.mark.parametrize("isotropic", [True, False])
def test_splat_transform_reads_our_spz_as_we_do(tmp_path, isotropic):
    g = random_map(1500, seed=9, isotropic=isotropic, sh_degree=1)
    g.opacity_logits[:4] = [-30, 30, -9, 9]  # the 8-bit codes 0 and 255
    spz.write_spz(g, tmp_path / "ours.spz")
    _convert(tmp_path / "ours.spz", tmp_path / "theirs.ply")
    theirs = _matched(read_ply(tmp_path / "theirs.ply"), g, 2.0**-12)
    ours = _matched(spz.read_spz(tmp_path / "ours.spz"), g, 2.0**-12)
    np.testing.assert_array_equal(theirs.means, ours.means)
    np.testing.assert_allclose(_log3(theirs), _log3(ours), atol=1e-6)
    np.testing.assert_allclose(theirs.opacities(), ours.opacities(), atol=0.26 / 255)  # edges
    np.testing.assert_allclose(theirs.sh_dc, ours.sh_dc, atol=1e-5)
    np.testing.assert_allclose(theirs.quats, ours.quats, atol=1e-6)
    np.testing.assert_allclose(theirs.sh_rest, ours.sh_rest, atol=1e-6)
    assert_spz_quantised(theirs, g)


@needs_splat_transform
@pytest.mark.parametrize("isotropic", [True, False])
def test_splat_transforms_spz_of_our_ply_imports_within_quantisation(tmp_path, isotropic):
    g = random_map(1500, seed=10, isotropic=isotropic, sh_degree=1)
    write_ply(g, tmp_path / "map.ply", importance=False)
    _convert(tmp_path / "map.ply", tmp_path / "theirs.spz")
    h = _matched(read_map_file(tmp_path / "theirs.spz"), g, 2.0**-12)
    assert_spz_quantised(h, g)


@needs_splat_transform
def test_splat_transforms_compressed_ply_of_our_ply_imports_within_quantisation(tmp_path):
    g = random_map(1500, seed=11, isotropic=False, sh_degree=1)
    write_ply(g, tmp_path / "map.ply", importance=False)
    _convert(tmp_path / "map.ply", tmp_path / "theirs.compressed.ply")
    h = _matched(read_map_file(tmp_path / "theirs.compressed.ply"), g, 4 / 1023)
    assert_compressed_quantised(h, g, sh_tolerance=1 / 60)  # 8 bits over [-4, 4]


@pytest.mark.parametrize("version", [3, 4])
def test_a_count_of_zero_is_refused(version):
    data = spz.encode_bytes(random_map(3, seed=1), version=version)
    raw = _with_count(data, version, 0)
    _one_line_refusal(raw if version == 3 else raw[:32], "declares no Gaussians")
