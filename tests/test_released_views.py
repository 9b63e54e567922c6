"""The views a run keeps for its final refinement hold no images between visits when the run
can read its frames again (`SlamSystem(frames=...)`, `View.source`), and the run is the same."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from gscompress.datasets.synthetic import synthetic_sequence
from gscompress.slam.config import preset
from gscompress.slam.system import SlamSystem

pytestmark = pytest.mark.slow


def run(frames: bool) -> SlamSystem:
    seq = synthetic_sequence(8, (48, 36))
    config = preset("cpu").with_overrides(**{"mapping.final_iters": 40})
    assert config.mapping.final_views == "frames"
    source = seq.frame if frames else None
    system = SlamSystem(config, seq.intrinsics, total_frames=len(seq), frames=source)
    for i in range(len(seq)):
        system.process(seq.frame(i))
    return system


def test_views_read_again_give_the_run_kept_in_memory_bit_for_bit():
    kept, read = run(frames=False), run(frames=True)
    assert [v.index for v in read.views] == list(range(8))
    assert all(v.source is not None for v in read.views)
    # after the final refinement (which reads each view when it visits it) no image is held
    assert [v.index for v in read.views if v.color.numel()] == []
    assert all(v.color.numel() > 0 for v in kept.views)
    a, b = kept.gaussian_map(), read.gaussian_map()
    assert np.array_equal(a.means, b.means) and np.array_equal(a.sh_dc, b.sh_dc)
    assert np.array_equal(a.opacity_logits, b.opacity_logits)
    assert all(np.array_equal(p, q) for p, q in zip(kept.poses, read.poses, strict=True))


def test_only_the_keyframes_used_last_hold_their_images_while_the_run_goes_on():
    seq = synthetic_sequence(12, (48, 36))
    config = preset("cpu").with_overrides(**{"keyframes.every": 2, "keyframes.window": 2})
    system = SlamSystem(config, seq.intrinsics, total_frames=None, frames=seq.frame)
    held = []
    for i in range(len(seq)):
        system.process(seq.frame(i))
        held.append([v.index for v in system.keyframes if v.color.numel()])
    assert all(len(h) <= 3 for h in held), held  # the window's 2 and the newest
    assert held[-1][-1] == 10 and len(system.keyframes) == 6
    # the frames that are not keyframes hold nothing after their own frame
    assert not system.views  # (no final refinement: none kept)


def test_a_released_view_loads_what_it_held():
    system = run(frames=True)
    view = system.views[1]
    seq = synthetic_sequence(8, (48, 36))
    view.load()
    assert torch.equal(view.color, torch.from_numpy(seq.frame(1).color.astype(np.float32)))
    view.release()
    assert view.color.numel() == 0 and view.depth.numel() == 0
