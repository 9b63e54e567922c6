"""SOG (PlayCanvas) maps read within their quantisation; hostile bundles refused with one line;
splat-transform's SOG of our PLY cross-checked (skipped without node)."""

import io
import shutil
import zipfile

import numpy as np
import pytest
from conftest import sog_bundle
from scipy.spatial import cKDTree

from gscompress.errors import MissingDependencyError, OutputError, SogFormatError
from gscompress.gaussians import GaussianMap, random_map
from gscompress.io.map_files import read_map_file
from gscompress.io.sog import SPLAT_TRANSFORM_ENV, read_sog, splat_transform, write_sog


def _unit(q: np.ndarray) -> np.ndarray:
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def assert_sog_close(h: GaussianMap, g: GaussianMap, codebook_error: float) -> None:
    """`h` is `g` within SOG's steps: 16-bit log-space positions, 8-bit rotation components and
    opacity, codebook entries within `codebook_error` for scales and colour."""
    reach = np.log1p(np.abs(g.means.astype(np.float64))).max()
    assert np.abs(h.means - g.means).max() <= 2 * reach / 65535 * np.exp(reach) + 1e-6
    dot = np.abs(np.sum(_unit(h.quats) * _unit(g.quats), axis=1))
    assert (1 - dot).max() <= 1e-3
    assert np.abs(h.opacities() - g.opacities()).max() <= 1 / 255 + 1e-6
    visible = h.opacities() > 1 / 255  # (SOG drops the colour of a fully transparent pixel)
    log3 = (np.broadcast_to(m.log_scales, (len(m), 3)) for m in (h, g))
    assert np.abs(np.subtract(*log3)).max() <= codebook_error
    assert np.abs(h.sh_dc - g.sh_dc)[visible].max() <= codebook_error


def test_a_sog_bundle_reads_within_its_quantisation(tmp_path):
    g = random_map(900, seed=2, isotropic=False)
    (tmp_path / "m.sog").write_bytes(sog_bundle(g))
    h = read_map_file(tmp_path / "m.sog")
    colour_step = (g.sh_dc.max() - g.sh_dc.min()) / 255
    assert_sog_close(h, g, codebook_error=colour_step / 2 + 1e-5)
    assert np.array_equal(h.ids, np.arange(900)) and h.sh_degree == 0


def test_an_unbundled_sog_reads_from_its_meta_json(tmp_path):
    g = random_map(100, seed=3)
    with zipfile.ZipFile(io.BytesIO(sog_bundle(g))) as bundle:
        bundle.extractall(tmp_path)
    h = read_map_file(tmp_path / "meta.json")
    assert len(h) == 100 and h.isotropic


@pytest.mark.parametrize(
    ("edit", "match"),
    [
        (lambda m: m.update(version=1), "SOG meta version 1 is not read"),
        (lambda m: m.pop("version"), r"version '1 \(none given\)' is not read"),
        (lambda m: m.update(count=2**40), "count must be a whole number"),
        (lambda m: m.update(count=5000), "is 32x29, not sized for 5000 Gaussians"),
        (lambda m: m["scales"].update(codebook=[0.0] * 255), "scales.codebook must be 256"),
        (lambda m: m["means"].update(mins=[0, float("nan"), 0]), "means.mins must be 3 finite"),
        (lambda m: m["quats"].update(files=["none.webp"]), "the bundle has no none.webp"),
        (lambda m: m["sh0"].update(files=[]), r"sh0.files must name 1 image"),
    ],
)
def test_hostile_sog_bundles_are_refused_with_one_line(tmp_path, edit, match):
    path = tmp_path / "m.sog"
    path.write_bytes(sog_bundle(random_map(900, seed=1), edit))
    with pytest.raises(SogFormatError, match=match) as info:
        read_map_file(path)
    assert "\n" not in str(info.value) and str(info.value).startswith(str(path))


def test_a_broken_zip_is_refused(tmp_path):
    path = tmp_path / "m.sog"
    path.write_bytes(sog_bundle(random_map(50))[:-40])
    with pytest.raises(SogFormatError, match=r"m\.sog: not a SOG bundle \(not a readable zip"):
        read_sog(path)


@pytest.mark.skipif(
    splat_transform() is None,
    reason="node or tests/js/node_modules (make js-deps) missing: splat-transform cannot run",
)
def test_splat_transforms_sog_of_our_map_reads_close_to_it(tmp_path):
    g = random_map(1500, seed=12, isotropic=False, sh_degree=1)
    size = write_sog(g, tmp_path / "map.sog")  # (splat-transform, from our PLY)
    assert size == (tmp_path / "map.sog").stat().st_size and list(tmp_path.iterdir()) == [
        tmp_path / "map.sog"
    ]
    h = read_map_file(tmp_path / "map.sog")
    dist, idx = cKDTree(h.means).query(g.means)
    assert dist.max() < 1e-3 and len(np.unique(idx)) == len(g)
    h = h.select(idx)
    assert_sog_close(h, g, codebook_error=0.05)  # 256 clustered entries
    assert np.abs(h.sh_rest - g.sh_rest).mean() < 0.05  # a 1024-set palette for 1500 Gaussians


def test_writing_sog_without_splat_transform_names_the_fix(tmp_path, monkeypatch):
    monkeypatch.setenv(SPLAT_TRANSFORM_ENV, str(tmp_path / "no-such-tool"))
    assert splat_transform() is None
    with pytest.raises(MissingDependencyError, match="make js-deps"):
        write_sog(random_map(10), tmp_path / "map.sog")
    assert list(tmp_path.iterdir()) == []


def test_a_failing_splat_transform_is_one_line_and_no_file(tmp_path, monkeypatch):
    if shutil.which("node") is None:
        pytest.skip("node missing: splat_transform() needs it to name any command")
    tool = tmp_path / "broken"
    tool.write_text("#!/bin/sh\necho 'Error: no GPU, no luck' >&2\nexit 3\n")
    tool.chmod(0o755)
    monkeypatch.setenv(SPLAT_TRANSFORM_ENV, str(tool))
    with pytest.raises(OutputError, match=r"map\.sog: splat-transform failed: Error: no GPU"):
        write_sog(random_map(10), tmp_path / "map.sog")
    assert not (tmp_path / "map.sog").exists()


def _member_edited(bundle: bytes, name: str, offset: int, value: int) -> bytes:
    """`bundle` with a 2-byte field of `name`'s central directory entry set to `value`
    (offset 8: the flag bits, 10: the compression method)."""
    data = bytearray(bundle)
    at = data.find(b"PK\x01\x02")
    while at >= 0:
        length = int.from_bytes(data[at + 28 : at + 30], "little")
        if data[at + 46 : at + 46 + length].decode() == name:
            data[at + offset : at + offset + 2] = value.to_bytes(2, "little")
            return bytes(data)
        at = data.find(b"PK\x01\x02", at + 46)
    raise AssertionError(f"no {name} in the bundle")


@pytest.mark.parametrize(
    ("offset", "value"), [(10, 99), (10, 14), (8, 1)], ids=["method-99", "lzma", "encrypted"]
)
def test_a_member_in_a_zip_method_sog_writers_do_not_use_is_refused(tmp_path, offset, value):
    """Found by `make fuzz` (sog target): an unknown method raised NotImplementedError from
    zipfile, an encrypted member RuntimeError."""
    g = random_map(100, seed=3)
    quats = "q.webp"  # (conftest's sog_bundle names the quaternions' image so)
    path = tmp_path / "m.sog"
    path.write_bytes(_member_edited(sog_bundle(g), quats, offset, value))
    with pytest.raises(SogFormatError, match=f"{quats} is encrypted or compressed by zip method"):
        read_sog(path)
