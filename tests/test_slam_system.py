"""The SLAM core on a tiny synthetic sequence: tracking, mapping, densification, pruning."""

from dataclasses import replace

import numpy as np
import pytest
import torch

from gscompress.camera import invert_transform, make_transform, quat_to_rotmat
from gscompress.datasets.synthetic import synthetic_sequence
from gscompress.errors import BudgetError, DivergenceError, InputError, MapError
from gscompress.gaussians import SH_C0, random_map
from gscompress.render import render
from gscompress.selection import STRATEGIES, keep_count, strategy_scores
from gscompress.slam.config import TrackingConfig, final_iterations, preset, stage_positions
from gscompress.slam.densify import densification_mask, gaussians_from_rgbd, rendered_footprint
from gscompress.slam.keyframes import View, overlap_fraction, sample_points, select_window
from gscompress.slam.mapper import Mapper
from gscompress.slam.params import GaussianParams
from gscompress.slam.poses import PoseAdam, orthonormalize, pose_gradient, pose_increment
from gscompress.slam.system import SlamSystem
from gscompress.slam.tracker import constant_velocity, track

# runs SLAM (or another minutes-long pipeline): not in `make test-fast`
pytestmark = pytest.mark.slow

SIZE = (64, 48)


@pytest.fixture(scope="module")
def seq():
    return synthetic_sequence(6, SIZE)


def pose_error(T, T_ref):
    """(translation error in cm, rotation error in degrees)."""
    d = invert_transform(T_ref) @ T
    angle = np.degrees(np.arccos(np.clip((np.trace(d[:3, :3]) - 1) / 2, -1, 1)))
    return 100 * np.linalg.norm(T[:3, 3] - T_ref[:3, 3]), angle


def test_tracking_recovers_a_small_pose_perturbation(seq):
    # The map is frame 0 back-projected at its true pose, and the observation is that map
    # rendered at the true pose, so the loss is minimal exactly there; the tracker starts
    # 1.8 cm and 0.8 degrees away.
    frame = seq.frame(0)
    g = gaussians_from_rgbd(
        frame.color, frame.depth, seq.intrinsics, frame.T_world_cam, opacity=0.99
    )
    inputs = GaussianParams.from_map(g).render_inputs()
    with torch.no_grad():
        T_cam_world = torch.tensor(invert_transform(frame.T_world_cam), dtype=torch.float32)
        observed = render(*inputs, seq.intrinsics, T_cam_world)
    axis = np.array([0.3, -0.8, 0.5]) / np.linalg.norm([0.3, -0.8, 0.5])
    half = np.deg2rad(0.8) / 2
    R = quat_to_rotmat(np.array([np.cos(half), *(np.sin(half) * axis)]))
    guess = frame.T_world_cam @ make_transform(R, [0.012, -0.008, 0.01])
    config = TrackingConfig(iters=40, lr_rotation=2e-3, lr_translation=2e-3)
    result = track(inputs, observed.color, observed.depth_normalized, seq.intrinsics, guess, config)
    t0, r0 = pose_error(guess, frame.T_world_cam)
    t1, r1 = pose_error(result.T_world_cam, frame.T_world_cam)
    assert t1 < t0 / 5 and r1 < r0 / 5, (t0, r0, t1, r1)
    assert result.loss < result.first_loss / 3 and result.iters == 40


def test_constant_velocity_repeats_the_last_motion():
    a = make_transform(np.eye(3), [0.0, 0, 0])
    R = quat_to_rotmat(np.array([np.cos(0.05), 0, np.sin(0.05), 0]))
    b = a @ make_transform(R, [0.1, 0, 0])
    c = constant_velocity(b, a)
    np.testing.assert_allclose(invert_transform(b) @ c, invert_transform(a) @ b, atol=1e-12)
    np.testing.assert_allclose(constant_velocity(b, None), b, atol=1e-15)


def test_constant_velocity_stays_rigid_over_a_long_run():
    # rounding error in chained poses must not grow (it did, geometrically, before the
    # rotation was projected back onto SO(3))
    R = quat_to_rotmat(np.array([np.cos(0.01), 0.3 * np.sin(0.01), np.sin(0.01), 0]))
    step = make_transform(R * (1 + 1e-12), [0.01, 0.002, 0.0])
    poses = [np.eye(4), step]
    for _ in range(300):
        poses.append(constant_velocity(poses[-1], poses[-2]))
    R_last = poses[-1][:3, :3]
    np.testing.assert_allclose(R_last.T @ R_last, np.eye(3), atol=1e-12)
    assert np.linalg.det(orthonormalize(np.diag([1.0, 1.0, -1.0, 1.0]))[:3, :3]) > 0


def test_pose_gradient_matches_finite_differences():
    # L(x) = sum(W * (pose_increment(x) @ T0)): dL/dT = W, so pose_gradient must give dL/dx
    rng = np.random.default_rng(3)
    T0 = make_transform(quat_to_rotmat(rng.normal(size=4)), rng.normal(size=3))
    W = rng.normal(size=(4, 4))
    for x in (np.zeros(6), rng.normal(0, 0.2, 6)):
        h = 1e-6
        numeric = [
            (
                np.sum(W * (pose_increment(x + h * e) @ T0))
                - np.sum(W * (pose_increment(x - h * e) @ T0))
            )
            / (2 * h)
            for e in np.eye(6)
        ]
        np.testing.assert_allclose(pose_gradient(x, T0, W), numeric, rtol=1e-6, atol=1e-8)


def test_pose_adam_follows_torch_adam_and_exponential_lr():
    rng = np.random.default_rng(4)
    grads = rng.normal(size=(25, 6)) * np.logspace(-4, 1, 6)
    lr, gamma = np.array([2e-3, 2e-3, 2e-3, 1e-3, 1e-3, 1e-3]), 0.93
    q = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    tau = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    optimizer = torch.optim.Adam([{"params": [q], "lr": 2e-3}, {"params": [tau], "lr": 1e-3}])
    scheduler = torch.optim.lr_scheduler.ExponentialLR(optimizer, gamma)
    adam, x = PoseAdam(lr, gamma), np.zeros(6)
    for g in grads:
        q.grad, tau.grad = torch.tensor(g[:3]), torch.tensor(g[3:])
        optimizer.step()
        scheduler.step()
        x = adam.step(x, g)
        np.testing.assert_allclose(x, torch.cat([q, tau]).detach().numpy(), rtol=1e-12, atol=1e-16)


def test_mapping_reduces_the_loss(seq):
    config = preset("tiny")
    frame = seq.frame(0)
    g = gaussians_from_rgbd(frame.color, frame.depth, seq.intrinsics, frame.T_world_cam)
    rng = np.random.default_rng(0)
    g.sh_dc += rng.normal(0, 0.5, g.sh_dc.shape).astype(np.float32)  # wrong colours
    mapper = Mapper(config, seq.intrinsics, torch.device("cpu"))
    mapper.add(g)
    view = View(0, torch.from_numpy(frame.color), torch.from_numpy(frame.depth), frame.T_world_cam)
    stats = mapper.optimize(view, [], 30, rng)
    assert stats.iters == 30 and mapper.iterations == 30
    assert stats.last_loss < 0.7 * stats.first_loss


def test_a_map_that_diverged_stops_the_mapping_and_the_tracking(seq):
    frame = seq.frame(0)
    g = gaussians_from_rgbd(frame.color, frame.depth, seq.intrinsics, frame.T_world_cam)
    view = View(0, torch.from_numpy(frame.color), torch.from_numpy(frame.depth), frame.T_world_cam)
    mapper = Mapper(preset("tiny"), seq.intrinsics, torch.device("cpu"))
    mapper.add(g)
    with torch.no_grad():
        mapper.params.sh_dc[3] = float("nan")
    before = mapper.params.means.detach().clone()
    with pytest.raises(DivergenceError, match=r"mapping diverged \(its loss became nan\): .*lr_"):
        mapper.optimize(view, [], 5, np.random.default_rng(0))
    assert torch.equal(mapper.params.means.detach(), before)  # no step was taken with it
    with pytest.raises(DivergenceError, match="mapping diverged"):
        mapper.refine([view], 5, np.random.default_rng(0))
    with pytest.raises(DivergenceError, match="tracking diverged"):
        track(
            mapper.params.render_inputs(),
            view.color,
            view.depth,
            seq.intrinsics,
            frame.T_world_cam,
            preset("tiny").tracking,
        )


def test_a_step_that_leaves_an_infinity_in_the_map_is_caught_at_once(seq, monkeypatch):
    frame = seq.frame(0)
    g = gaussians_from_rgbd(frame.color, frame.depth, seq.intrinsics, frame.T_world_cam)
    view = View(0, torch.from_numpy(frame.color), torch.from_numpy(frame.depth), frame.T_world_cam)
    mapper = Mapper(preset("tiny"), seq.intrinsics, torch.device("cpu"))
    mapper.add(g)
    step = mapper.optimizer.step

    def overflowing_step() -> None:
        step()
        with torch.no_grad():
            mapper.params.log_scales[0] = float("inf")

    monkeypatch.setattr(mapper.optimizer, "step", overflowing_step)
    with pytest.raises(DivergenceError, match=r"\(log_scales hold non-finite values\)"):
        mapper.optimize(view, [], 1, np.random.default_rng(0))  # the last step: no next loss


def test_a_stage_with_nothing_scored_says_what_went_wrong(seq):
    config = replace(preset("tiny"), pwas=replace(preset("tiny").pwas, sigma_d=1e-4))
    system = SlamSystem(config, seq.intrinsics, "cpu", total_frames=len(seq))
    with pytest.raises(BudgetError, match="pruning stage 1: none of the map's Gaussians has a pw"):
        for i in range(len(seq)):
            system.process(seq.frame(i))


def test_cleanup_removes_transparent_and_huge_gaussians(seq):
    config = preset("tiny")
    frame = seq.frame(0)
    g = gaussians_from_rgbd(frame.color, frame.depth, seq.intrinsics, frame.T_world_cam)
    g.opacity_logits[:10] = -8.0  # opacity 3e-4 < 0.005
    g.log_scales[10:13] = np.log(5.0)
    mapper = Mapper(config, seq.intrinsics, torch.device("cpu"))
    mapper.add(g)
    mapper.scene_radius = 1.0
    assert mapper.cleanup() == 13
    assert set(mapper.params.ids.tolist()) == set(g.ids[13:].tolist())


def test_refinement_ends_removing_transparent_but_not_huge_gaussians(seq):
    frame = seq.frame(0)
    g = gaussians_from_rgbd(frame.color, frame.depth, seq.intrinsics, frame.T_world_cam)
    g.opacity_logits[:10] = -30.0  # stays transparent after one step
    g.log_scales[10:13] = np.log(5.0)
    mapper = Mapper(preset("tiny"), seq.intrinsics, torch.device("cpu"))
    mapper.add(g)
    mapper.scene_radius = 1.0
    view = View(0, torch.from_numpy(frame.color), torch.from_numpy(frame.depth), frame.T_world_cam)
    stats = mapper.refine([view], 1, np.random.default_rng(0))
    assert stats.removed == 10 and set(mapper.params.ids.tolist()) == set(g.ids[10:].tolist())


def test_densification_mask_rule():
    depth = np.full((4, 6), 2.0, np.float32)
    depth[0, 0] = 0.0
    silhouette = np.ones((4, 6))
    silhouette[1, :2] = 0.2
    rendered = depth + np.float32(0.001) * np.arange(24, dtype=np.float32).reshape(4, 6)
    rendered[3, 5] = 3.0  # observed surface 1 m in front of the map
    rendered[2, 5] = 1.0  # observed surface behind the map: not added
    mask = densification_mask(silhouette, rendered, depth, depth_error_factor=50.0)
    expected = np.zeros((4, 6), bool)
    expected[1, :2] = True
    expected[3, 5] = True
    np.testing.assert_array_equal(mask, expected)

    residual = np.zeros((4, 6), np.float32)
    residual[0, 0] = residual[1, 0] = residual[0, 3] = 0.5  # no depth; empty; covered
    residual[0, 4] = 0.1499  # just below the threshold
    residual[0, 5] = 0.15
    with_color = densification_mask(
        silhouette, rendered, depth, color_residual=residual, color_error=0.15
    )
    expected[0, 3] = expected[0, 5] = True
    np.testing.assert_array_equal(with_color, expected)
    footprint = np.full((4, 6), 2.0)
    footprint[0, 3] = 1.0  # as fine as a new Gaussian: colour adds nothing there
    with_footprint = densification_mask(
        silhouette,
        rendered,
        depth,
        color_residual=residual,
        color_error=0.15,
        footprint=footprint,
        min_footprint=1.0,
    )
    expected[0, 3] = False
    np.testing.assert_array_equal(with_footprint, expected)
    with pytest.raises(ValueError, match="color_residual"):
        densification_mask(silhouette, rendered, depth, color_error=0.15)


def test_keyframe_overlap_and_window(seq):
    f0, f5 = seq.frame(0), seq.frame(5)
    rng = np.random.default_rng(0)
    points = sample_points(f0.depth, seq.intrinsics, f0.T_world_cam, 500, rng)
    assert len(points) == 500
    assert overlap_fraction(points, seq.intrinsics, f0.T_world_cam) == 1.0
    away = f0.T_world_cam @ make_transform(quat_to_rotmat(np.array([0.0, 1, 0, 0])), [0, 0, 0])
    assert overlap_fraction(points, seq.intrinsics, away) == 0.0
    assert 0.5 < overlap_fraction(points, seq.intrinsics, f5.T_world_cam) < 1.0

    def view(i, T):
        return View(i, torch.zeros(SIZE[1], SIZE[0], 3), torch.from_numpy(f0.depth), T)

    keyframes = [view(0, f0.T_world_cam), view(1, away), view(2, f5.T_world_cam), view(3, away)]
    config = preset("tiny").keyframes
    window = select_window(keyframes, view(9, f0.T_world_cam), seq.intrinsics, config, rng)
    assert [kf.index for kf in window] == [3, 0, 2]  # latest always, then by overlap, no zeros


def test_stage_positions():
    assert stage_positions(6, (1 / 3, 2 / 3)) == {1: 1, 3: 2}
    assert stage_positions(60, (1 / 3, 2 / 3)) == {19: 1, 39: 2}
    assert stage_positions(2, (0.1, 0.2)) == {0: 1}
    assert stage_positions(10, ()) == {}


def test_a_map_over_its_size_is_pruned_after_the_frame(seq):
    # No stage in the schedule: only the map's size places one, after each frame that leaves
    # the map over the cap, so that no frame ends with more than it.
    free = preset("tiny").with_overrides(**{"prune.stages": ()})
    system = SlamSystem(free, seq.intrinsics, total_frames=len(seq))
    sizes = [system.process(seq.frame(i)).gaussians for i in range(4)]
    cap = (sizes[0] + sizes[1]) // 2  # over it from the second frame on
    capped = SlamSystem(
        free.with_overrides(**{"prune.max_gaussians": cap}), seq.intrinsics, total_frames=len(seq)
    )
    results = [capped.process(seq.frame(i)) for i in range(4)]
    assert results[0].event is None and results[0].gaussians == sizes[0]
    assert results[1].event == "prune-size" and results[1].removed > 0
    assert all(r.gaussians <= cap for r in results)
    with pytest.raises(InputError, match="max_gaussians"):
        free.with_overrides(**{"prune.max_gaussians": -1})


def test_system_runs_and_prunes_exactly_the_top_fraction(seq):
    config = preset("tiny").with_overrides(**{"prune.stages": ()})
    system = SlamSystem(config, seq.intrinsics, total_frames=len(seq))
    results = [system.process(seq.frame(i)) for i in range(3)]
    assert [r.position for r in results] == [0, 1, 2] and len(system.poses) == 3
    assert results[0].keyframe and results[0].tracking is None and results[1].tracking
    assert all(r.event is None for r in results)
    assert set(results[0].ms) >= {"tracking", "densification", "mapping", "pwas", "pruning"}
    before = system.gaussian_map()
    assert before.has_importance and len(before) == results[-1].gaussians
    assert np.all(before.importance_weight > 0)  # every Gaussian was seen at least once
    removed = system.prune_to(0.3)
    after = system.gaussian_map()
    assert len(after) == keep_count(len(before), 0.3) == len(before) - removed
    order = np.lexsort((before.ids, -before.importance.astype(np.float64)))
    np.testing.assert_array_equal(np.sort(after.ids), np.sort(before.ids[order[: len(after)]]))
    # the optimizer still matches the map and the next frame works
    assert system.mapper.optimizer.param_groups[0]["params"][0] is system.mapper.params.means
    result = system.process(seq.frame(3))
    assert result.gaussians == len(system.gaussian_map())
    assert np.isfinite(result.T_world_cam).all()


def test_add_gaussians_renumbers_or_refuses_clashing_ids(seq):
    system = SlamSystem(preset("tiny"), seq.intrinsics)
    system.process(seq.frame(0))
    n = len(system)
    extra = random_map(5, seed=1)
    assert system.add_gaussians(extra) == 5
    ids = system.gaussian_map().ids
    np.testing.assert_array_equal(ids[-5:], np.arange(n, n + 5))
    with pytest.raises(MapError, match="already in the map"):
        system.add_gaussians(replace(extra, ids=ids[:5]), renumber=False)
    foreign = replace(extra, ids=np.arange(10**6, 10**6 + 5))
    assert system.add_gaussians(foreign, renumber=False) == 5
    np.testing.assert_allclose(system.gaussian_map().importance_sum[-5:], extra.importance_sum)


def test_a_received_share_is_kept_out_of_the_stage_ranking(seq):
    system = SlamSystem(preset("tiny"), seq.intrinsics)
    share = replace(random_map(12, seed=2), ids=np.arange(500, 512))
    share.importance_sum[:] = 0.0  # the lowest possible scores: a ranking would drop them first
    assert system.receive(share) == 12 and system.own_ids_from == 512
    system.process(seq.frame(0))
    with pytest.raises(MapError, match="before the first frame"):
        system.receive(replace(share, ids=np.arange(900, 912)))
    before = system.gaussian_map()
    own = before.ids >= 512
    system.prune_to(0.3)
    after = system.gaussian_map()
    assert set(before.ids[~own]) <= set(after.ids)
    assert np.count_nonzero(after.ids >= 512) == keep_count(int(own.sum()), 0.3)


def test_a_received_share_does_not_stand_in_for_the_runs_own_densification(seq):
    frame = seq.frame(0)
    cover = gaussians_from_rgbd(frame.color, frame.depth, seq.intrinsics, frame.T_world_cam)
    alone = SlamSystem(preset("tiny"), seq.intrinsics).process(frame).added
    system = SlamSystem(preset("tiny"), seq.intrinsics)
    system.receive(replace(cover, ids=np.arange(len(cover)) + 10**6))
    assert system.process(frame).added == alone == np.count_nonzero(frame.depth > 0)


def assert_added_where_brighter(added, frame, error):
    """A map that covers the frame in black (rendering ~0) errs by each pixel's brightness, so a
    colour threshold `error` adds about the valid pixels brighter than it (0.02 either side for
    the render's blur), and on this scene more than a fifth of them."""
    valid = frame.depth > 0
    brightness = frame.color.mean(-1)
    assert (
        np.count_nonzero(valid & (brightness > error + 0.02))
        <= added
        <= np.count_nonzero(valid & (brightness > error - 0.02))
    )
    assert added > 0.2 * np.count_nonzero(valid)


def test_a_share_that_already_shows_the_frame_is_not_mapped_twice(seq):
    frame = seq.frame(0)
    cover = gaussians_from_rgbd(
        frame.color, frame.depth, seq.intrinsics, frame.T_world_cam, opacity=0.99
    )
    config = preset("tiny").with_overrides(**{"densify.received_color_error": 0.3})
    valid = frame.depth > 0
    black = np.full_like(cover.sh_dc, -0.5 / SH_C0)  # covers the frame, renders ~0
    added = {}
    for name, sh_dc in [("right", cover.sh_dc), ("black", black)]:
        system = SlamSystem(config, seq.intrinsics)
        system.receive(replace(cover, sh_dc=sh_dc, ids=np.arange(len(cover)) + 10**6))
        added[name] = system.process(frame).added
    assert added["right"] < 0.1 * np.count_nonzero(valid)  # explained: no second layer
    assert_added_where_brighter(added["black"], frame, 0.3)


def test_colour_densification_adds_where_the_map_shows_the_wrong_colour(seq):
    frame = seq.frame(0)
    cover = gaussians_from_rgbd(
        frame.color, frame.depth, seq.intrinsics, frame.T_world_cam, opacity=0.99
    )
    valid = frame.depth > 0
    black = replace(cover, sh_dc=np.full_like(cover.sh_dc, -0.5 / SH_C0))  # renders ~0
    added = {}
    for error in (0.0, 0.3):
        for name, gaussians in [("right", cover), ("black", black)]:
            config = preset("tiny").with_overrides(
                **{"densify.color_error": error, "densify.color_min_footprint": 0.0}
            )
            system = SlamSystem(config, seq.intrinsics)
            system.add_gaussians(gaussians)
            added[name, error] = system.process(frame).added
    assert added["right", 0.0] == added["black", 0.0] < 0.02 * np.count_nonzero(valid)
    # the right colours, blurred over the texture's noise: a few edge pixels
    assert added["right", 0.3] < 0.1 * np.count_nonzero(valid)
    assert_added_where_brighter(added["black", 0.3], frame, 0.3)


def test_colour_adds_nothing_where_the_map_is_as_fine_as_a_new_gaussian(seq):
    # A black cover renders every pixel wrong by its brightness. Where its Gaussians are as
    # fine as those densification would add (a pixel, here 0.8 of one), mapping is left to
    # correct the colour; where they are twice as wide, detail is missing and colour adds.
    frame = seq.frame(0)
    cover = gaussians_from_rgbd(
        frame.color, frame.depth, seq.intrinsics, frame.T_world_cam, opacity=0.99
    )
    black = replace(cover, sh_dc=np.full_like(cover.sh_dc, -0.5 / SH_C0))
    config = preset("tiny").with_overrides(**{"densify.color_error": 0.3})
    assert config.densify.color_min_footprint == 1.0
    added = {}
    for factor in (0.8, 2.0):
        system = SlamSystem(config, seq.intrinsics)
        system.add_gaussians(replace(black, log_scales=black.log_scales + np.log(factor)))
        added[factor] = system.process(frame).added
    assert added[0.8] < 0.02 * np.count_nonzero(frame.depth > 0)  # as without the colour rule
    assert_added_where_brighter(added[2.0], frame, 0.3)


def test_rendered_footprint_is_the_width_of_the_gaussians_in_pixels(seq):
    frame = seq.frame(0)
    valid = frame.depth > 0
    T = torch.from_numpy(invert_transform(frame.T_world_cam)).float()
    for stride, factor in [(1, 1.0), (1, 3.0), (2, 1.0)]:
        cover = gaussians_from_rgbd(
            frame.color, frame.depth, seq.intrinsics, frame.T_world_cam, stride=stride
        )
        cover = replace(cover, log_scales=cover.log_scales + np.log(factor))
        params = GaussianParams.from_map(cover, torch.device("cpu"))
        width = rendered_footprint(params.render_inputs(), seq.intrinsics, T, "cpu")
        assert np.median(width[valid]) == pytest.approx(stride * factor, rel=0.02)


def test_frames_after_a_stage_track_against_the_map_before_it(seq, monkeypatch):
    config = preset("tiny").with_overrides(
        **{"prune.stages": (1 / 3,), "prune.track_prestage_frames": 2}
    )
    system = SlamSystem(config, seq.intrinsics, total_frames=6)  # the stage: frame 1
    tracked_against, before_stage = [], []

    def spy_track(gaussians, *args, **kwargs):
        tracked_against.append(len(gaussians.means))
        return track(gaussians, *args, **kwargs)

    def spy_prune(*args, **kwargs):
        before_stage.append(len(system.mapper))
        return prune_to(*args, **kwargs)

    prune_to = system.prune_to
    monkeypatch.setattr(system, "prune_to", spy_prune)
    monkeypatch.setattr("gscompress.slam.system.track", spy_track)
    results = [system.process(seq.frame(i)) for i in range(5)]
    assert results[1].event == "prune-stage-1" and len(before_stage) == 1
    assert results[1].gaussians < before_stage[0]
    # frames 1-4 are tracked: frames 2 and 3 against the map before the stage, then the live map
    assert tracked_against[1:] == [before_stage[0], before_stage[0], results[3].gaussians]


def test_stage_events_follow_the_schedule(seq):
    system = SlamSystem(preset("tiny"), seq.intrinsics, total_frames=6)
    events = {}
    for i in range(4):
        r = system.process(seq.frame(i))
        if r.event:
            events[i] = r.event
            assert r.removed >= r.gaussians  # kept ~30%: removed at least as many as kept
    assert events == {1: "prune-stage-1", 3: "prune-stage-2"}


@pytest.mark.parametrize("by", STRATEGIES)
def test_a_stage_keeps_exactly_the_top_fraction_by_its_score(seq, by):
    config = preset("tiny").with_overrides(
        **{"prune.stages": (0.5,), "prune.keep": 0.35, "prune.by": by, "seed": 3}
    )
    system = SlamSystem(config, seq.intrinsics, total_frames=4)
    calls = []
    keep = system.mapper.keep

    def spy(index):
        calls.append((system.gaussian_map(), index))
        return keep(index)

    system.mapper.keep = spy
    results = [system.process(seq.frame(i)) for i in range(2)]
    assert results[1].event == "prune-stage-1"
    before, _ = calls[-1]  # the stage is the last removal of frame 1 (no refinement here)
    after = system.gaussian_map()
    assert len(after) == keep_count(len(before), 0.35) == results[1].gaussians
    scores = strategy_scores(before, by, seed=3 * 1000 + 1)
    order = np.lexsort((before.ids, -scores))
    np.testing.assert_array_equal(np.sort(after.ids), np.sort(before.ids[order[: len(after)]]))
    dropped = ~np.isin(before.ids, after.ids)
    assert scores[~dropped].min() >= scores[dropped].max()  # nothing dropped outranks a kept one


def test_refinement_after_a_stage_and_after_the_last_frame(seq):
    config = preset("tiny").with_overrides(
        **{
            "prune.stages": (0.5,),
            "prune.refine_iters": 5,
            "mapping.final_iters": 7,
            "mapping.final_lr_fraction": 0.5,
        }
    )
    system = SlamSystem(config, seq.intrinsics, total_frames=4)
    visited, rates = [], []
    step = system.mapper._step

    def spy(view, stats, pose_rate=None):
        visited.append(view.index)
        rates.append(system.mapper.optimizer.param_groups[0]["lr"])
        return step(view, stats, pose_rate)

    system.mapper._step = spy
    results, views = [], []
    for i in range(4):
        before = len(visited)
        results.append(system.process(seq.frame(i)))
        views.append(visited[before:])
    assert [r.refinement is not None for r in results] == [False, True, False, True]
    assert results[1].refinement.iters == 5 and results[3].refinement.iters == 7
    assert results[1].stats()["refine_iters"] == 5 and "refine_iters" not in results[2].stats()
    assert all("refinement" in r.ms for r in results)
    # keyframes of tiny: every 2nd frame -> positions 0 and 2; after the last frame (3, not a
    # keyframe) the views are 0, 2 and 3, each once per shuffled pass
    final = views[3][-7:]
    assert sorted(final[:3]) == [0, 2, 3] and sorted(final[3:6]) == [0, 2, 3]
    stage = views[1][-5:]
    assert sorted(stage[:2]) == [0, 1] and sorted(stage[2:4]) == [0, 1]
    # the stage's refinement runs at the mapping rate; only the final one decays
    lr = config.mapping.lr_means
    n1 = sum(len(v) for v in views[:2])
    assert rates[n1 - 5 : n1] == [lr] * 5
    assert rates[-7] == lr and rates[-1] == pytest.approx(0.5 * lr)


def test_final_refinement_on_every_frame_with_decaying_rates(seq):
    config = preset("tiny").with_overrides(
        **{
            "prune.stages": (),
            "mapping.final_iters": 9,
            "mapping.final_views": "frames",
            "mapping.final_lr_fraction": 0.25,
        }
    )
    system = SlamSystem(config, seq.intrinsics, total_frames=4)
    assert system.keeps_every_view
    visited, rates = [], []
    step = system.mapper._step

    def spy(view, stats, pose_rate=None):
        visited.append(view.index)
        rates.append([g["lr"] for g in system.mapper.optimizer.param_groups])
        return step(view, stats, pose_rate)

    system.mapper._step = spy
    for i in range(4):
        before = len(visited)
        system.process(seq.frame(i))
    final, lrs = visited[before:][-9:], np.array(rates[-9:])
    # every frame (not only the keyframes 0 and 2), each once per shuffled pass
    assert sorted(final[:4]) == [0, 1, 2, 3] and sorted(final[4:8]) == [0, 1, 2, 3]
    assert [v.index for v in system.views] == [0, 1, 2, 3]
    base = lrs[0]
    np.testing.assert_allclose(lrs[-1], 0.25 * base, rtol=1e-9)
    np.testing.assert_allclose(lrs[1:] / lrs[:-1], np.full((8, len(base)), 0.25 ** (1 / 8)))
    # the mapping rates come back after the refinement
    assert [g["lr"] for g in system.mapper.optimizer.param_groups] == list(base)


def test_a_short_run_refines_at_most_its_per_frame_share(seq):
    config = preset("tiny").with_overrides(
        **{"prune.stages": (), "mapping.final_iters": 50, "mapping.final_iters_per_frame": 3}
    )
    system = SlamSystem(config, seq.intrinsics, total_frames=4)
    results = [system.process(seq.frame(i)) for i in range(4)]
    assert results[-1].refinement is not None and results[-1].refinement.iters == 12
    assert final_iterations(config.mapping, 40) == 50  # a longer run gets final_iters


def test_a_stop_request_ends_the_final_refinement_but_not_a_stage_refinement(seq):
    config = preset("tiny").with_overrides(
        **{"prune.stages": (0.5,), "prune.refine_iters": 6, "mapping.final_iters": 20}
    )
    system = SlamSystem(config, seq.intrinsics, total_frames=4)
    polls = []

    def stop_requested() -> bool:
        polls.append(len(system.poses))
        return len(polls) > 7  # true from the 8th poll on

    system.stop_requested = stop_requested
    results = [system.process(seq.frame(i)) for i in range(4)]
    # the stage's refinement runs whole and never polls; the final one stops at its 8th poll
    assert [r.refinement.iters for r in results[:-1] if r.refinement is not None] == [6]
    assert set(polls) == {3} and len(polls) == 8
    assert results[-1].refinement is not None and results[-1].refinement.iters == 7
    assert len(system.poses) == 4  # the frame itself is whole


def test_only_a_final_refinement_on_every_frame_keeps_every_view(seq):
    frames = {"mapping.final_views": "frames", "mapping.final_iters": 5}
    for overrides, total in (({}, 3), ({**frames, "mapping.final_iters": 0}, 3), (frames, None)):
        config = preset("tiny").with_overrides(**{"prune.stages": (), **overrides})
        system = SlamSystem(config, seq.intrinsics, total_frames=total)
        for i in range(3):
            system.process(seq.frame(i))
        assert not system.keeps_every_view and system.views == []
        assert [v.index for v in system.keyframes] == [0, 2]


def test_refinement_lowers_the_loss_over_the_keyframes(seq):
    config = preset("tiny").with_overrides(**{"prune.stages": ()})
    system = SlamSystem(config, seq.intrinsics, total_frames=6)
    for i in range(4):
        system.process(seq.frame(i))
    stats = system.mapper.refine(system.keyframes, 30, np.random.default_rng(0))
    assert stats.iters == 30 and stats.last_loss < stats.first_loss


def _hole_pixels(system, views):
    """Valid-depth pixels whose rendered silhouette is below 0.5, summed over `views`."""
    total = 0
    with torch.no_grad():
        inputs = system.mapper.params.render_inputs()
        for view in views:
            out = render(*inputs, system.intrinsics, view.T_cam_world())
            total += int(((out.silhouette < 0.5) & (view.depth > 0)).sum())
    return total


def test_refill_after_a_stage_fills_the_holes_it_opened(seq):
    # no scheduled stage: the test prunes and refills by hand after frame 2
    config = preset("tiny").with_overrides(**{"prune.stages": (), "prune.refill": "keyframes"})
    system = SlamSystem(config, seq.intrinsics, total_frames=4)
    for i in range(3):
        system.process(seq.frame(i))
    views = system.keyframes
    system.prune_to(0.1)
    holes = _hole_pixels(system, views)
    assert holes > 100  # keeping 10% opens holes
    n = len(system)
    stats = system._refine(views[-1], 2, pruned=True, keyframe=True)
    assert stats is not None and stats.iters == 0 and stats.added == len(system) - n > 0
    assert _hole_pixels(system, views) < holes / 4


def test_refill_of_the_current_view_fills_only_its_holes(seq):
    added = {}
    for refill in ("current", "keyframes"):
        config = preset("tiny").with_overrides(**{"prune.stages": (), "prune.refill": refill})
        system = SlamSystem(config, seq.intrinsics, total_frames=4)
        for i in range(3):
            system.process(seq.frame(i))
        current = system.keyframes[-1]
        system.prune_to(0.1)
        holes = _hole_pixels(system, [current])
        stats = system._refine(current, 2, pruned=True, keyframe=True)
        assert stats is not None
        added[refill] = stats.added
        assert _hole_pixels(system, [current]) < holes / 4
    assert 0 < added["current"] < added["keyframes"]  # the older keyframe's holes stay


def test_shaping_gives_three_scales_and_a_rotation_without_changing_the_render(seq):
    frame = seq.frame(0)
    mapper = Mapper(preset("tiny"), seq.intrinsics, torch.device("cpu"))
    mapper.add(gaussians_from_rgbd(frame.color, frame.depth, seq.intrinsics, frame.T_world_cam))
    view = View(0, torch.from_numpy(frame.color), torch.from_numpy(frame.depth), frame.T_world_cam)
    mapper.optimize(view, [], 3, np.random.default_rng(0))  # (Adam moments to carry along)
    T = view.T_cam_world()
    with torch.no_grad():
        before = render(*mapper.params.render_inputs(), seq.intrinsics, T)
    moments = mapper.optimizer.state[mapper.params.log_scales]["exp_avg"].clone()
    assert mapper.params.isotropic
    assert "quats" not in [g["name"] for g in mapper.optimizer.param_groups]
    mapper.shape()
    mapper.shape()  # (once shaped, again changes nothing)
    p = mapper.params
    assert p.log_scales.shape == (len(p), 3) and not p.isotropic
    torch.testing.assert_close(p.log_scales, p.log_scales[:, :1].expand(-1, 3))
    state = mapper.optimizer.state[p.log_scales]["exp_avg"]
    torch.testing.assert_close(state, moments.expand(-1, 3))
    names = [g["name"] for g in mapper.optimizer.param_groups]
    assert names.count("quats") == 1
    with torch.no_grad():
        after = render(*p.render_inputs(), seq.intrinsics, T)
    torch.testing.assert_close(after.color, before.color)
    torch.testing.assert_close(after.depth, before.depth)
    # mapping now turns and stretches the Gaussians, one scale apart from another
    quats = p.quats.detach().clone()
    mapper.optimize(view, [], 5, np.random.default_rng(1))
    p = mapper.params
    assert not torch.equal(p.quats, quats)
    assert float((p.log_scales[:, 0] - p.log_scales[:, 1]).detach().abs().max()) > 0


def test_a_shaping_stage_leaves_a_map_of_shaped_gaussians_that_keeps_growing(seq):
    def run(shape):
        config = preset("tiny").with_overrides(**{"prune.stages": (0.5,), "prune.shape": shape})
        system = SlamSystem(config, seq.intrinsics, total_frames=4)
        results = [system.process(seq.frame(i)) for i in range(4)]
        assert results[1].event == "prune-stage-1"
        return system, results

    round_system, _ = run(False)
    assert round_system.gaussian_map().isotropic
    system, results = run(True)
    shaped = system.gaussian_map()
    assert not shaped.isotropic and sum(r.added for r in results[2:]) > 0
    # Gaussians added after the stage start round (three equal scales); survivors have turned
    new = shaped.ids >= results[1].next_id
    assert new.any() and (~new).any()
    spread = np.ptp(shaped.log_scales, axis=1)
    assert spread[~new].max() > 1e-4
    # a resumed run optimises the rotations as the run it resumes did
    again = SlamSystem(system.config, seq.intrinsics, total_frames=4)
    views = [
        View.from_frame(v.index, seq.frame(v.index), v.T_world_cam, "cpu") for v in system.keyframes
    ]
    again.restore(
        shaped,
        [(i, seq.frame(i).timestamp, T) for i, T in enumerate(system.poses)],
        views,
        mapping_iterations=system.mapper.iterations,
        next_id=system.next_id,
        first_depth=seq.frame(0).depth,
    )
    assert "quats" in [g["name"] for g in again.mapper.optimizer.param_groups]
