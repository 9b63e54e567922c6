"""PWAS accumulation, scoring an existing map by rendering, and `gsc score`."""

import json
import math
from functools import partial

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from gscompress.camera import Intrinsics, make_transform
from gscompress.errors import InputError
from gscompress.gaussians import SH_C0, GaussianMap
from gscompress.importance import PAPER_SIGMA_D, ImportanceSums
from gscompress.io.mcap_log import LogReader, read_map
from gscompress.io.ply import write_ply
from gscompress.ops.score import score_map
from gscompress.selection import select_top
from gscompress.slam.densify import gaussians_from_rgbd
from gscompress_cli.main import cli

INTR = Intrinsics(40.0, 40.0, 15.5, 11.5, 32, 24)


def test_accumulate_matches_the_equations():
    sums = ImportanceSums.zeros(3)
    means = torch.tensor([[0.0, 0, 1], [0, 0, 5], [0, 0, 50]])
    sigma_d = 2.0
    frames = [
        (torch.tensor([4.0, 1.0, 0.0]), torch.tensor([True, True, False]), torch.zeros(3)),
        (
            torch.tensor([2.0, 0.0, 0.0]),
            torch.tensor([True, True, True]),
            torch.tensor([0, 0, 1.0]),
        ),
    ]
    for contribution, visible, center in frames:
        sums.accumulate(contribution, visible, means, center, sigma_d)
    w = [[np.exp(-d / 2.0) for d in (1, 5, 50)], [np.exp(-d / 2.0) for d in (0, 4, 49)]]
    S = [4 * w[0][0] + 2 * w[1][0], 1 * w[0][1], 0.0]
    W = [w[0][0] + w[1][0], w[0][1] + w[1][1], w[1][2]]
    np.testing.assert_allclose(sums.importance_sum.numpy(), S, rtol=1e-12)
    np.testing.assert_allclose(sums.importance_weight.numpy(), W, rtol=1e-12)
    np.testing.assert_allclose(sums.alpha_t_sum.numpy(), [6, 1, 0])
    np.testing.assert_allclose(sums.score().numpy(), np.array(S) / (np.array(W) + 1e-8))
    # visible-but-occluded frames lower the score (the second Gaussian)
    assert sums.score()[1] < 1.0


def _scene() -> GaussianMap:
    """A large near Gaussian in front of a small distant one on the optical axis, plus one
    off to the side that no camera sees."""
    return GaussianMap.new(
        means=[[0.0, 0.0, 1.0], [0.0, 0.0, 4.0], [30.0, 0.0, 1.0]],
        log_scales=np.log([[0.2], [0.05], [0.1]]),
        quats=[[1, 0, 0, 0]] * 3,
        opacity_logits=[4.0, 4.0, 4.0],
        sh_dc=np.full((3, 3), (0.7 - 0.5) / SH_C0),
    )


def test_score_ranks_near_large_above_distant_occluded():
    views = [make_transform(np.eye(3), np.array([dx, 0.0, 0.0])) for dx in (-0.05, 0.0, 0.05)]
    scored = score_map(_scene(), views, INTR, sigma_d=PAPER_SIGMA_D, backend="torch")
    s = scored.importance
    assert s[0] > 10 * s[1] > 0
    assert scored.importance_weight[2] == 0 and s[2] == 0  # never visible
    assert scored.importance_weight[1] > 0  # visible, though occluded
    kept, _ = select_top(scored, 1 / 3, "pwas")
    assert kept.ids.tolist() == [0]


def test_score_from_views_accumulates_across_calls():
    views = [make_transform(np.eye(3), np.zeros(3))]
    score = partial(score_map, sigma_d=PAPER_SIGMA_D, backend="torch")
    once = score(_scene(), views * 2, INTR)
    twice = score(score(_scene(), views, INTR), views, INTR, accumulate=True)
    np.testing.assert_allclose(twice.importance_sum, once.importance_sum, rtol=1e-6)
    np.testing.assert_allclose(twice.importance_weight, once.importance_weight, rtol=1e-6)


def test_backprojection_lands_on_the_depth():
    depth = np.full((24, 32), 2.0, np.float32)
    depth[:, :4] = 0
    color = np.random.default_rng(0).random((24, 32, 3)).astype(np.float32)
    T = make_transform(np.eye(3), np.array([1.0, 2.0, 3.0]))
    g = gaussians_from_rgbd(color, depth, INTR, T, stride=2, first_id=7)
    assert len(g) == 12 * 14 and g.ids[0] == 7 and g.isotropic
    np.testing.assert_allclose(g.means[:, 2], 5.0)
    np.testing.assert_allclose(g.scales()[:, 0], 2.0 * 2 / 40.0, rtol=1e-6)
    np.testing.assert_allclose(g.colors()[0], color[0, 4], rtol=1e-6)


@pytest.fixture(scope="module")
def synth_sequence(tmp_path_factory):
    """The synthetic room as `gsc synth` writes it: 6 frames at 32x24."""
    out = tmp_path_factory.mktemp("seq") / "synthetic"
    r = CliRunner().invoke(cli, ["synth", str(out), "--frames", "6", "--size", "32x24"])
    assert r.exit_code == 0, r.output
    return out


def test_gsc_score_ply_and_mcap(synth_sequence, tmp_path):
    from gscompress.datasets import open_sequence

    seq = open_sequence(synth_sequence)
    f = seq.frame(0)
    g = gaussians_from_rgbd(f.color, f.depth, seq.intrinsics, f.T_world_cam, stride=2)
    write_ply(g, tmp_path / "m.ply", importance=False)
    r = CliRunner().invoke(
        cli,
        [
            "score",
            str(tmp_path / "m.ply"),
            "--seq",
            str(synth_sequence),
            "-o",
            str(tmp_path / "s.mcap"),
            "--json",
        ],
    )
    assert r.exit_code == 0, r.output
    scored = read_map(tmp_path / "s.mcap")
    assert scored.has_importance and np.array_equal(scored.means, g.means)
    with LogReader(tmp_path / "s.mcap") as log:
        counts = {c.topic: c.messages for c in log.channels}
        assert counts["/camera/pose"] == 6 and counts["/camera/calibration"] == 1
        assert log.metadata.provenance[-1]["operation"]["name"] == "score"
    # scoring a log again replaces only its map
    r = CliRunner().invoke(
        cli,
        [
            "score",
            str(tmp_path / "s.mcap"),
            "--seq",
            str(synth_sequence),
            "--frames",
            "0:3",
            "-o",
            str(tmp_path / "t.mcap"),
        ],
    )
    assert r.exit_code == 0, r.output
    again = read_map(tmp_path / "t.mcap")
    assert np.all(again.importance_weight <= scored.importance_weight + 1e-6)
    from gscompress.pipeline.score import score_file

    calls: list[tuple[int, int]] = []  # what the progress bar is given: views done, of how many
    score_file(
        tmp_path / "m.ply",
        tmp_path / "u.mcap",
        synth_sequence,
        frames="1:6:2",
        progress=lambda done, total: calls.append((done, total)),
    )
    assert calls == [(1, 3), (2, 3), (3, 3)]


def test_gsc_score_without_poses_is_a_clear_error(synth_sequence, tmp_path):
    import shutil

    seq = tmp_path / "nogt"
    shutil.copytree(synth_sequence, seq)
    (seq / "groundtruth.txt").unlink()
    write_ply(_scene(), tmp_path / "m.ply")
    r = CliRunner().invoke(
        cli, ["score", str(tmp_path / "m.ply"), "--seq", str(seq), "-o", str(tmp_path / "s.mcap")]
    )
    assert r.exit_code == 1 and "--poses" in r.output
    assert not (tmp_path / "s.mcap").exists()


def test_gsc_score_with_poses_matches_them_to_frames_by_time(synth_sequence, tmp_path):
    import shutil

    seq = tmp_path / "nogt"
    shutil.copytree(synth_sequence, seq)
    (seq / "groundtruth.txt").unlink()
    write_ply(_scene(), tmp_path / "m.ply")
    # the ground truth as another tool's estimate: shuffled rows, times off by 10 ms
    rows = [
        r
        for r in (synth_sequence / "groundtruth.txt").read_text().splitlines()
        if r and not r.startswith("#")
    ][::-1]
    shifted = [f"{float(r.split()[0]) + 0.01:.6f} {' '.join(r.split()[1:])}" for r in rows]
    (tmp_path / "est.txt").write_text("\n".join(shifted) + "\n")
    args = ["score", str(tmp_path / "m.ply"), "-o"]
    r = CliRunner().invoke(cli, [*args, str(tmp_path / "gt.mcap"), "--seq", str(synth_sequence)])
    assert r.exit_code == 0, r.output
    r = CliRunner().invoke(
        cli,
        [
            *args,
            str(tmp_path / "est.mcap"),
            "--seq",
            str(seq),
            "--poses",
            str(tmp_path / "est.txt"),
        ],
    )
    assert r.exit_code == 0, r.output
    np.testing.assert_allclose(
        read_map(tmp_path / "est.mcap").importance,
        read_map(tmp_path / "gt.mcap").importance,
        rtol=1e-5,
    )

    (tmp_path / "short.txt").write_text("\n".join(shifted[1:]) + "\n")  # the last frame's row gone
    r = CliRunner().invoke(
        cli,
        [
            *args,
            str(tmp_path / "s.mcap"),
            "--seq",
            str(seq),
            "--poses",
            str(tmp_path / "short.txt"),
        ],
    )
    assert r.exit_code == 1 and "has no pose within 0.02 s of frame time" in r.output
    assert not (tmp_path / "s.mcap").exists()


def test_gsc_score_of_a_log_takes_its_poses_frames_and_size(synth_sequence, tmp_path):
    import shutil

    from gscompress.io.trajectory import write_tum_trajectory
    from gscompress.pipeline import share_log, slam_file
    from gscompress.pipeline.score import score_file
    from gscompress.pipeline.slam_run.options import SlamOptions

    seq = tmp_path / "nogt"  # no ground truth: the run's world frame is its first camera
    shutil.copytree(synth_sequence, seq)
    (seq / "groundtruth.txt").unlink()
    slam_file(seq, tmp_path / "a.mcap", SlamOptions(preset="tiny", frames="odd", size=(24, 18)))
    r = score_file(tmp_path / "a.mcap", tmp_path / "s.mcap", seq)
    assert r["views"] == 3 and r["poses"] == "estimated"  # frames 1, 3, 5 at the log's poses
    assert r["frames_without_pose"] == 0
    every = score_file(tmp_path / "a.mcap", tmp_path / "e.mcap", seq, frames="all")
    assert every["views"] == 3 and every["frames_without_pose"] == 3  # the even frames
    with LogReader(tmp_path / "s.mcap") as log:
        assert log.metadata.provenance[-1]["operation"]["size"] == [24, 18]
        stamps, poses = log.read_poses()
    write_tum_trajectory(tmp_path / "est.txt", stamps / 1e9, poses)
    again = score_file(
        tmp_path / "a.mcap",
        tmp_path / "t.mcap",
        seq,
        poses=tmp_path / "est.txt",
        frames="odd",
        size=(24, 18),
    )
    assert again["poses"] == "est.txt"
    np.testing.assert_allclose(
        read_map(tmp_path / "t.mcap").importance,
        read_map(tmp_path / "s.mcap").importance,
        rtol=1e-5,
    )

    share_log(tmp_path / "a.mcap", tmp_path / "share.mcap", 0.5)  # a map without poses
    with pytest.raises(InputError, match="world frame is its run's first camera"):
        score_file(tmp_path / "share.mcap", tmp_path / "u.mcap", seq)
    assert not (tmp_path / "u.mcap").exists()


def _depth_at_ranges(ranges: np.ndarray) -> np.ndarray:
    """[24, 32] depth (along the optical axis of INTR) whose pixels lie at `ranges` metres from
    the camera centre; 0 (invalid) where `ranges` is 0."""
    v, u = np.mgrid[0:24, 0:32]
    stretch = np.sqrt(((u - INTR.cx) / INTR.fx) ** 2 + ((v - INTR.cy) / INTR.fy) ** 2 + 1)
    return (ranges / stretch).astype(np.float64)


def test_sigma_d_rule_is_the_median_camera_to_gaussian_distance_of_the_first_frame():
    from gscompress.importance import median_range, resolve_sigma_d

    rng = np.random.default_rng(3)
    ranges = rng.choice([0.6, 1.0, 1.5, 2.5, 4.0], size=(24, 32), p=[0.2, 0.2, 0.25, 0.2, 0.15])
    ranges[:, :5] = 0  # no depth there
    depth = _depth_at_ranges(ranges)
    T = make_transform(np.eye(3), np.array([1.0, -2.0, 0.5]))  # (where the camera is: no matter)
    gaussians = gaussians_from_rgbd(np.full((24, 32, 3), 0.5), depth, INTR, T, stride=1)
    distances = np.linalg.norm(gaussians.means - T[:3, 3], axis=1)
    np.testing.assert_allclose(np.sort(distances), np.sort(ranges[ranges > 0]), rtol=1e-5)

    sigma_d = resolve_sigma_d(None, [np.zeros((24, 32)), depth], INTR)  # (first valid depth)
    assert sigma_d == pytest.approx(np.median(distances), rel=1e-6) == median_range(depth, INTR)
    assert sigma_d == 1.5
    assert resolve_sigma_d(2.0, [depth], INTR) == 2.0  # a number set is kept
    assert resolve_sigma_d(math.inf, [], INTR) == math.inf
    with pytest.raises(InputError, match="no frame has valid depth"):
        resolve_sigma_d(None, [np.zeros((24, 32))], INTR)
    with pytest.raises(InputError, match="above 0"):
        resolve_sigma_d(0.0, [depth], INTR)

    # the proximity weight now tells near from far: a Gaussian at 0.6 m weighs 5.3 times one at
    # 4 m (the paper's 20 m: 1.18 times, i.e. hardly at all; inf: exactly equal)
    near, far = np.argmin(distances), np.argmax(distances)
    means = torch.from_numpy(gaussians.means[[near, far]])
    for scale, ratio in (
        (sigma_d, np.exp(3.4 / 1.5)),
        (PAPER_SIGMA_D, np.exp(3.4 / 20)),
        (math.inf, 1.0),
    ):
        sums = ImportanceSums.zeros(2)
        sums.accumulate(
            torch.ones(2), torch.ones(2, dtype=torch.bool), means, torch.from_numpy(T[:3, 3]), scale
        )
        w = sums.importance_weight.numpy()
        assert w[0] / w[1] == pytest.approx(ratio, rel=1e-6)
    assert np.exp(3.4 / 1.5) > 5 and np.exp(3.4 / 20) < 1.2


def test_gsc_score_derives_sigma_d_from_the_scene_or_takes_it(synth_sequence, tmp_path):
    from gscompress.datasets import open_sequence
    from gscompress.importance import median_range

    seq = open_sequence(synth_sequence)
    f = seq.frame(0)
    g = gaussians_from_rgbd(f.color, f.depth, seq.intrinsics, f.T_world_cam, stride=2)
    write_ply(g, tmp_path / "m.ply", importance=False)
    args = ["score", str(tmp_path / "m.ply"), "--seq", str(synth_sequence), "--json", "-o"]
    used = {}
    for setting in ("auto", "inf", "0.5"):
        out = tmp_path / f"{setting}.mcap"
        extra = [] if setting == "auto" else ["--sigma-d", setting]
        r = CliRunner().invoke(cli, [*args, str(out), *extra])
        assert r.exit_code == 0, r.output
        with LogReader(out) as log:
            used[setting] = log.metadata.results["sigma_d"]
            setting_recorded = log.metadata.provenance[-1]["operation"]["sigma_d"]
        assert str(setting_recorded) == setting
        assert json.loads(r.output)["sigma_d"] == used[setting]
    assert used["auto"] == pytest.approx(median_range(f.depth, seq.intrinsics))
    assert 0.5 < used["auto"] < 10 and used["inf"] == "inf" and used["0.5"] == 0.5
    # without proximity weighting a Gaussian's weight counts the views that see it
    unweighted = read_map(tmp_path / "inf.mcap").importance_weight
    np.testing.assert_array_equal(unweighted, np.round(unweighted))
    assert unweighted.max() == 6
    r = CliRunner().invoke(cli, [*args, str(tmp_path / "x.mcap"), "--sigma-d", "-1"])
    assert r.exit_code == 2 and "not a finite number above 0" in r.output
