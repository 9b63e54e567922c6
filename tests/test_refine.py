"""Refinement after selection: `gsc prune --refine` and `gsc share --refine`."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from gscompress.datasets.synthetic import write_synthetic_sequence
from gscompress.errors import InputError
from gscompress.gaussians import GaussianMap
from gscompress.io.mcap_log import TOPIC_POSE, TOPIC_STATS, LogReader, read_map
from gscompress.pipeline import evaluate_log, prune_log, share_log
from gscompress.pipeline.images import ImageOptions
from gscompress.pipeline.logs import recorded_keyframes
from gscompress.pipeline.refining import (
    PSEUDO_VIEWS,
    LogRefiner,
    RefineOptions,
    pseudo_poses,
    teacher_views,
)
from gscompress.selection import select_top
from gscompress_cli.main import cli

# runs SLAM (or another minutes-long pipeline): not in `make test-fast`
pytestmark = pytest.mark.slow


def keyframe_indices(log: Path) -> set[int]:
    with LogReader(log) as reader:
        return {
            json.loads(m.data)["frame"]
            for _s, _c, m in reader.iter_messages([TOPIC_STATS])
            if json.loads(m.data)["keyframe"]
        }


def mean_psnr_off_keyframes(log: Path, seq: Path, keyframes: set[int]) -> float:
    per_frame = evaluate_log(log, seq, ImageOptions(lpips=False))["per_frame"]
    scores = [f["psnr"] for f in per_frame if f["index"] not in keyframes]
    assert scores, "no frame outside the keyframes"
    return float(np.mean(scores))


def test_the_log_keyframes_are_the_ones_its_stats_mark(run: dict[str, Path]) -> None:
    with LogReader(run["log"]) as reader:
        times = recorded_keyframes(reader)
        pose_ns, _ = reader.read_poses(TOPIC_POSE)
    assert times == {int(pose_ns[k]) for k in (0, 2, 4)}  # the tiny preset: every 2nd frame
    refiner = LogRefiner(run["log"], run["seq"], RefineOptions(1))
    assert [v.index for v in refiner.views] == [0, 2, 4]
    every = LogRefiner(run["log"], run["seq"], RefineOptions(1, views="frames"))
    assert len(every.views) == 6


def test_refinement_improves_a_pruned_map_off_its_keyframes(run: dict[str, Path]) -> None:
    plain, refined = run["root"] / "pruned.mcap", run["root"] / "refined.mcap"
    prune_log(run["log"], plain, 0.3)
    refiner = LogRefiner(run["log"], run["seq"], RefineOptions(80))
    result = prune_log(run["log"], refined, 0.3, refine=refiner)
    assert result["refine_loss_after"] < result["refine_loss_before"]
    assert result["refine_views"] == 3 and result["refine_iters"] == 80
    assert result["refine_pseudo_views"] == 2 * PSEUDO_VIEWS  # between the 3 keyframes
    before, after = read_map(plain), read_map(refined)
    # the same Gaussians in the same order: none of the pruned ones came back, none dropped
    assert np.array_equal(before.ids, after.ids) and len(after) == result["kept"]
    assert not np.array_equal(before.means, after.means)
    assert np.array_equal(before.importance_sum, after.importance_sum)  # sums carried
    keyframes = keyframe_indices(run["log"])
    assert mean_psnr_off_keyframes(refined, run["seq"], keyframes) > mean_psnr_off_keyframes(
        plain, run["seq"], keyframes
    )
    with LogReader(refined) as reader:
        step = reader.metadata.provenance[-1]["operation"]
    assert step["refine"]["iters"] == 80 and step["refine"]["views"] == "keyframes"


def test_pseudo_views_lie_between_keyframes_and_show_the_teacher(run: dict[str, Path]) -> None:
    refiner = LogRefiner(run["log"], run["seq"], RefineOptions(1))
    poses = [v.T_world_cam for v in refiner.views]
    between = pseudo_poses(poses, 3)
    assert len(between) == 3 * (len(poses) - 1)
    for k, pose in enumerate(between):  # on the segment between its two keyframes, in order
        a, b = poses[k // 3][:3, 3], poses[k // 3 + 1][:3, 3]
        t = (k % 3 + 1) / 4
        np.testing.assert_allclose(pose[:3, 3], (1 - t) * a + t * b, atol=1e-12)
    full = read_map(run["log"])
    views = teacher_views(full, between[:1], refiner.intrinsics, refiner.backend, "cpu")
    assert views[0].color.shape == refiner.views[0].color.shape
    assert float(views[0].color.std()) > 0.01  # a picture of the map, not a blank
    assert float((views[0].depth > 0).float().mean()) > 0.5  # opaque where the map is
    unscored = LogRefiner(run["log"], run["seq"], RefineOptions(5, pseudo_views=0))
    assert unscored(select_top(full, 0.3)[0], teacher=full)[1]["pseudo_views"] == 0


def test_a_refined_share_stays_within_its_budget(run: dict[str, Path]) -> None:
    """A fraction budget keeps its count; a byte budget bounds the file of the refined values
    (which compress differently), keeping the best of the Gaussians first chosen."""
    refine = LogRefiner(run["log"], run["seq"], RefineOptions(5))
    plain, refined = run["root"] / "s.mcap", run["root"] / "s_refined.mcap"
    a = share_log(run["log"], plain, 0.3)
    b = share_log(run["log"], refined, 0.3, refine=refine, force=True)
    assert a["selected"] == b["selected"] and b["refine_iters"] == 5
    assert np.array_equal(np.sort(read_map(plain).ids), np.sort(read_map(refined).ids))
    a = share_log(run["log"], plain, "20kB", force=True)
    b = share_log(run["log"], refined, "20kB", refine=refine, force=True)
    assert b["file_bytes"] == refined.stat().st_size <= 20_000
    assert 0.9 * a["selected"] <= b["selected"] <= a["selected"]
    assert set(read_map(refined).ids.tolist()) <= set(read_map(plain).ids.tolist())


def test_refinement_refuses_another_scene(run: dict[str, Path]) -> None:
    other = write_synthetic_sequence(run["root"] / "other" / "room", 6, (48, 36), seed=7)
    with pytest.raises(InputError, match="not recorded on this room"):
        LogRefiner(run["log"], other, RefineOptions(5))


def test_prune_cli_refines_with_a_sequence_and_asks_for_one(run: dict[str, Path]) -> None:
    out = run["root"] / "cli.mcap"
    args = ["prune", str(run["log"]), "--keep", "0.5", "-o", str(out)]
    r = CliRunner().invoke(cli, [*args, "--refine", "3"])
    assert r.exit_code == 2 and "--refine needs the sequence" in r.output
    assert len(r.output.strip().splitlines()) == 1 and not out.exists()
    r = CliRunner().invoke(cli, [*args, "--seq", str(run["seq"])])
    assert r.exit_code == 2 and "--seq is only used with --refine" in r.output
    assert not out.exists()
    r = CliRunner().invoke(cli, [*args, "--refine", "3", "--seq", str(run["seq"]), "--json"])
    assert r.exit_code == 0, r.output
    result = json.loads(r.output)
    assert result["refine_iters"] == 3 and result["refine_views"] == 3
    full = read_map(run["log"])
    assert np.array_equal(read_map(out).ids, select_top(full, 0.5, "pwas")[0].ids)


def test_share_cli_asks_for_the_sequence_to_refine_on(run: dict[str, Path]) -> None:
    out = run["root"] / "share_cli.mcap"
    r = CliRunner().invoke(cli, ["share", str(run["log"]), str(out), "--refine", "3"])
    assert r.exit_code == 2 and "--refine needs the sequence" in r.output
    assert not out.exists()


def test_an_anisotropic_refinement_shapes_the_kept_gaussians(run: dict[str, Path]) -> None:
    """`RefineOptions(anisotropic=True)`: the isotropic map is cut as an anisotropic one, so
    that each folded group keeps its covariance, and the refinement steps three scales and a
    rotation; the same Gaussians come out, and the provenance says how they were shaped."""
    full = read_map(run["log"])
    assert full.isotropic
    flat, shaped = run["root"] / "iso.mcap", run["root"] / "aniso.mcap"
    iso = prune_log(
        run["log"], flat, 0.3, refine=LogRefiner(run["log"], run["seq"], RefineOptions(40))
    )
    refiner = LogRefiner(run["log"], run["seq"], RefineOptions(40, anisotropic=True))
    aniso = prune_log(run["log"], shaped, 0.3, refine=refiner)
    a, b = read_map(flat), read_map(shaped)
    assert a.isotropic and not b.isotropic
    assert np.array_equal(a.ids, b.ids)
    spread = np.ptp(b.log_scales, axis=1)
    assert float(np.median(spread)) > 0.05  # the three scales differ: shaped, not promoted
    assert aniso["refine_loss_after"] < aniso["refine_loss_before"]
    assert aniso["refine_loss_after"] <= iso["refine_loss_after"] * 1.05
    with LogReader(shaped) as reader:
        assert reader.metadata.provenance[-1]["operation"]["refine"]["anisotropic"] is True
    with LogReader(flat) as reader:
        assert "anisotropic" not in reader.metadata.provenance[-1]["operation"]["refine"]


def test_an_anisotropic_cut_folds_into_the_group_covariance(run: dict[str, Path]) -> None:
    """Folding into an anisotropic pool keeps each group's moment-matched covariance: a kept
    Gaussian that absorbs neighbours along a surface becomes elongated, where the isotropic
    fold keeps only the trace."""
    from gscompress.ops.fold import cut_map, cut_pool

    full = read_map(run["log"])
    scores = full.importance_sum / np.maximum(full.importance_weight, 1e-12)
    count = len(full) // 3

    class Shaping:
        anisotropic = True

    iso = cut_map(cut_pool(full, None), count, scores, True)
    aniso = cut_map(cut_pool(full, Shaping()), count, scores, True)  # type: ignore[arg-type]
    assert iso.isotropic and not aniso.isotropic
    np.testing.assert_allclose(aniso.means, iso.means, atol=1e-6)
    # the same trace per Gaussian, split unevenly over the axes
    trace_iso = 3 * np.exp(2 * iso.log_scales[:, 0].astype(np.float64))
    trace_aniso = np.exp(2 * aniso.log_scales.astype(np.float64)).sum(axis=1)
    np.testing.assert_allclose(trace_aniso, trace_iso, rtol=1e-4)
    from gscompress.ops.fold import fold_groups
    from gscompress.selection import select_by

    _, kept = select_by(full, count, scores)
    group = fold_groups(full, kept)
    absorbed = np.bincount(group[group >= 0], None, count) > 1
    spread = np.ptp(aniso.log_scales, axis=1)
    assert absorbed.mean() > 0.3 and float(np.median(spread[absorbed])) > 0.1
    assert np.all(spread[~absorbed] < 1e-5)  # alone in its group: as round as it was


def test_prune_cli_refines_anisotropic_unless_told_not_to(run: dict[str, Path]) -> None:
    args = ["prune", str(run["log"]), "--keep", "0.5", "--refine", "2", "--seq", str(run["seq"])]
    for flag, isotropic in (([], False), (["--isotropic"], True)):
        out = run["root"] / f"cli_shape_{isotropic}.mcap"
        r = CliRunner().invoke(cli, [*args, *flag, "-o", str(out)])
        assert r.exit_code == 0, r.output
        assert read_map(out).isotropic is isotropic


def test_a_byte_budget_share_refines_the_count_its_refined_values_fit(
    run: dict[str, Path],
) -> None:
    """Refined values may compress worse than the cut's (here: every rotation turned at
    random, as an anisotropic refinement turns them). A probe refinement learns that first, so
    the full refinement runs on the count that then fits, and at most a few refined are left
    out."""
    from dataclasses import replace

    from gscompress.pipeline.share.cut import PROBE_ITERS

    class Turning:
        anisotropic = True

        def __init__(self) -> None:
            self.calls: list[tuple[int, int | None]] = []

        def record(self) -> dict[str, object]:
            return {}

        def __call__(
            self,
            gaussians: GaussianMap,
            rates: object = None,
            teacher: GaussianMap | None = None,
            iters: int | None = None,
        ) -> tuple[GaussianMap, dict[str, object]]:
            self.calls.append((len(gaussians), iters))
            # each Gaussian turned by its id alone: the probe and the full refinement give the
            # Gaussians they share the same values
            turns = np.sin(gaussians.ids[:, None] * np.arange(1.1, 8.0, 1.0)[None, :7] * 7.3)
            quats = turns[:, :4].astype(np.float32) + np.float32(1e-3)
            quats /= np.linalg.norm(quats, axis=1, keepdims=True)
            scales = gaussians.log_scales + 0.3 * turns[:, 4:7]
            return replace(gaussians, quats=quats, log_scales=scales.astype(np.float32)), {}

    refine = Turning()
    plain = share_log(run["log"], run["root"] / "plain.mcap", "12kB")
    result = share_log(run["log"], run["root"] / "turned.mcap", "12kB", refine=refine)
    (probed, probe_iters), (refined_count, full_iters) = refine.calls
    assert probe_iters == PROBE_ITERS and full_iters is None
    assert probed > refined_count  # the turned values take more bytes a Gaussian
    # (the probe's values were folded from more Gaussians, so they compress a little
    # differently: at most the last few refined are left out, as `ShareCut.refined` says)
    assert refined_count - 0.01 * refined_count <= result["selected"] <= refined_count
    assert result["file_bytes"] <= 12_000
    assert plain["selected"] >= probed


def test_a_refined_share_is_shaped_only_when_its_budget_leaves_gaussians_out(
    run: dict[str, Path],
) -> None:
    """Under a byte budget that holds the whole map as it is, three scales a Gaussian would
    only leave some out: the share stays isotropic. Below it, and under a count budget, it is
    shaped."""
    refiner = LogRefiner(run["log"], run["seq"], RefineOptions(3, anisotropic=True))
    whole = share_log(run["log"], run["root"] / "w.mcap", 1.0)["file_bytes"]
    roomy = share_log(run["log"], run["root"] / "roomy.mcap", f"{whole + 2000}B", refine=refiner)
    assert read_map(run["root"] / "roomy.mcap").isotropic and roomy["selected"] == roomy["total"]
    share_log(run["log"], run["root"] / "tight.mcap", f"{whole // 2}B", refine=refiner)
    assert not read_map(run["root"] / "tight.mcap").isotropic
    share_log(run["log"], run["root"] / "count.mcap", 1.0, refine=refiner)
    assert not read_map(run["root"] / "count.mcap").isotropic
