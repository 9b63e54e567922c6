"""3DGS PLY: exact round trips, plyfile agreement, other tools' layouts, hostile files."""

import numpy as np
import pytest
from plyfile import PlyData, PlyElement

from gscompress.errors import PlyFormatError
from gscompress.gaussians import random_map
from gscompress.io.ply import read_ply, write_ply


@pytest.mark.parametrize("isotropic", [True, False])
@pytest.mark.parametrize("sh_degree", [0, 3])
def test_round_trip_is_bit_identical(tmp_path, isotropic, sh_degree):
    g = random_map(200, seed=7, isotropic=isotropic, sh_degree=sh_degree)
    path = write_ply(g, tmp_path / "m.ply")
    assert read_ply(path).equals(g)


def test_plyfile_reads_ours_with_inria_names_and_values(tmp_path):
    g = random_map(100, seed=1, isotropic=False, sh_degree=1)
    path = write_ply(g, tmp_path / "m.ply")
    v = PlyData.read(str(path))["vertex"]
    names = [p.name for p in v.properties]
    assert names[:9] == ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    assert names[9:18] == [f"f_rest_{i}" for i in range(9)]
    assert names[18:26] == [
        "opacity",
        "scale_0",
        "scale_1",
        "scale_2",
        "rot_0",
        "rot_1",
        "rot_2",
        "rot_3",
    ]
    assert names[26:] == ["importance", "importance_sum", "importance_weight", "alpha_t_sum", "id"]
    np.testing.assert_array_equal(v["x"], g.means[:, 0])
    np.testing.assert_array_equal(v["rot_0"], g.quats[:, 0])
    np.testing.assert_array_equal(v["importance"], g.importance)
    # f_rest is channel-major: f_rest_{c*K + k} is coefficient k of colour channel c
    np.testing.assert_array_equal(v["f_rest_4"], g.sh_rest[:, 1, 1])
    assert v["id"].dtype == np.uint32


def test_plain_inria_export_has_no_extras(tmp_path):
    g = random_map(10)
    path = write_ply(g, tmp_path / "m.ply", importance=False)
    names = [p.name for p in PlyData.read(str(path))["vertex"].properties]
    assert "importance" not in names and "id" not in names and len(names) == 17
    back = read_ply(path)
    assert not back.has_importance and back.ids.tolist() == list(range(10))


def _write_foreign(path, names, n=20, seed=0, byte_order="<", extra_element=False):
    rng = np.random.default_rng(seed)
    data = np.zeros(n, dtype=[(name, "f4") for name in names])
    for name in names:
        data[name] = rng.normal(size=n)
    elements = [PlyElement.describe(data, "vertex")]
    if extra_element:
        faces = np.zeros(2, dtype=[("a", "i4")])
        elements.insert(0, PlyElement.describe(faces, "meta"))
    PlyData(elements, byte_order=byte_order).write(str(path))
    return data


BASE = [
    "x",
    "y",
    "z",
    "f_dc_0",
    "f_dc_1",
    "f_dc_2",
    "opacity",
    "scale_0",
    "scale_1",
    "scale_2",
    "rot_0",
    "rot_1",
    "rot_2",
    "rot_3",
]


def test_reads_inria_layout_with_degree_3(tmp_path):
    names = [
        "x",
        "y",
        "z",
        "nx",
        "ny",
        "nz",
        "f_dc_0",
        "f_dc_1",
        "f_dc_2",
        *[f"f_rest_{i}" for i in range(45)],
        *BASE[6:],
    ]
    data = _write_foreign(tmp_path / "inria.ply", names)
    g = read_ply(tmp_path / "inria.ply")
    assert g.sh_degree == 3 and not g.isotropic and not g.has_importance
    np.testing.assert_array_equal(g.sh_rest[:, 14, 2], data["f_rest_44"])
    np.testing.assert_array_equal(g.sh_rest[:, 0, 1], data["f_rest_15"])
    np.testing.assert_array_equal(g.log_scales[:, 2], data["scale_2"])


def test_reads_gsplat_layout_without_normals_big_endian_and_other_elements(tmp_path):
    data = _write_foreign(tmp_path / "g.ply", BASE, byte_order=">", extra_element=True)
    g = read_ply(tmp_path / "g.ply")
    np.testing.assert_array_equal(g.means[:, 1], data["y"])
    np.testing.assert_array_equal(g.quats[:, 3], data["rot_3"])


def test_foreign_importance_becomes_the_score(tmp_path):
    path = tmp_path / "s.ply"
    data = _write_foreign(path, [*BASE, "importance"])
    data["importance"] = np.abs(data["importance"])
    PlyData([PlyElement.describe(data, "vertex")]).write(str(path))
    g = read_ply(path)
    assert g.has_importance
    np.testing.assert_array_equal(g.importance, data["importance"])
    data["importance"][0] = -1.0
    PlyData([PlyElement.describe(data, "vertex")]).write(str(path))
    with pytest.raises(PlyFormatError, match="importance_sum has negative"):
        read_ply(path)


HEAD = b"ply\nformat binary_little_endian 1.0\n"


@pytest.mark.parametrize(
    "content, message",
    [
        (b"hello world", "not a PLY"),
        (
            b"ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\nend_header\n",
            "unsupported PLY format",
        ),
        (
            HEAD + b"element vertex 2\nproperty list uchar int i\nend_header\n",
            "list properties",
        ),
        (
            b"ply\nformat binary_little_endian 1.0\nelement face 0\nproperty float a\nend_header\n",
            "no vertex element",
        ),
        (
            HEAD + b"element vertex 1000000000\nproperty float x\nend_header\n",
            "truncated",
        ),
    ],
)
def test_malformed_files_are_refused(tmp_path, content, message):
    path = tmp_path / "bad.ply"
    path.write_bytes(content)
    with pytest.raises(PlyFormatError, match=message):
        read_ply(path)


def test_missing_required_properties_are_named(tmp_path):
    _write_foreign(tmp_path / "p.ply", ["x", "y", "z", "red", "green", "blue"])
    with pytest.raises(PlyFormatError, match="missing vertex properties scale_0"):
        read_ply(tmp_path / "p.ply")


def test_truncated_data_is_refused(tmp_path):
    path = write_ply(random_map(100), tmp_path / "m.ply")
    path.write_bytes(path.read_bytes()[:-10])
    with pytest.raises(PlyFormatError, match="truncated"):
        read_ply(path)


def test_bytes_beyond_the_declared_elements_and_a_wrong_magic_are_refused(tmp_path):
    path = write_ply(random_map(100), tmp_path / "m.ply")
    data = path.read_bytes()
    path.write_bytes(data + b"\0" * 7)
    with pytest.raises(PlyFormatError, match="7 bytes after the elements the header declares"):
        read_ply(path)
    path.write_bytes(data + b"\n")  # a line end left by a writer is not data
    assert len(read_ply(path)) == 100
    path.write_bytes(data.replace(b"element vertex 100", b"element vertex 10", 1))
    with pytest.raises(PlyFormatError, match="a wrong vertex count"):
        read_ply(path)
    path.write_bytes(b"plyx" + data[3:])
    with pytest.raises(PlyFormatError, match="not a PLY file"):
        read_ply(path)


@pytest.mark.parametrize("value", [-1.0, 1.5, 2.0**32, np.nan, 1e20])
def test_an_id_that_is_not_a_uint32_is_refused(tmp_path, value):
    names = [*BASE, "id"]
    data = np.zeros(4, dtype=[(name, "f8" if name == "id" else "f4") for name in names])
    data["rot_0"], data["id"] = 1.0, [0, 1, 2, 3]
    PlyData([PlyElement.describe(data, "vertex")]).write(str(tmp_path / "ok.ply"))
    assert read_ply(tmp_path / "ok.ply").ids.tolist() == [0, 1, 2, 3]  # whole doubles are read
    data["id"][2] = value
    PlyData([PlyElement.describe(data, "vertex")]).write(str(tmp_path / "bad.ply"))
    with pytest.raises(PlyFormatError, match=r"bad\.ply: id has values that are not whole"):
        read_ply(tmp_path / "bad.ply")


def test_non_finite_values_are_refused(tmp_path):
    g = random_map(10)
    g.log_scales[0] = np.nan
    path = write_ply(g, tmp_path / "m.ply")
    with pytest.raises(PlyFormatError, match=r"m\.ply: .*non-finite"):  # names the file
        read_ply(path)
