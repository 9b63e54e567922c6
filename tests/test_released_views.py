"""The views a run keeps for its final refinement hold no images between visits when the run
can read its frames again (`SlamSystem(frames=...)`, `View.source`), and the run is the same."""

from __future__ import annotations

import numpy as np
import torch

from gscompress.datasets.synthetic import synthetic_sequence
from gscompress.slam.config import preset
from gscompress.slam.keyframes import is_keyframe
from gscompress.slam.system import SlamSystem


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
    every = kept.config.keyframes
    assert [v.index for v in read.views] == list(range(8))
    for view in read.views:  # only the keyframes hold their images
        assert (view.color.numel() > 0) == is_keyframe(view.index, every), view.index
        assert (view.source is None) == is_keyframe(view.index, every)
    assert all(v.color.numel() > 0 for v in kept.views)
    a, b = kept.gaussian_map(), read.gaussian_map()
    assert np.array_equal(a.means, b.means) and np.array_equal(a.sh_dc, b.sh_dc)
    assert np.array_equal(a.opacity_logits, b.opacity_logits)
    assert all(np.array_equal(p, q) for p, q in zip(kept.poses, read.poses, strict=True))


def test_a_released_view_loads_what_it_held():
    system = run(frames=True)
    view = system.views[1]
    seq = synthetic_sequence(8, (48, 36))
    view.load()
    assert torch.equal(view.color, torch.from_numpy(seq.frame(1).color.astype(np.float32)))
    view.release()
    assert view.color.numel() == 0 and view.depth.numel() == 0
