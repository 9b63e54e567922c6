"""Sequence readers: the real sequences in ../shared/data, frame subsets, resizing, and broken
sequences built in a temporary folder."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from gscompress.camera import Intrinsics
from gscompress.datasets import open_sequence, parse_frames, write_tum_sequence
from gscompress.datasets.synthetic import synthetic_sequence
from gscompress.datasets.tum import associate, freiburg_intrinsics
from gscompress.errors import DatasetError, InputError

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"

# folder -> (frames, intrinsics fx fy cx cy w h, depth range (m) of frame 0, gt poses)
REAL = {
    "tsdffusion_tabletop_box": (50, (615.1952, 615.1953, 298.4427, 247.5192, 640, 480), 50),
    "3dmatch_office_frag1": (50, (570.3422, 570.3422, 320.0, 240.0, 640, 480), 50),
    "icl_livingroom1_clean_o3d211": (211, (525.0, 525.0, 319.5, 239.5, 640, 480), 211),
    "replica_office0_nvblox4": (4, (600.0, 600.0, 599.5, 339.5, 1200, 680), 4),
}


@pytest.mark.data
@pytest.mark.parametrize("name", sorted(REAL))
def test_real_sequences_open(name: str) -> None:
    if not (DATA / name).is_dir():
        pytest.skip(f"{DATA / name} not present")
    n, k, n_gt = REAL[name]
    seq = open_sequence(DATA / name)
    assert len(seq) == n
    got = seq.intrinsics
    np.testing.assert_allclose([got.fx, got.fy, got.cx, got.cy], k[:4], atol=1e-3)
    assert (got.width, got.height) == k[4:]
    assert seq.has_ground_truth and len(seq.ground_truth()[0]) == n_gt
    for i in (0, n - 1):
        f = seq.frame(i)
        assert f.color.shape == (k[5], k[4], 3) and f.color.dtype == np.float32
        assert f.depth.shape == (k[5], k[4]) and f.depth.dtype == np.float32
        assert 0.0 <= f.color.min() and f.color.max() <= 1.0 and f.color.max() > 0.5
        valid = f.depth[f.depth > 0]
        assert valid.size > 0.2 * f.depth.size  # the SR300 tabletop frames are ~1/3 valid
        # indoor scenes: metres, not millimetres or PNG units
        assert 0.05 < valid.min() and valid.max() < 10.0
        assert f.T_world_cam is not None and f.T_world_cam.shape == (4, 4)
        np.testing.assert_allclose(
            f.T_world_cam[:3, :3] @ f.T_world_cam[:3, :3].T, np.eye(3), atol=1e-6
        )
    stamps = seq.timestamps
    assert np.all(np.diff(stamps) > 0)


@pytest.mark.data
def test_replica_sample_native_layout_and_scale() -> None:
    root = DATA / "replica_office0_nvblox4"
    if not root.is_dir():
        pytest.skip("Replica sample not present")
    seq = open_sequence(root / "office0")  # the scene folder itself; cam_params.json in parent
    assert len(seq) == 4 and seq.depth_scale == 6553.5
    raw = np.asarray(Image.open(root / "office0" / "results" / "depth000002.png"))
    np.testing.assert_allclose(seq.frame(2).depth, raw / 6553.5, rtol=1e-6)
    traj = np.loadtxt(root / "office0" / "traj.txt")
    np.testing.assert_allclose(seq.frame(3).T_world_cam, traj[3].reshape(4, 4))
    small = open_sequence(root, size=(300, 170), frames="odd")
    assert list(small.indices) == [1, 3]
    f = small.frame(0)
    assert f.index == 1 and f.color.shape == (170, 300, 3) and f.depth.shape == (170, 300)
    assert small.intrinsics == Intrinsics(150.0, 150.0, 149.5, 84.5, 300, 170)


def test_parse_frames() -> None:
    assert list(parse_frames("all").apply(5)) == [0, 1, 2, 3, 4]
    assert list(parse_frames("odd").apply(6)) == [1, 3, 5]  # agent A
    assert list(parse_frames("even").apply(6)) == [0, 2, 4]  # agent B
    assert list(parse_frames("2:8:3").apply(10)) == [2, 5]
    assert list(parse_frames("::4").apply(10)) == [0, 4, 8]
    assert list(parse_frames("-3:").apply(10)) == [7, 8, 9]
    assert list(parse_frames(" 5: ").apply(7)) == [5, 6]
    assert list(parse_frames("-2:3").apply(4)) == [2]  # mixed signs depend on the length
    for bad in ("", "first", "1:2:0", "1:2:-1", "a:b", "1:2:3:4", "-:", "5:2", "3:3", "-2:-5"):
        with pytest.raises(InputError):
            parse_frames(bad)
    for backwards in ("1:2:0", "1:2:-1", "0:9:-"):  # said as such, not as a malformed subset
        with pytest.raises(InputError, match="STEP must be a positive integer"):
            parse_frames(backwards)


def test_associate_follows_tum_rule() -> None:
    rgb = np.array([0.0, 0.033, 0.066, 0.5])
    depth = np.array([0.001, 0.03, 0.031, 0.07, 0.9])
    # greedy by smallest difference, one to one, < 0.02 s; 0.5 has no partner
    assert associate(rgb, depth, 0.02) == [(0, 0), (1, 2), (2, 3)]


def test_freiburg_names() -> None:
    assert freiburg_intrinsics("rgbd_dataset_freiburg1_desk").fx == 517.3
    assert freiburg_intrinsics("fr3_office").fy == 539.2
    assert freiburg_intrinsics("3dmatch_office_frag1") is None


# ---------------------------------------------------------------------------------------------
# Sequences written in tmp_path


@pytest.fixture
def tum_dir(tmp_path: Path) -> Path:
    """A 6-frame 40x30 synthetic sequence written in TUM layout."""
    out = tmp_path / "seq"
    write_tum_sequence(synthetic_sequence(6, (40, 30), seed=2), out)
    return out


def test_written_sequence_round_trips(tum_dir: Path) -> None:
    mem = synthetic_sequence(6, (40, 30), seed=2)
    seq = open_sequence(tum_dir)
    assert len(seq) == 6 and seq.intrinsics == mem.intrinsics and seq.has_ground_truth
    for i in (0, 5):
        a, b = seq.frame(i), mem.frame(i)
        assert np.abs(a.color - b.color).max() <= 0.5 / 255 + 1e-6
        assert np.abs(a.depth - b.depth).max() <= 0.5 / 5000 + 1e-6
        np.testing.assert_allclose(a.T_world_cam, b.T_world_cam, atol=1e-9)
        assert a.timestamp == pytest.approx(b.timestamp, abs=1e-6)


def test_subsets_and_resize(tum_dir: Path) -> None:
    seq = open_sequence(tum_dir, size=(20, 15), frames="1:6:2")
    assert list(seq.indices) == [1, 3, 5] and len(seq) == 3
    f = seq.frame(1)
    assert f.index == 3 and f.color.shape == (15, 20, 3)
    full = open_sequence(tum_dir).frame(3)
    # area average of 2x2 blocks, and depth picked from one of the four pixels
    np.testing.assert_allclose(
        f.color, full.color.reshape(15, 2, 20, 2, 3).mean(axis=(1, 3)), atol=1e-5
    )
    blocks = full.depth.reshape(15, 2, 20, 2).transpose(0, 2, 1, 3).reshape(15, 20, 4)
    assert np.all(np.any(blocks == f.depth[..., None], axis=-1))
    assert seq.intrinsics == open_sequence(tum_dir).intrinsics.scaled(20, 15)


def test_missing_ground_truth_gives_no_poses(tum_dir: Path) -> None:
    (tum_dir / "groundtruth.txt").unlink()
    seq = open_sequence(tum_dir)
    assert not seq.has_ground_truth and seq.frame(0).T_world_cam is None
    assert len(seq.ground_truth()[0]) == 0


def test_sparse_ground_truth_is_associated_by_time(tum_dir: Path) -> None:
    lines = (tum_dir / "groundtruth.txt").read_text().splitlines()
    rows = [ln for ln in lines if not ln.startswith("#")]
    (tum_dir / "groundtruth.txt").write_text("\n".join(rows[::2]) + "\n")  # frames 0, 2, 4
    seq = open_sequence(tum_dir)
    assert [seq.frame(i).T_world_cam is not None for i in range(6)] == [
        True,
        False,
        True,
        False,
        True,
        False,
    ]


def test_rgb_txt_pointing_at_a_missing_file(tum_dir: Path) -> None:
    (tum_dir / "rgb" / "000003.png").unlink()
    with pytest.raises(DatasetError, match=r"colour image .* not found: .*000003.png"):
        open_sequence(tum_dir)


def test_missing_depth_txt(tum_dir: Path) -> None:
    (tum_dir / "depth.txt").unlink()
    with pytest.raises(DatasetError, match=r"no depth\.txt"):
        open_sequence(tum_dir)


def test_eight_bit_depth(tum_dir: Path) -> None:
    p = tum_dir / "depth" / "000002.png"
    Image.fromarray(np.full((30, 40), 9, np.uint8)).save(p)
    seq = open_sequence(tum_dir)
    seq.frame(1)
    with pytest.raises(DatasetError, match=r"000002.png is L \(8-bit\)"):
        seq.frame(2)


def test_mismatched_sizes(tum_dir: Path) -> None:
    Image.fromarray(np.zeros((15, 20), np.uint16)).save(tum_dir / "depth" / "000001.png")
    with pytest.raises(DatasetError, match=r"000001.png is 20x15 but the intrinsics are for 40x30"):
        open_sequence(tum_dir).frame(1)
    Image.fromarray(np.zeros((30, 41, 3), np.uint8)).save(tum_dir / "rgb" / "000002.png")
    Image.fromarray(np.zeros((30, 41), np.uint16)).save(tum_dir / "depth" / "000002.png")
    with pytest.raises(DatasetError, match="intrinsics are for 40x30"):
        open_sequence(tum_dir).frame(2)


def test_corrupt_image_and_bad_lists(tum_dir: Path) -> None:
    (tum_dir / "rgb" / "000000.png").write_bytes(b"not a png")
    with pytest.raises(DatasetError, match=r"cannot read colour image .*000000.png"):
        open_sequence(tum_dir).frame(0)
    (tum_dir / "depth.txt").write_text("0.0 depth/000000.png\nabc depth/000001.png\n")
    with pytest.raises(DatasetError, match=r"depth.txt:2: bad timestamp"):
        open_sequence(tum_dir)


def test_intrinsics_resolution(tum_dir: Path, tmp_path: Path) -> None:
    (tum_dir / "intrinsics.json").unlink()
    with pytest.raises(DatasetError, match="no intrinsics") as failure:
        open_sequence(tum_dir)
    assert "add an intrinsics.json (a JSON object of fx, fy, cx, cy," in str(failure.value)
    k_file = tmp_path / "k.json"
    k_file.write_text(
        json.dumps(
            {
                "fx": 30,
                "fy": 31,
                "cx": 19.5,
                "cy": 14.5,
                "width": 40,
                "height": 30,
                "depth_scale": 5000,
            }
        )
    )
    seq = open_sequence(tum_dir, intrinsics=k_file)
    assert seq.intrinsics == Intrinsics(30.0, 31.0, 19.5, 14.5, 40, 30)
    renamed = tum_dir.parent / "rgbd_dataset_freiburg2_xyz"
    shutil.move(tum_dir, renamed)
    seq = open_sequence(renamed)  # freiburg2 by name (its 640x480 then mismatches the images)
    assert seq.intrinsics.fx == 520.9 and seq.depth_scale == 5000.0
    with pytest.raises(DatasetError, match="intrinsics are for 640x480"):
        seq.frame(0)


def test_not_a_sequence(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match="not found"):
        open_sequence(tmp_path / "nothing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(DatasetError, match="not a known RGB-D layout"):
        open_sequence(tmp_path / "empty")
    with pytest.raises(InputError):
        open_sequence(tmp_path / "empty", size=(0, 10))


def test_replica_layout_built_in_tmp(tmp_path: Path) -> None:
    scene = tmp_path / "room0"
    (scene / "results").mkdir(parents=True)
    for i in range(3):
        Image.fromarray(np.full((20, 30, 3), 40 * i, np.uint8)).save(
            scene / "results" / f"frame{i:06d}.jpg"
        )
        Image.fromarray(np.full((20, 30), 6553 * (i + 1), np.uint16)).save(
            scene / "results" / f"depth{i:06d}.png"
        )
    K = Intrinsics(20.0, 20.0, 14.5, 9.5, 30, 20)
    seq = open_sequence(scene, intrinsics=K)
    assert len(seq) == 3 and not seq.has_ground_truth
    assert seq.frame(2).depth[0, 0] == pytest.approx(3 * 6553 / 6553.5)
    # the camera: the scene's intrinsics.json, else a cam_params.json beside it or above it
    (tmp_path / "cam_params.json").write_text(
        '{"camera": {"w": 30, "h": 20, "fx": 21, "fy": 21, "cx": 14.5, "cy": 9.5, "scale": 1000}}'
    )
    seq = open_sequence(scene)
    assert seq.intrinsics.fx == 21 and seq.depth_scale == 1000
    (scene / "intrinsics.json").write_text(
        '{"fx": 22, "fy": 22, "cx": 14.5, "cy": 9.5, "width": 30, "height": 20}'
    )
    seq = open_sequence(scene)
    assert seq.intrinsics.fx == 22 and seq.depth_scale == 6553.5
    np.savetxt(scene / "traj.txt", np.tile(np.eye(4).ravel(), (2, 1)))
    with pytest.raises(DatasetError, match="has 2 poses but frame 2 needs one"):
        open_sequence(scene, intrinsics=K)


def test_replica_traj_errors_name_their_line(tmp_path: Path) -> None:
    from gscompress.datasets.replica import read_replica_traj

    eye = " ".join(str(v) for v in np.eye(4).ravel())
    cases = {
        "1 2 3": r"traj.txt:3: expected 16 finite",
        eye.replace("0.0", "nan", 1): r"traj.txt:3: expected 16 finite",
        eye[: -len("1.0")] + "1.1": r"traj.txt:3: last row",
        eye.replace("0.0", "x", 1): r"traj.txt:3: not a number",
    }
    path = tmp_path / "traj.txt"
    for bad, message in cases.items():
        path.write_text(f"{eye}\n# a comment\n{bad}\n{eye}\n")
        with pytest.raises(DatasetError, match=message):
            read_replica_traj(path)
    path.write_text(f"{eye}\n\n{eye} # trailing comment\n")
    poses = read_replica_traj(path)
    assert poses.shape == (2, 4, 4) and np.array_equal(poses[1], np.eye(4))


def test_a_frame_fingerprint_survives_resampling_noise_but_not_another_scene() -> None:
    from dataclasses import replace

    from gscompress.datasets.base import same_fingerprint

    frame = synthetic_sequence(2, (64, 48)).frame(0)
    noise = np.random.default_rng(0).normal(0, 1e-3, frame.color.shape).astype(np.float32)
    resampled = replace(frame, color=frame.color + noise, depth=frame.depth * (1 + 1e-5))
    assert same_fingerprint(frame.fingerprint(), resampled.fingerprint())
    other = synthetic_sequence(2, (64, 48), seed=5).frame(0)
    assert not same_fingerprint(frame.fingerprint(), other.fingerprint())
    assert not same_fingerprint(frame.fingerprint(), frame.fingerprint()[:3])


def test_a_recorded_fingerprint_that_is_not_four_numbers_counts_as_none() -> None:
    from gscompress.datasets.base import recorded_fingerprint

    assert recorded_fingerprint([1, 2.5, 0.5, 0.25]) == [1.0, 2.5, 0.5, 0.25]
    for bad in (["1", "2", "3", "4"], [1, 2, 3], [1, 2, 3, float("nan")], [True] * 4, "x", None):
        assert recorded_fingerprint(bad) is None
