"""TUM trajectory text: exact round trips, tolerance of comments, strictness on bad rows, and
interchange with evo in both directions."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from gscompress.camera import make_transform, quat_to_rotmat
from gscompress.errors import InputError
from gscompress.io.trajectory import (
    nearest_times,
    parse_tum_trajectory,
    read_transform,
    read_tum_trajectory,
    write_tum_trajectory,
)


def _poses(n: int = 20, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 4))
    T = make_transform(quat_to_rotmat(q), rng.normal(0, 3, (n, 3)))
    return 1305031102.175304 + np.arange(n) / 30.0, T


def test_round_trip_is_exact_for_timestamps_and_translations(tmp_path: Path) -> None:
    stamps, T = _poses()
    write_tum_trajectory(tmp_path / "t.txt", stamps, T, comments=["made by a test"])
    back = read_tum_trajectory(tmp_path / "t.txt")
    assert np.array_equal(back.timestamps, stamps)
    assert np.array_equal(back.T_world_cam[:, :3, 3], T[:, :3, 3])
    np.testing.assert_allclose(back.T_world_cam, T, atol=1e-14)
    assert (tmp_path / "t.txt").read_text().startswith("# made by a test\n")


def test_comments_blank_lines_and_commas_are_tolerated() -> None:
    text = "# header\n\n  1.0 1 2 3 0 0 0 1  # trailing\n\t\n2.0,4,5,6,0,0,0,2\n"
    traj = parse_tum_trajectory(text)
    assert len(traj) == 2
    np.testing.assert_array_equal(traj.timestamps, [1.0, 2.0])
    np.testing.assert_allclose(traj.T_world_cam[1, :3, 3], [4, 5, 6])
    np.testing.assert_allclose(traj.T_world_cam[1, :3, :3], np.eye(3))  # quaternion normalised
    assert len(parse_tum_trajectory("# only a comment\n")) == 0


@pytest.mark.parametrize(
    ("row", "message"),
    [
        ("1.0 1 2 3 0 0 0", "expected 8 numbers"),
        ("1.0 1 2 3 0 0 0 1 7", "expected 8 numbers"),
        ("1.0 1 two 3 0 0 0 1", "not a number"),
        ("1.0 1 2 nan 0 0 0 1", "non-finite"),
        ("1.0 1 2 3 0 0 0 0", "zero-length quaternion"),
    ],
)
def test_malformed_rows_name_the_line(tmp_path: Path, row: str, message: str) -> None:
    p = tmp_path / "bad.txt"
    p.write_text("# ok\n0.0 0 0 0 0 0 0 1\n" + row + "\n")
    with pytest.raises(InputError, match=rf"bad.txt:3: .*{message}"):
        read_tum_trajectory(p)


@pytest.mark.parametrize(
    ("q", "zero"), [("0 0 1e-7 0", True), ("0 0 2e-6 0", False), ("1e300 0 0 1e300", False)]
)
def test_trajectories_and_transforms_take_the_same_quaternions_for_zero(
    tmp_path: Path, q: str, zero: bool
) -> None:
    (tmp_path / "t.txt").write_text(f"1.0 1 2 3 {q}\n")
    (tmp_path / "T.txt").write_text(f"1 2 3 {q}\n")
    reads = [
        lambda: read_tum_trajectory(tmp_path / "t.txt").T_world_cam[0],
        lambda: read_transform(tmp_path / "T.txt"),
    ]
    for read in reads:
        if zero:
            with pytest.raises(InputError, match="zero"):
                read()
        else:
            R = read()[:3, :3]
            np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)


def test_nearest_times_takes_the_nearest_within_tolerance_in_any_order() -> None:
    ref = np.array([2_000_000_000, 0, 1_000_000_000])  # indices refer to this order
    query = np.array([5, 999_500_000, 1_500_000_000, 2_000_999_999, 3_000_000_000])
    tol = 1_000_000
    assert nearest_times(query, ref, tol).tolist() == [1, 2, -1, 0, -1]
    assert nearest_times(query, ref[:0], tol).tolist() == [-1] * 5
    assert nearest_times(np.array([0.5]), np.array([1.0, 0.0]), 0.5).tolist() == [1]  # tie: earlier
    assert nearest_times(np.array([0.5]), np.array([1.0, 0.0]), 0.5, strict=True).tolist() == [-1]
    assert nearest_times(np.array([7.0]), np.array([3.0]), 5.0).tolist() == [0]


def test_writing_a_trajectory_keeps_the_old_file_on_failure_and_refuses_links(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import os

    from gscompress.errors import OutputError
    from gscompress.io import files

    stamps, T = _poses(3)
    path = tmp_path / "t.txt"
    path.write_text("old\n")

    def full_disk(*args: object) -> None:
        raise OSError(28, "No space left on device")

    with monkeypatch.context() as m:
        m.setattr(files.AtomicFile, "commit", full_disk)
        with pytest.raises(OutputError, match="No space left"):
            write_tum_trajectory(path, stamps, T)
    assert path.read_text() == "old\n" and [p.name for p in tmp_path.iterdir()] == ["t.txt"]
    os.symlink(path, tmp_path / "link.txt")
    with pytest.raises(OutputError, match="symbolic link"):
        write_tum_trajectory(tmp_path / "link.txt", stamps, T)
    assert path.read_text() == "old\n"


def test_a_byte_order_mark_before_the_first_line_is_not_read_as_text(tmp_path: Path) -> None:
    path = tmp_path / "bom.txt"
    path.write_bytes(b"\xef\xbb\xbf# made on Windows\n1.0 1 2 3 0 0 0 1\n")
    assert len(read_tum_trajectory(path)) == 1


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="not found"):
        read_tum_trajectory(tmp_path / "nope.txt")


def test_evo_reads_ours_and_we_read_evos(tmp_path: Path) -> None:
    file_interface = pytest.importorskip("evo.tools.file_interface")
    from evo.core.trajectory import PoseTrajectory3D

    stamps, T = _poses(15, seed=3)
    write_tum_trajectory(tmp_path / "ours.txt", stamps, T)
    theirs = file_interface.read_tum_trajectory_file(str(tmp_path / "ours.txt"))
    np.testing.assert_allclose(theirs.timestamps, stamps, rtol=0, atol=0)
    np.testing.assert_allclose(np.array(theirs.poses_se3), T, atol=1e-12)

    evo_traj = PoseTrajectory3D(poses_se3=list(T), timestamps=stamps)
    file_interface.write_tum_trajectory_file(str(tmp_path / "evo.txt"), evo_traj)
    back = read_tum_trajectory(tmp_path / "evo.txt")
    np.testing.assert_allclose(back.timestamps, stamps, atol=1e-6)
    np.testing.assert_allclose(back.T_world_cam, T, atol=1e-6)
