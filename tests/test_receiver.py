"""A receiver-aware share (`gsc share --for`): what the receiver has not seen goes first."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from gscompress.camera import Intrinsics, make_transform
from gscompress.errors import BudgetError, InputError
from gscompress.gaussians import GaussianMap
from gscompress.io.mcap_log import LogMetadata, LogReader, LogWriter, read_map
from gscompress.ops.budget import Budget
from gscompress.pipeline.share import share_log
from gscompress.pipeline.share.cut import ShareCut
from gscompress.pipeline.share.options import ShareOptions
from gscompress.pipeline.share.receiver import read_request, unseen_ids
from gscompress.selection import top_k, top_k_first
from gscompress_cli.main import cli

CAMERA = Intrinsics(40.0, 40.0, 16.0, 12.0, 32, 24)
WORLD = "ground-truth:room"


def two_walls() -> GaussianMap:
    """Two walls of 4x4 opaque Gaussians: ids 0-15 at z = +2 m (in front of a camera at the
    origin looking down +z), ids 16-31 at z = -2 m (behind it). The front wall scores higher."""
    grid = np.stack(np.meshgrid(np.linspace(-0.3, 0.3, 4), np.linspace(-0.3, 0.3, 4)), -1)
    xy = grid.reshape(-1, 2)
    means = np.concatenate([np.c_[xy, np.full(16, 2.0)], np.c_[xy, np.full(16, -2.0)]])
    n = len(means)
    return GaussianMap.new(
        means=means,
        log_scales=np.full((n, 1), np.log(0.08)),
        quats=np.tile([1.0, 0.0, 0.0, 0.0], (n, 1)),
        opacity_logits=np.full(n, 4.0),
        sh_dc=np.zeros((n, 3)),
        importance_sum=np.r_[np.full(16, 10.0), np.full(16, 1.0)] + np.arange(n) * 1e-3,
        importance_weight=np.ones(n),
        alpha_t_sum=np.ones(n),
    )


def write_log(
    path: Path, *, gaussians: GaussianMap | None, poses: list[np.ndarray], world: str = WORLD
) -> Path:
    with LogWriter(path, LogMetadata(sequence="room", world_frame=world)) as out:
        out.write_calibration(CAMERA, 0)
        for i, T in enumerate(poses):
            out.write_pose(T, (i + 1) * 10**8)
        if gaussians is not None:
            out.write_gaussians(gaussians, len(poses) * 10**8)
    return path


@pytest.fixture
def agents(tmp_path: Path) -> dict[str, Path]:
    """A: the two walls, seen from both sides; B: a camera at the origin that saw only the
    front wall."""
    behind = make_transform(np.diag([-1.0, 1.0, -1.0]), np.zeros(3))  # looking down -z
    a = write_log(tmp_path / "a.mcap", gaussians=two_walls(), poses=[np.eye(4), behind])
    b = write_log(tmp_path / "b.mcap", gaussians=None, poses=[np.eye(4), np.eye(4)])
    return {"a": a, "b": b, "root": tmp_path}


def test_marked_entries_rank_above_the_rest_each_group_in_score_order():
    scores = np.array([5.0, 1.0, 4.0, 3.0, 2.0])
    ids = np.arange(5)
    first = np.array([False, True, False, False, True])
    assert top_k_first(scores, ids, 1, first).tolist() == [4]
    assert top_k_first(scores, ids, 2, first).tolist() == [1, 4]
    assert top_k_first(scores, ids, 3, first).tolist() == [0, 1, 4]
    none = np.zeros(5, bool)
    assert top_k_first(scores, ids, 3, none).tolist() == top_k(scores, ids, 3).tolist()
    with pytest.raises(InputError, match="preferred set"):
        top_k_first(scores, ids, 2, first[:3])


def test_the_wall_behind_the_receiver_is_unseen(agents):
    request = read_request(agents["b"])
    assert len(request.poses) == 2 and request.intrinsics == CAMERA
    assert sorted(unseen_ids(two_walls(), request).tolist()) == list(range(16, 32))
    # turned around by a transform between the frames, the receiver sees the back wall
    half_turn = make_transform(np.diag([-1.0, 1.0, -1.0]), np.zeros(3))
    assert sorted(unseen_ids(two_walls(), request, half_turn).tolist()) == list(range(16))


def test_a_share_for_the_receiver_sends_what_it_has_not_seen(agents):
    plain = share_log(
        agents["a"], agents["root"] / "plain.mcap", 0.5, ShareOptions(fold=False, ids=True)
    )  # (the ids say which were sent)
    aware = share_log(
        agents["a"],
        agents["root"] / "for_b.mcap",
        0.5,
        ShareOptions(fold=False, ids=True),
        receiver=agents["b"],
    )
    assert sorted(read_map(plain["output"]).ids.tolist()) == list(range(16))
    assert sorted(read_map(aware["output"]).ids.tolist()) == list(range(16, 32))
    assert aware["unseen"] == 16 and aware["views"] == 2 and aware["for"] == "b.mcap"
    with LogReader(aware["output"]) as log:
        step = log.metadata.provenance[-1]["operation"]
    assert step["for"]["request_bytes"] == aware["request_bytes"] > 0


def test_the_request_counts_in_a_byte_budget(agents):
    request_bytes = len(read_request(agents["b"]).data)
    assert request_bytes == 4 * (6 + 2 * 7)
    fp32 = ShareOptions(fold=False, codec="fp32")  # (76 B a Gaussian: the request takes 2)
    whole = share_log(agents["a"], agents["root"] / "w.mcap", "9999B", fp32)
    assert whole["selected"] == 32
    counted = ShareCut(agents["a"], Budget.parse("9999B"), fp32).size(32)  # (names at a size)
    assert whole["file_bytes"] <= counted
    budget = counted + 10  # holds the whole map, but not with the request
    plain = share_log(agents["a"], agents["root"] / "p.mcap", f"{budget}B", fp32)
    aware = share_log(
        agents["a"], agents["root"] / "f.mcap", f"{budget}B", fp32, receiver=agents["b"]
    )
    assert plain["selected"] == 32 > aware["selected"]
    assert aware["file_bytes"] + request_bytes <= budget
    with pytest.raises(BudgetError, match="request"):
        share_log(agents["a"], agents["root"] / "x.mcap", f"{request_bytes}B", receiver=agents["b"])


def test_a_receiver_in_another_frame_is_refused_without_alignment(agents):
    other = write_log(
        agents["root"] / "c.mcap", gaussians=None, poses=[np.eye(4)], world="first-camera:room:0"
    )
    with pytest.raises(InputError, match="`align_to`"):
        share_log(agents["a"], agents["root"] / "c_share.mcap", 0.5, receiver=other)
    no_poses = write_log(agents["root"] / "d.mcap", gaussians=None, poses=[])
    with pytest.raises(InputError, match="/camera/pose"):
        share_log(agents["a"], agents["root"] / "d_share.mcap", 0.5, receiver=no_poses)


def test_share_cli_for_a_receiver(agents):
    out = agents["root"] / "cli.mcap"
    args = ["share", str(agents["a"]), str(out), "--budget", "0.25", "--for", str(agents["b"])]
    r = CliRunner().invoke(cli, [*args, "--no-fold", "--ids"])
    assert r.exit_code == 0, r.output
    assert "unseen by b.mcap first (16 of them" in r.output
    assert set(read_map(out).ids.tolist()) <= set(range(16, 32))
