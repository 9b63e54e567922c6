"""An agent on a scene whose truth is exact moves and turns as far as its camera did (the
motion bias: docs/drift.md). Open: this test fails until the bias is removed."""

from __future__ import annotations

import numpy as np
import pytest

from gscompress.camera import invert_transform, rotation_angle_deg
from gscompress.datasets.synthetic import synthetic_sequence
from gscompress.slam.config import preset
from gscompress.slam.system import SlamSystem

FRAMES = 21
"""The agent's first 20 steps, as the bias is judged (`bench/drift.py --at 20`)."""


def motion(first: np.ndarray, last: np.ndarray) -> tuple[float, float]:
    """The distance (m) and angle (degrees) from pose `first` to pose `last`."""
    step = invert_transform(first) @ last
    return float(np.linalg.norm(step[:3, 3])), rotation_angle_deg(step[:3, :3])


@pytest.mark.slow
@pytest.mark.xfail(
    strict=True, reason="open: an agent travels 0.97-0.98 of the true distance (docs/drift.md)"
)
def test_an_agent_moves_and_turns_as_far_as_the_camera_on_an_exact_scene() -> None:
    # make demo's room (160x120, supersampled twice), the cpu preset; the final refinement
    # moves no pose, so it is left out.
    seq = synthetic_sequence(FRAMES, (160, 120), supersample=2)
    config = preset("cpu").with_overrides(**{"mapping.final_iters": 0})
    system = SlamSystem(config, seq.intrinsics, total_frames=FRAMES, frames=seq.frame)
    truth = []
    for i in range(FRAMES):
        frame = seq.frame(i)
        assert frame.T_world_cam is not None
        truth.append(frame.T_world_cam)
        system.process(frame)
    moved, turned = motion(system.poses[0], system.poses[-1])
    true_move, true_turn = motion(truth[0], truth[-1])
    assert true_move > 0.05 and true_turn > 1.0  # (a motion both ratios describe)
    assert abs(moved / true_move - 1) <= 0.01, moved / true_move
    assert abs(turned / true_turn - 1) <= 0.01, turned / true_turn
