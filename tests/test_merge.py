"""`gsc merge`: a share injected into a receiver's map keeps every Gaussian and its sums."""

from __future__ import annotations

import json
import sys
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from gscompress.datasets.synthetic import write_synthetic_sequence
from gscompress.errors import InputError, MapError
from gscompress.gaussians import GaussianMap, random_map
from gscompress.io.mcap_log import LogReader
from gscompress.io.ply import write_ply
from gscompress.ops.merge import EXACT, merge_maps
from gscompress.pipeline import import_ply, merge_logs, share_log, slam_file
from gscompress.pipeline.slam_run.options import SlamOptions
from gscompress.render import resolve_backend
from gscompress_cli.main import cli

# runs SLAM (or another minutes-long pipeline): not in `make test-fast`
pytestmark = pytest.mark.slow

STACK = EXACT


def by_id(gaussians: GaussianMap) -> GaussianMap:
    return gaussians.select(np.argsort(gaussians.ids, kind="stable"))


def test_merge_maps_keeps_every_gaussian_and_its_sums() -> None:
    receiver = random_map(50, seed=3)
    share = random_map(20, seed=4)  # its ids clash with the receiver's
    merged, offset = merge_maps(receiver, share)
    assert len(merged) == 70
    assert offset == int(receiver.ids.max()) + 1 - int(share.ids.min())  # all moved past
    assert merged.select(np.arange(50)).equals(receiver)
    tail = merged.select(np.arange(50, 70))
    assert tail.equals(replace(share, ids=share.ids + np.uint32(offset)))
    assert len(np.unique(merged.ids)) == 70

    disjoint = replace(share, ids=share.ids + np.uint32(1000))
    merged, offset = merge_maps(receiver, disjoint)
    assert offset == 0 and merged.select(np.arange(50, 70)).equals(disjoint)


@pytest.fixture(scope="module")
def agents(tmp_path_factory: pytest.TempPathFactory, seq_dir_8: Path) -> dict[str, Path]:
    root, seq = tmp_path_factory.mktemp("agents"), seq_dir_8
    a, b = root / "a.mcap", root / "b.mcap"
    slam_file(seq, a, SlamOptions(preset="tiny", frames="odd"))
    slam_file(seq, b, SlamOptions(preset="tiny", frames="even"))
    share = root / "share.mcap"
    share_log(a, share, 0.3)
    return {"seq": seq, "a": a, "b": b, "share": share, "root": root}


def test_merge_refines_and_keeps_every_gaussian_and_sum(agents: dict[str, Path]) -> None:
    out = agents["root"] / "merged.mcap"
    result = merge_logs(agents["b"], agents["share"], out, seq=agents["seq"], iters=30, merge=STACK)
    with LogReader(agents["b"]) as log:
        own = log.read_map()
    with LogReader(agents["share"]) as log:
        shared = log.read_map()
    with LogReader(out) as log:
        merged = log.read_map()
        meta = log.metadata
        counts = {c.topic: c.messages for c in log.channels}
    assert result["gaussians"] == len(merged) == len(own) + len(shared)
    offset = result["id_offset"]
    expected, _ = merge_maps(own, shared)
    # same Gaussians, same ids, same PWAS sums; the parameters were refined
    assert np.array_equal(merged.ids, expected.ids)
    for name in ("importance_sum", "importance_weight", "alpha_t_sum"):
        assert np.array_equal(getattr(merged, name), getattr(expected, name))
    assert not np.array_equal(merged.means, expected.means)
    assert result["refine_iters"] == 30 and result["refine_views"] == 4  # all of B's frames
    assert result["refine_backend"] == resolve_backend("auto", torch.device("cpu"))
    # provenance names both inputs; the receiver's poses and stats are all there
    step = meta.provenance[-1]
    assert step["parent"] == "b.mcap" and step["operation"]["share"] == "share.mcap"
    assert step["operation"]["name"] == "merge" and len(step["operation"]["share_sha256"]) == 64
    assert counts["/camera/pose"] == 4 and meta.world_frame == "ground-truth:room"
    assert offset >= 0


def test_merge_refines_on_keyframes_only_when_asked(agents: dict[str, Path]) -> None:
    out = agents["root"] / "keyframes.mcap"
    result = merge_logs(
        agents["b"],
        agents["share"],
        out,
        seq=agents["seq"],
        iters=4,
        views="keyframes",
        backend="torch",
    )
    assert result["refine_views"] == 2  # B's 4 frames, a keyframe every 2 in the tiny preset
    assert result["refine_backend"] == "torch"  # the option's, not the receiver's config's
    with LogReader(out) as log:
        assert log.metadata.provenance[-1]["operation"]["views"] == "keyframes"
    with pytest.raises(InputError, match="`views`"):
        merge_logs(
            agents["b"], agents["share"], agents["root"] / "x.mcap", seq=agents["seq"], views="all"
        )
    assert not (agents["root"] / "x.mcap").exists()


def test_merge_without_refinement_is_exact_concatenation(agents: dict[str, Path]) -> None:
    out = agents["root"] / "concat.mcap"
    merge_logs(agents["b"], agents["share"], out, iters=0, merge=STACK)
    with LogReader(agents["b"]) as log:
        own = log.read_map()
    with LogReader(agents["share"]) as log:
        shared = log.read_map()
    with LogReader(out) as log:
        assert log.read_map().equals(merge_maps(own, shared)[0])


def test_merge_refuses_unknown_or_different_world_frames(
    agents: dict[str, Path], tmp_path: Path
) -> None:
    ply = tmp_path / "other.ply"
    write_ply(random_map(10), ply)
    foreign = tmp_path / "foreign.mcap"
    import_ply(ply, foreign)
    with pytest.raises(MapError, match="unknown"):
        merge_logs(agents["b"], foreign, tmp_path / "x.mcap", iters=0)
    other_seq = write_synthetic_sequence(tmp_path / "other", 3, (64, 48), seed=2)
    other = tmp_path / "other.mcap"
    slam_file(other_seq, other, SlamOptions(preset="tiny"))
    with pytest.raises(MapError, match="not known to agree"):
        merge_logs(agents["b"], other, tmp_path / "x.mcap", iters=0)
    with pytest.raises(InputError, match="`seq`"):
        merge_logs(agents["b"], agents["share"], tmp_path / "x.mcap", iters=5)
    with pytest.raises(InputError, match="the receiver log itself"):
        merge_logs(agents["b"], agents["b"], tmp_path / "x.mcap", iters=0)
    assert not (tmp_path / "x.mcap").exists()


def test_merge_warns_of_another_sequence_name_and_refuses_other_frames(
    agents: dict[str, Path], tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    import shutil

    renamed = shutil.copytree(agents["seq"], tmp_path / "other")  # the same frames
    merge_logs(agents["b"], agents["share"], tmp_path / "x.mcap", seq=renamed, iters=1)
    assert "recorded from sequence 'room', not 'other'" in caplog.text
    other = write_synthetic_sequence(tmp_path / "room", 8, (64, 48), seed=5)  # other frames
    with pytest.raises(InputError, match=r"b\.mcap was not recorded on this room: its first frame"):
        merge_logs(agents["b"], agents["share"], tmp_path / "z.mcap", seq=other, iters=1)
    assert not (tmp_path / "z.mcap").exists()
    caplog.clear()
    merge_logs(agents["b"], agents["share"], tmp_path / "y.mcap", seq=agents["seq"], iters=1)
    assert "recorded from sequence" not in caplog.text


def test_gsc_merge_command(agents: dict[str, Path]) -> None:
    out = agents["root"] / "cli.mcap"
    args = [
        "merge",
        agents["b"],
        agents["share"],
        "--seq",
        agents["seq"],
        "-o",
        out,
        "--iters",
        "5",
        "--json",
    ]
    r = CliRunner().invoke(cli, [str(a) for a in args])
    assert r.exit_code == 0, r.output
    result = json.loads(r.output)
    assert result["refine_iters"] == 5 and Path(result["output"]) == out
    r = CliRunner().invoke(cli, [str(a) for a in args])
    assert r.exit_code == 1 and r.output.startswith("Error: ") and "--force" in r.output
    r = CliRunner().invoke(cli, [str(a) for a in args] + ["--force", "--backend", "torch"])
    assert r.exit_code == 0, r.output
    assert json.loads(r.output)["refine_backend"] == "torch"
    with LogReader(out) as log:
        operation = log.metadata.provenance[-1]["operation"]
    assert operation["backend"] == "torch" and operation["margin"] == 2.0  # the default
    r = CliRunner().invoke(cli, [str(a) for a in args] + ["--force", "--margin", "3.5"])
    assert r.exit_code == 0, r.output
    with LogReader(out) as log:
        assert log.metadata.provenance[-1]["operation"]["margin"] == 3.5
    r = CliRunner().invoke(cli, [str(a) for a in args] + ["--force", "--margin", "0.5"])
    assert r.exit_code == 2 and "--margin" in r.output


def test_gsc_merge_aligns_by_default_without_open3d(
    agents: dict[str, Path], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setitem(sys.modules, "open3d", None)  # (an import of it now fails)
    out = agents["root"] / "no_open3d.mcap"
    args = ["merge", agents["b"], agents["share"], "-o", out, "--iters", "0", "--json"]
    r = CliRunner().invoke(cli, [str(a) for a in args])
    assert r.exit_code == 0, r.output
    assert json.loads(r.output)["align_pairs"] > 0  # (aligned: the maps overlap)
    with LogReader(out) as log:
        assert log.metadata.provenance[-1]["operation"]["icp"] == "builtin"
    r = CliRunner().invoke(cli, [str(a) for a in args] + ["--force", "--icp", "open3d"])
    assert r.exit_code == 1 and len(r.output.strip().splitlines()) == 1
    assert "pip install 'gscompress[align]'" in r.output and "--no-align" in r.output


def test_transform_map_moves_means_and_orientations_rigidly() -> None:
    from gscompress.camera import invert_transform, make_transform, quat_to_rotmat
    from gscompress.ops.merge import transform_map

    gaussians = random_map(30, seed=5, isotropic=False)
    angle = 0.7
    R = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]])
    T = make_transform(R, [1.0, -2.0, 0.5])
    moved = transform_map(gaussians, T)
    np.testing.assert_allclose(moved.means, gaussians.means @ R.T + T[:3, 3], atol=1e-5)
    np.testing.assert_allclose(
        quat_to_rotmat(moved.quats), R @ quat_to_rotmat(gaussians.quats), atol=1e-6
    )
    back = transform_map(moved, invert_transform(T))
    np.testing.assert_allclose(back.means, gaussians.means, atol=1e-5)
    assert np.array_equal(back.ids, gaussians.ids) and back.log_scales is moved.log_scales
    with pytest.raises(MapError, match="rigid"):
        transform_map(gaussians, np.diag([2.0, 1.0, 1.0, 1.0]))


def test_merge_across_world_frames_with_an_explicit_transform(
    agents: dict[str, Path], tmp_path: Path
) -> None:
    from gscompress.io.trajectory import read_transform

    other_seq = write_synthetic_sequence(tmp_path / "other", 3, (64, 48), seed=2)
    other = tmp_path / "other.mcap"
    slam_file(other_seq, other, SlamOptions(preset="tiny"))
    transform = tmp_path / "T.txt"
    transform.write_text("# share frame -> receiver frame\n0.5 0 0  0 0 0 1\n")
    out = tmp_path / "merged.mcap"
    result = merge_logs(agents["b"], other, out, iters=0, share_transform=transform, merge=STACK)
    with LogReader(other) as log:
        shared = log.read_map()
    with LogReader(out) as log:
        merged = log.read_map()
        step = log.metadata.provenance[-1]["operation"]
    tail = merged.select(np.arange(result["receiver"], len(merged)))
    np.testing.assert_allclose(tail.means, shared.means + np.array([0.5, 0, 0]), atol=1e-6)
    assert step["share_world_frame"] == "ground-truth:other" and step["transform"][0][3] == 0.5
    for text, message in (
        ("1 2 3", "expected 16 numbers"),
        ("a b", "numbers only"),
        ("0 0 0 0 0 0 0", "quaternion qx qy qz qw is zero"),
        ("2 0 0 0  0 2 0 0  0 0 2 0  0 0 0 1", "not a rotation"),  # a scale
        ("-1 0 0 0  0 1 0 0  0 0 1 0  0 0 0 1", "not a rotation"),  # a mirror
    ):
        transform.write_text(text)
        with pytest.raises(InputError, match=message):
            read_transform(transform)
    transform.write_text("0 -1 0 0.1  1 0 0 0.2  0 0 1 0.3  0 0 0 1")  # 90 degrees about z
    np.testing.assert_allclose(read_transform(transform)[:3, 3], [0.1, 0.2, 0.3])
    c, s = np.cos(np.pi / 6), np.sin(np.pi / 6)  # 30 degrees written to 4 decimals
    transform.write_text(f"{c:.4f} {-s:.4f} 0 0  {s:.4f} {c:.4f} 0 0  0 0 1 0  0 0 0 1")
    R = read_transform(transform)[:3, :3]  # taken as the rotation it rounds
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(R[:2, :2], [[c, -s], [s, c]], atol=1e-4)


def test_refinement_loss_is_compared_on_the_same_views(agents: dict[str, Path]) -> None:
    """The reported losses are means over all the views before and after refining: the one
    before depends on the map and views only, not on how long the refinement runs."""
    b, share, seq = agents["b"], agents["share"], agents["seq"]
    runs = [
        merge_logs(b, share, agents["root"] / f"loss{n}.mcap", seq=seq, iters=n) for n in (1, 40)
    ]
    assert runs[0]["refine_loss_before"] == runs[1]["refine_loss_before"]
    assert runs[1]["refine_loss_after"] < 0.9 * runs[1]["refine_loss_before"]
    assert runs[1]["refine_loss_after"] < runs[0]["refine_loss_after"]


def test_gsc_merge_usage_errors_and_sigterm(
    agents: dict[str, Path], tmp_path: Path, terminated: Any
) -> None:
    """Options that do not go together exit 2 naming merge's help; SIGTERM while refining ends
    with 130 and leaves neither the output nor its temporary file."""
    out = tmp_path / "m.mcap"
    base = ["merge", str(agents["b"]), str(agents["share"]), "-o", str(out)]
    r = CliRunner().invoke(cli, [*base, "--iters", "5"])
    assert r.exit_code == 2 and "pass --seq" in r.output and "merge --help" in r.output
    r = CliRunner().invoke(
        cli, ["merge", str(agents["b"]), str(agents["b"]), "-o", str(out), "--iters", "0"]
    )
    assert r.exit_code == 2 and "the receiver log itself" in r.output
    cmd = [
        sys.executable,
        "-m",
        "gscompress_cli",
        *base,
        "--seq",
        str(agents["seq"]),
        "--iters",
        "100000",
    ]

    def refining(stderr: str) -> bool:  # after torch's import: its output is open, unfinished
        return "refine:" in stderr and any(tmp_path.glob(".m.mcap.*.tmp"))

    code, stderr = terminated(cmd, refining)
    assert code == 130 and "Interrupted" in stderr.splitlines()[-1], stderr
    assert list(tmp_path.iterdir()) == []


def test_refinement_learning_rates_decay_to_the_fraction_and_are_restored(
    agents: dict[str, Path], monkeypatch: pytest.MonkeyPatch
) -> None:
    """Every rate falls geometrically from its mapping value to lr_final times it at the last
    iteration; the optimizer's rates are the mapping ones again afterwards. The merge records
    the fraction, and a fraction outside (0, 1] is a usage error."""
    from gscompress.slam.params import Adam

    seen: list[list[float]] = []
    optimizers: list[Adam] = []
    step = Adam.step

    def recording_step(self: Adam) -> None:
        seen.append([group["lr"] for group in self.param_groups])
        if self not in optimizers:
            optimizers.append(self)
        step(self)

    monkeypatch.setattr(Adam, "step", recording_step)
    out = agents["root"] / "decay.mcap"
    merge_logs(agents["b"], agents["share"], out, seq=agents["seq"], iters=5, lr_final=0.01)
    rates = np.array(seen)
    assert rates.shape[0] == 5
    ratios = rates / rates[0]
    assert np.allclose(ratios, np.logspace(0, -2, 5)[:, None])  # 1, 0.316, 0.1, 0.0316, 0.01
    (optimizer,) = optimizers
    assert [g["lr"] for g in optimizer.param_groups] == list(rates[0])
    with LogReader(out) as log:
        assert log.metadata.provenance[-1]["operation"]["lr_final"] == 0.01
    seen.clear()
    merge_logs(
        agents["b"], agents["share"], out, seq=agents["seq"], iters=3, lr_final=1.0, force=True
    )
    assert np.all(np.array(seen) == np.array(seen)[0])  # constant, exactly
    # an exception part-way leaves the optimizer at its mapping rates
    from gscompress.slam.mapper import Mapper

    calls: list[tuple[Mapper, list[float]]] = []

    def failing_step(self: Mapper, view: Any, stats: Any, pose_rate: Any = None) -> None:
        calls.append((self, [group["lr"] for group in self.optimizer.param_groups]))
        if len(calls) == 2:
            raise RuntimeError("step failed")

    monkeypatch.setattr(Mapper, "_step", failing_step)
    with pytest.raises(RuntimeError, match="step failed"):
        merge_logs(
            agents["b"], agents["share"], out, seq=agents["seq"], iters=3, lr_final=0.1, force=True
        )
    (mapper, first), (_, second) = calls
    assert second != first and [g["lr"] for g in mapper.optimizer.param_groups] == first
    base = ["merge", str(agents["b"]), str(agents["share"]), "-o", str(agents["root"] / "x.mcap")]
    for bad in ("0", "1.5"):
        r = CliRunner().invoke(cli, [*base, "--lr-final", bad])
        assert r.exit_code == 2 and "--lr-final" in r.output, r.output
