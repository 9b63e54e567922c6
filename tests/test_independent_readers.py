"""Independent readers accept our files: the official TypeScript MCAP reader and splat-transform.

The node packages are installed by `make js-deps` (part of `make test` and CI) into tests/js.
These tests skip only when node / npm are not installed at all.
"""

import json
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

from gscompress.camera import Intrinsics
from gscompress.gaussians import random_map
from gscompress.io.mcap_log import LogMetadata, LogWriter
from gscompress.io.ply import read_ply, write_ply

JS = Path(__file__).parent / "js"

pytestmark = pytest.mark.skipif(
    shutil.which("node") is None or shutil.which("npm") is None,
    reason="node/npm are not installed: the independent JavaScript readers cannot run",
)


def node_modules() -> Path:
    modules = JS / "node_modules"
    assert modules.is_dir(), "tests/js/node_modules is missing: run `make js-deps`"
    return modules


def test_typescript_mcap_reader_lists_our_channels_and_counts(tmp_path):
    node_modules()
    path = tmp_path / "run.mcap"
    with LogWriter(path, LogMetadata(command="test")) as log:
        log.write_calibration(Intrinsics(50, 50, 16, 12, 32, 24), 0)
        for i in range(7):
            log.write_pose(np.eye(4), i)
            log.write_pose(np.eye(4), i, ground_truth=True)
            log.write_stats({"frame": i, "gaussians": 10}, i)
        log.write_gaussians(random_map(5000, seed=1), 3)  # larger than one chunk
        log.write_gaussians(random_map(1234, seed=2, sh_degree=1), 8)
    out = subprocess.run(
        ["node", str(JS / "read_mcap.mjs"), str(path)],
        capture_output=True,
        text=True,
        check=True,
        timeout=120,
    )
    result = json.loads(out.stdout)
    assert result["profile"] == "gscompress"
    assert result["metadata"] == ["gscompress"]
    expected = {
        "/gaussians": 2,
        "/camera/pose": 7,
        "/camera/pose_gt": 7,
        "/tf": 7,
        "/slam/stats": 7,
        "/camera/calibration": 1,
    }
    assert {t: c["messages"] for t, c in result["channels"].items()} == expected
    assert result["counted"] == expected
    assert result["channels"]["/gaussians"]["schema"] == "foxglove.PointCloud"
    assert result["channels"]["/slam/stats"]["encoding"] == "json"
    g = result["gaussians"]
    assert g["points"] == 1234 and g["point_stride"] == 4 * len(g["fields"])
    assert g["fields"][:3] == ["x", "y", "z"] and "importance" in g["fields"]


def _quat_sign_fixed(q):
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    return q * np.where(q[:, :1] < 0, -1.0, 1.0)


@pytest.mark.parametrize("importance", [True, False])
def test_splat_transform_converts_our_ply_to_spz_and_back(tmp_path, importance):
    tool = node_modules() / ".bin" / "splat-transform"
    g = random_map(2000, seed=5, isotropic=False, sh_degree=1)
    src = write_ply(g, tmp_path / "map.ply", importance=importance)
    spz, back = tmp_path / "map.spz", tmp_path / "back.ply"
    for a, b in ((src, spz), (spz, back)):
        subprocess.run([str(tool), str(a), str(b)], check=True, capture_output=True, timeout=120)
    h = read_ply(back)
    assert len(h) == len(g)
    # converters may reorder Gaussians: match each of ours to its nearest converted centre
    dist, idx = cKDTree(h.means).query(g.means)
    assert dist.max() < 2e-3  # spz stores positions as 24-bit fixed point
    assert len(np.unique(idx)) == len(g)
    h = h.select(idx)
    np.testing.assert_allclose(h.log_scales, g.log_scales, atol=1 / 16 + 1e-3)  # 8-bit log scale
    np.testing.assert_allclose(h.opacities(), g.opacities(), atol=2 / 255)
    np.testing.assert_allclose(_quat_sign_fixed(h.quats), _quat_sign_fixed(g.quats), atol=0.03)
    np.testing.assert_allclose(h.sh_dc, g.sh_dc, atol=0.03)
    np.testing.assert_allclose(h.sh_rest, g.sh_rest, atol=0.1)


def test_splat_transform_rejects_a_broken_ply(tmp_path):
    tool = node_modules() / ".bin" / "splat-transform"
    src = write_ply(random_map(100), tmp_path / "map.ply")
    src.write_bytes(src.read_bytes()[:-1000])
    r = subprocess.run(
        [str(tool), str(src), str(tmp_path / "x.spz")], capture_output=True, timeout=120
    )
    assert r.returncode != 0  # the check above would be meaningless if .spz accepted anything
