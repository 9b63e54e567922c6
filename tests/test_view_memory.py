"""What a run keeps of its views does not grow with its frames: released views share one empty
pair, so that only the keyframes the mapping used last hold tensors of their own (a release that
allocated a new pair per view left the heap fragmented by every view the final refinement
visited: docs/recordings.md, "Streaming and memory")."""

from __future__ import annotations

import functools

import numpy as np
import pytest
import torch
from bounded import rss_bytes

from gscompress.datasets.synthetic import synthetic_sequence
from gscompress.pipeline.slam_run import _malloc_trim, release_free_heap
from gscompress.slam.config import final_iterations, preset
from gscompress.slam.keyframes import HeldImages, View
from gscompress.slam.system import RELEASE_EVERY, SlamSystem


def view_tensors(views: list[View]) -> set[int]:
    """The distinct tensors (by id) that `views` hold: colour, depth and depth edges."""
    return {id(t) for v in views for t in (v.color, v.depth, *v._edges.values())}


def test_released_views_hold_one_shared_empty_pair() -> None:
    seq = synthetic_sequence(6, (32, 24))
    images = HeldImages(seq.frame, torch.device("cpu"), capacity=2)
    views = [
        images.sourced(View.from_frame(i, seq.frame(i), np.eye(4), images.device))
        for i in range(len(seq))
    ]
    for _ in range(3):  # visits, as the final refinement makes them
        for view in views:
            view.load().edges(1.0)
            view.release()
    assert all(v.color.numel() == 0 and v.depth.numel() == 0 for v in views)
    assert view_tensors(views) == view_tensors(views[:1])  # one pair, whatever the views
    images.hold(views[-2:])
    assert len(view_tensors(views)) == 2
    assert torch.equal(views[3].load().color, torch.from_numpy(seq.frame(3).color))


def run_census(frames: int) -> list[int]:
    """Distinct tensors held by the views of a run with a final refinement on every frame,
    after each frame (the last after the refinement)."""
    seq = synthetic_sequence(frames, (32, 24))
    config = preset("tiny").with_overrides(
        **{"mapping.final_iters": 2 * frames, "mapping.final_views": "frames"}
    )
    system = SlamSystem(config, seq.intrinsics, total_frames=frames, frames=seq.frame)
    counts = []
    for i in range(frames):
        system.process(seq.frame(i))
        counts.append(len(view_tensors([*system.views, *system.keyframes])))
    assert len(system.views) == frames
    return counts


def test_the_views_a_run_keeps_hold_no_more_tensors_with_more_frames() -> None:
    window = preset("tiny").keyframes.window
    short, long = run_census(6), run_census(16)
    bound = 3 * (window + 1) + 2  # the held keyframes' images and edges, the empty pair
    assert max(short) <= bound and max(long) <= bound, (short, long)
    assert short[-1] == long[-1] == 2  # after the refinement, every view released


@pytest.mark.skipif(_malloc_trim() is None, reason="needs glibc's malloc_trim")
def test_free_heap_goes_back_to_the_system() -> None:
    # 2,000 blocks of 64 kB come from the heap (below glibc's mmap threshold); with the last
    # one kept, freeing the others leaves 125 MB of free heap in the process, which
    # release_free_heap hands back.
    blocks = [np.ones(8192) for _ in range(2000)]
    last = blocks[-1]
    del blocks
    before = rss_bytes()
    release_free_heap()
    assert before - rss_bytes() > 60 * 2**20
    assert last.sum() == 8192


def test_a_refinement_hands_the_heap_back_every_few_iterations() -> None:
    # the final refinement, one frame's work over every view, hands back what the views'
    # visits freed every RELEASE_EVERY iterations; the map is the same as without
    frames = 4
    seq = synthetic_sequence(frames, (32, 24))
    config = preset("tiny").with_overrides(**{"mapping.final_iters": 25})
    maps, calls = [], []
    for release in (False, True):
        system = SlamSystem(config, seq.intrinsics, total_frames=frames, frames=seq.frame)
        if release:
            system.release = functools.partial(lambda s: calls.append(len(s.poses)), system)
        for i in range(frames):
            system.process(seq.frame(i))
        maps.append(system.gaussian_map())
    refined = final_iterations(config.mapping, frames)
    assert refined >= RELEASE_EVERY
    assert calls == [frames - 1] * (refined // RELEASE_EVERY)  # in the last frame's refinement
    assert maps[0].equals(maps[1])


def test_gsc_slam_hands_the_heap_back_after_each_frame_and_in_its_end(monkeypatch, tmp_path):
    import gscompress.pipeline.slam_run as slam_run

    calls: list[None] = []
    monkeypatch.setattr(slam_run, "release_free_heap", lambda: calls.append(None))
    frames = 12
    config = preset("tiny").with_overrides(**{"mapping.final_iters": 25})
    slam_run.slam_file(
        None, tmp_path / "run.mcap", config=config, sequence=synthetic_sequence(frames, (32, 24))
    )
    refined = final_iterations(config.mapping, frames)
    # after each frame, in the final refinement and in the final scoring (a view each)
    assert len(calls) == frames + refined // RELEASE_EVERY + frames // RELEASE_EVERY


def test_the_poses_a_run_keeps_come_from_one_block_not_one_array_a_frame() -> None:
    # a pose array made per frame and kept to the end splits the heap's free space where it
    # lands (docs/recordings.md, "Streaming and memory"): they come a block at a time
    frames = 6
    seq = synthetic_sequence(frames, (32, 24))
    system = SlamSystem(preset("tiny"), seq.intrinsics, total_frames=frames, frames=seq.frame)
    results = [system.process(seq.frame(i)) for i in range(frames)]
    assert all(p.base is not None for p in system.poses)
    assert len({id(p.base) for p in system.poses}) == 1
    assert all(r.T_world_cam is p for r, p in zip(results, system.poses, strict=True))
    assert np.array_equal(system.poses[0], seq.frame(0).T_world_cam)
