"""The SLAM system: one RGB-D frame at a time.

Per frame: constant-velocity pose guess -> tracking (pose only) -> densification (new Gaussians
where the map does not explain the frame) -> mapping (Gaussians only, over a window of
overlapping keyframes and the current frame) -> PWAS accumulation for the frame at its final
mapped state and estimated pose -> stage-wise PWAS pruning when the frame is a stage.

The first frame is put at its ground-truth pose when the sequence gives one (so that estimated
and true trajectories share a world frame), else at the identity; the whole valid depth map is
back-projected, then mapped for `first_frame_iters` iterations. That frame's depth also fixes the
run's scales: the scene radius of the huge-Gaussian cleanup, and PWAS's sigma_d unless the config
sets it (`gscompress.importance.resolve_sigma_d`; `SlamSystem.sigma_d`). Frames before the first
one with valid depth add nothing to the PWAS sums.

The system is pure: no files, no printing. `gscompress.pipeline.slam_file` runs it over a
sequence and writes the log.

Random choices (the mapping window's views) draw from a generator seeded by (seed, position),
so a run restored at any frame (`SlamSystem.restore`, what `gsc slam --resume` uses) makes the
same choices as an uninterrupted one. Another agent's share enters through
`SlamSystem.receive(share)` before the first frame, which keeps its ids and PWAS sums. The
received Gaussians are tracked against, optimised, scored and cleaned up like the run's own, but
two steps look at the run's own Gaussians only:

- densification adds Gaussians where the run's own map does not explain the frame: a share is
  a sparse, blurred cover of the scene, and letting it stand in for the receiver's own map
  stops the receiver from mapping;
- the PWAS pruning stages rank the run's own Gaussians only: the sender already chose the share
  under its budget, and ranking it again would cut it twice.

(docs/merge.md, "Injected instead of merged", has what either did when it was not so.)
"""

from __future__ import annotations

import itertools
import logging
import time
from collections.abc import Callable
from dataclasses import replace
from typing import Any

import numpy as np
import torch

from gscompress.camera import Intrinsics, invert_transform
from gscompress.datasets.base import Frame
from gscompress.errors import BudgetError, InputError, MapError
from gscompress.gaussians import GaussianMap
from gscompress.importance import median_range, resolve_sigma_d
from gscompress.render import render, resolve_device
from gscompress.selection import keep_count, strategy_scores, top_k
from gscompress.slam.config import SlamConfig, final_iterations, stage_positions
from gscompress.slam.densify import densification_mask, gaussians_from_rgbd, rendered_footprint
from gscompress.slam.keyframes import (
    HeldImages,
    View,
    frame_tensors,
    is_keyframe,
    select_window,
)
from gscompress.slam.lost import (
    PREVIOUS,
    VELOCITY,
    Lost,
    TrackLevel,
    gap_reason,
    lost_reason,
    relocalisation_guesses,
    relocalise,
)
from gscompress.slam.mapper import Mapper, MappingStats
from gscompress.slam.params import RenderInputs
from gscompress.slam.poses import PoseStore, orthonormalize
from gscompress.slam.results import PHASES, FrameResult
from gscompress.slam.tracker import TrackResult, constant_velocity, track, velocity_guess

log = logging.getLogger(__name__)

RELEASE_EVERY = 10
"""Refinement iterations between two calls of `SlamSystem.release`."""


def counted_steps(
    total: int,
    report: Callable[[int, int], object] | None = None,
    release: Callable[[], object] | None = None,
) -> Callable[[Any], None]:
    """A callback for each of `total` steps (whatever it is called with): it reports (steps
    done, `total`) to `report` and calls `release` every `RELEASE_EVERY` steps (either may be
    None)."""
    done = itertools.count(1)

    def step(_: Any) -> None:
        k = next(done)
        if release is not None and k % RELEASE_EVERY == 0:
            release()
        if report is not None:
            report(k, total)

    return step


class SlamSystem:
    """SplaTAM-style RGB-D SLAM with PWAS importance, fed one frame at a time.

    Args:
        config: hyperparameters (`gscompress.slam.config`).
        intrinsics: camera intrinsics at the working size of the frames.
        device: torch device (or "auto").
        total_frames: frames the run will have; needed to place the PWAS pruning stages
            (None: no stage-wise pruning).
        frames: the run's frame at a processing position (`RGBDSequence.frame`), read again
            when needed: with it the views kept for the final refinement that are not
            keyframes hold no images between its visits (`View.source`), so that what the run
            keeps per frame does not grow with the frames' size (None: they stay in memory).

    Example:
        system = SlamSystem(preset("tiny"), sequence.intrinsics, total_frames=len(sequence))
        for frame in iter_frames(sequence):
            result = system.process(frame)
        gaussians = system.gaussian_map()
    """

    def __init__(
        self,
        config: SlamConfig,
        intrinsics: Intrinsics,
        device: str | torch.device = "cpu",
        *,
        total_frames: int | None = None,
        frames: Callable[[int], Frame] | None = None,
    ) -> None:
        self.config = config
        self.intrinsics = intrinsics
        self.device = resolve_device(device, config.backend)
        self.mapper = Mapper(config, intrinsics, self.device)
        self.keyframes: list[View] = []
        self.carried: list[View] = []
        """Another agent's keyframes received with its share (`receive`)."""
        self.views: list[View] = []
        """Every frame's view when the final refinement runs on every frame, else empty."""
        self.poses: list[np.ndarray] = []
        self.kept_poses = PoseStore()
        """Where the arrays of `poses` come from (`gscompress.slam.poses.PoseStore`)."""
        self.frame_indices: list[int] = []
        self.timestamps: list[float] = []
        self.next_id = 0
        self.own_ids_from = 0
        """Gaussians with ids below this were received from another agent (`receive`)."""
        self.prestage: tuple[RenderInputs, int] | None = None
        """The map before the last stage and how many more frames track against it."""
        self.track_level = TrackLevel()
        self.images = HeldImages(frames, self.device, config.keyframes.window + 1)
        """Which views hold their images (`gscompress.slam.keyframes.HeldImages`)."""
        """The running level of the tracked frames' depth errors (lost-track detection)."""
        self.stages = (
            stage_positions(total_frames, config.prune.stages) if total_frames is not None else {}
        )
        self.total_frames = total_frames
        self.stop_requested: Callable[[], bool] | None = None
        """Polled by the final refinement before each iteration: true ends it there (`gsc slam`
        sets it to "Ctrl-C or SIGTERM came", so that a stop does not wait for the whole
        refinement)."""
        self.in_final_refinement = False
        """True while the final refinement runs (a stop then ends that refinement)."""
        self.on_final_step: Callable[[int, int], object] | None = None
        """Called after each iteration of the final refinement with (iterations done,
        iterations): `gsc slam`'s progress through it (minutes at full size on a CPU)."""
        self.release: Callable[[], object] | None = None
        """Called every `RELEASE_EVERY` iterations of a refinement: `gsc slam` hands the heap's
        free memory back to the system there (`gscompress.pipeline.slam_run.release_free_heap`,
        as after each frame), so that the final refinement, one frame's work over every view,
        does not hold what each view's visit freed (docs/recordings.md, "Streaming and
        memory")."""
        self.sigma_d: float | None = None
        """PWAS's distance scale in metres (inf: no proximity weighting), known from the first
        frame with valid depth on (`pwas.sigma_d` of the config, else derived from that
        frame)."""

    # ------------------------------------------------------------------ state

    def gaussian_map(self) -> GaussianMap:
        """The current map with its PWAS sums (a numpy copy)."""
        return self.mapper.params.to_map()

    @property
    def _pose_rates(self) -> np.ndarray:
        """[6] Adam rates of a refined pose's increment (`PoseConfig`)."""
        poses = self.config.poses
        return np.repeat([poses.lr_rotation, poses.lr_translation], 3)

    def refined_poses(self) -> list[np.ndarray]:
        """Every processed frame's [4, 4] camera-to-world pose as the mapping left it.

        A keyframe, and a frame whose view the mapping refined, has its view's pose; any other
        frame keeps its tracked pose relative to the latest keyframe at or before it, which
        moves as that keyframe's pose was refined. Without pose refinement these are the
        tracked poses (`poses`).
        """
        views = self._own_views()
        return [self._refined_pose(position, views) for position in range(len(self.poses))]

    def _own_views(self) -> dict[int, View]:
        """The run's own kept views (keyframes and every-frame views) by position."""
        return {v.index: v for v in [*self.keyframes, *self.views] if v.index >= 0}

    def _refined_pose(self, position: int, views: dict[int, View]) -> np.ndarray:
        """`refined_poses` of one frame."""
        view = views.get(position)
        if view is not None and (view.refined or is_keyframe(position, self.config.keyframes)):
            return view.T_world_cam
        anchor = position - position % self.config.keyframes.every
        keyframe = views.get(anchor)
        tracked = self.poses[position] if view is None else view.T_world_cam  # (unrefined)
        if keyframe is None or not keyframe.refined:  # (nothing moved it)
            return tracked
        moved = keyframe.T_world_cam @ invert_transform(self.poses[anchor])
        return orthonormalize(moved @ tracked)

    def _repose_views(self) -> None:
        """Put every kept view the mapping has not refined at its `refined_poses` pose (it
        moves with its keyframe), before a refinement that steps them all."""
        views = self._own_views()
        for position, view in views.items():
            if not view.refined and not is_keyframe(position, self.config.keyframes):
                view.T_world_cam = self._refined_pose(position, views)
                view.pose = None
                view.refinable(self._pose_rates)

    @property
    def keeps_every_view(self) -> bool:
        """Whether the run keeps every frame's view (for a final refinement on every frame; a
        system that does not know its `total_frames` runs no final refinement)."""
        mapping = self.config.mapping
        has_final = self.total_frames is not None and mapping.final_iters > 0
        return has_final and mapping.final_views == "frames"

    def __len__(self) -> int:
        """Gaussians in the map."""
        return len(self.mapper)

    def add_gaussians(self, gaussians: GaussianMap, *, renumber: bool = True) -> int:
        """Append Gaussians to the map (densification, and a received share: `receive`).

        Args:
            gaussians: the new Gaussians, with or without importance sums.
            renumber: give them fresh ids after the map's (keep theirs when False).

        Raises:
            MapError: with `renumber=False`, ids that the map already holds.
        """
        if not renumber and len(gaussians) and len(self.mapper):
            held = self.mapper.params.ids.cpu().numpy()
            clash = np.intersect1d(held, gaussians.ids.astype(np.int64))
            if clash.size:
                raise MapError(f"{clash.size} of the new Gaussians' ids are already in the map")
        if renumber:
            n = len(gaussians)
            ids = np.arange(self.next_id, self.next_id + n, dtype=np.uint32)
            gaussians = replace(gaussians, ids=ids)
        added = self.mapper.add(gaussians)
        if len(gaussians):
            self.next_id = max(self.next_id, int(gaussians.ids.max()) + 1)
        return added

    def receive(self, share: GaussianMap, views: list[View] | None = None) -> int:
        """Start the map with another agent's share (ids and PWAS sums kept); returns its size.

        Densification and the pruning stages look past the received Gaussians (module docstring).
        `views`, the sender's keyframes the share carries (at their poses in this run's world
        frame), become keyframes before this run's own: mapping windows take them where they
        overlap the frame, and the refinements after a pruning stage and at the end map on
        them too.

        Raises:
            MapError: the run has already started (the map is not empty).
        """
        if len(self.mapper) or self.poses:
            raise MapError("a share can only be received before the first frame")
        added = self.add_gaussians(share, renumber=False)
        self.own_ids_from = self.next_id
        self.carried = list(views or [])
        self.keyframes = list(self.carried)
        return added

    def restore(
        self,
        gaussians: GaussianMap,
        poses: list[tuple[int, float, np.ndarray]],
        views: list[View],
        *,
        mapping_iterations: int,
        next_id: int,
        first_depth: np.ndarray,
        own_ids_from: int = 0,
    ) -> None:
        """Put a fresh system in the state of a run after its first `len(poses)` frames.

        The map (with its PWAS sums), the poses, the keyframes, the mapping iteration count
        (which places the cyclic cleanup) and the id counter come back exactly; the optimizer
        restarts with zero moments, which a log does not record.

        Args:
            gaussians: the map after the last restored frame.
            poses: (frame index, timestamp, [4, 4] camera-to-world) of each processed frame, as
                tracked.
            views: the views of those frames that the run keeps, in order: every frame's when
                `keeps_every_view`, else the keyframes' (extra ones are ignored), at their
                refined poses when the run refines poses (`refined_poses`).
            mapping_iterations: mapping iterations run so far.
            next_id: the id the next new Gaussian gets.
            first_depth: [H, W] depth of the first frame (sets the scene radius).
            own_ids_from: `own_ids_from` of the run (ids below it were received).
        """
        if len(self.poses) or len(self.mapper):
            raise MapError("restore() needs a fresh SlamSystem")
        if self.keeps_every_view and [v.index for v in views] != list(range(len(poses))):
            raise MapError("restore() needs the view of every restored frame, in order")
        self.add_gaussians(gaussians, renumber=False)
        if self.config.prune.shape and not self.mapper.params.isotropic:
            self.mapper.shape()  # (a stage has shaped the map: its rotations are optimised)
        for index, stamp, T in poses:
            self.frame_indices.append(int(index))
            self.timestamps.append(float(stamp))
            self.poses.append(np.asarray(T, dtype=np.float64))
        if self.config.poses.enabled:
            views = [v.refinable(self._pose_rates) if v.index > 0 else v for v in views]
        self.keyframes = [v for v in views if is_keyframe(v.index, self.config.keyframes)]
        self.views = list(views) if self.keeps_every_view else []
        for view in views:
            self.images.sourced(view).release()
        self.images.hold(self.keyframes[-self.images.capacity :])
        self.mapper.iterations = int(mapping_iterations)
        self.next_id = max(self.next_id, int(next_id))
        self.own_ids_from = int(own_ids_from)
        self._init_scene_radius(first_depth)

    # ------------------------------------------------------------------ one frame

    def process(self, frame: Frame) -> FrameResult:
        """Track, densify, map, score and (when scheduled) prune with one frame.

        Args:
            frame: colour [H, W, 3] and depth [H, W] at the working size of `intrinsics`.

        Returns:
            The frame's pose estimate, counts, losses and timings.
        """
        shape = (self.intrinsics.height, self.intrinsics.width)
        if frame.color.shape[:2] != shape or frame.depth.shape != shape:
            raise InputError(
                f"frame {frame.index} is {frame.depth.shape[1]}x{frame.depth.shape[0]}, "
                f"the intrinsics are for {shape[1]}x{shape[0]}"
            )
        ms: dict[str, float] = dict.fromkeys(PHASES, 0.0)
        start = time.perf_counter()
        position = len(self.poses)
        color, depth = frame_tensors(frame, self.device)

        clock = time.perf_counter()
        T_world_cam, tracking = self._pose(frame, color, depth, position)
        T_world_cam = self.kept_poses.keep(T_world_cam)  # (kept to the end: `PoseStore`)
        ms["tracking"] = 1e3 * (time.perf_counter() - clock)
        current = self.images.sourced(View(position, color, depth, T_world_cam))
        keyframe = is_keyframe(position, self.config.keyframes)
        if position > 0 and self.config.poses.enabled and (keyframe or self.keeps_every_view):
            current.refinable(self._pose_rates)

        clock = time.perf_counter()
        added = self._densify(current)
        ms["densification"] = 1e3 * (time.perf_counter() - clock)

        clock = time.perf_counter()
        rng = np.random.default_rng([self.config.seed, position])
        window = select_window(self.keyframes, current, self.intrinsics, self.config.keyframes, rng)
        iters = (
            self.config.mapping.first_frame_iters if position == 0 else self.config.mapping.iters
        )
        mapping = self.mapper.optimize(current, window, iters, rng)
        if keyframe:
            self.keyframes.append(current)
        if self.keeps_every_view:
            self.views.append(current)
        ms["mapping"] = 1e3 * (time.perf_counter() - clock)

        clock = time.perf_counter()
        psnr = self._accumulate_pwas(current)
        ms["pwas"] = 1e3 * (time.perf_counter() - clock)

        clock = time.perf_counter()
        removed = mapping.removed
        event = None
        stage = self.stages.get(position)
        over = 0 < self.config.prune.max_gaussians < self.own_gaussians()
        if stage is not None or over:
            frames = self.config.prune.track_prestage_frames
            if frames and not self.config.tracking.use_ground_truth:
                with torch.no_grad():  # clone: means, quats are the parameters themselves
                    inputs = RenderInputs(*(x.clone() for x in self.mapper.params.render_inputs()))
                self.prestage = (inputs, frames)
            # (a stage for the map's size is numbered by its frame: a resumed run numbers alike)
            number = stage if stage is not None else 1000 * (position + 1)
            removed += self.prune_to(self.config.prune.keep, stage=number)
            if self.config.prune.shape:
                self.mapper.shape()
            event = f"prune-stage-{stage}" if stage is not None else "prune-size"
        ms["pruning"] = 1e3 * (time.perf_counter() - clock)

        clock = time.perf_counter()
        refinement = self._refine(current, position, event is not None, keyframe)
        if refinement is not None:
            removed += refinement.removed
            added += refinement.added
        ms["refinement"] = 1e3 * (time.perf_counter() - clock)
        ms["total"] = 1e3 * (time.perf_counter() - start)
        self.images.hold([current, *window] if keyframe else window)
        if not keyframe:
            current.release()  # (read again if the final refinement visits it)

        self.poses.append(T_world_cam)
        self.frame_indices.append(frame.index)
        self.timestamps.append(frame.timestamp)
        return FrameResult(
            position=position,
            frame=frame.index,
            timestamp=float(frame.timestamp),
            T_world_cam=T_world_cam,
            keyframe=keyframe,
            gaussians=len(self.mapper),
            added=added,
            removed=removed,
            event=event,
            tracking=tracking,
            mapping=mapping,
            psnr=psnr,
            refinement=refinement,
            next_id=self.next_id,
            ms=ms,
        )

    def own_gaussians(self) -> int:
        """How many of the map's Gaussians are the run's own (not received)."""
        return int((self.mapper.params.ids >= self.own_ids_from).sum())

    def prune_to(self, keep: float, by: str | None = None, *, stage: int = 0) -> int:
        """Keep the top `keep` fraction of the run's own Gaussians; returns how many went.

        Of the N Gaussians with ids from `own_ids_from` on (all of them unless a share was
        received), exactly `keep_count(N, keep)` survive, ranked as `gsc prune` ranks a map
        (`gscompress.selection.strategy_scores`, ties to the lower id); received Gaussians
        all stay.

        Args:
            keep: fraction kept, in (0, 1].
            by: "pwas", "opacity", "alpha-t" or "random"; None: `prune.by` of the config.
            stage: stage number, mixed into the seed of "random".
        """
        gaussians = self.gaussian_map()
        ids = gaussians.ids.astype(np.int64)
        own = np.flatnonzero(ids >= self.own_ids_from)
        if own.size == 0:
            return 0
        by = self.config.prune.by if by is None else by
        seed = self.config.seed * 1000 + stage
        try:
            scores = strategy_scores(gaussians.select(own), by, seed=seed)
        except BudgetError:  # (the map is not empty: no frame has seen any of it)
            raise BudgetError(
                f"pruning stage {stage}: none of the map's Gaussians has a {by} score (no frame "
                "saw any with a weight above 0: mapping.lr_* too high for the data, or too "
                "small a pwas.sigma_d?)"
            ) from None
        kept = own[
            top_k(
                scores,
                ids[own],
                keep_count(own.size, keep, "keep ratio (`keep`, prune.keep)", options=("keep",)),
            )
        ]
        index = np.union1d(np.flatnonzero(ids < self.own_ids_from), kept)
        return self.mapper.keep(torch.from_numpy(index).to(self.device))

    # ------------------------------------------------------------------ phases

    def _pose(
        self, frame: Frame, color: torch.Tensor, depth: torch.Tensor, position: int
    ) -> tuple[np.ndarray, TrackResult | None]:
        """The frame's camera-to-world pose: initial, ground truth or tracked."""
        gt = frame.T_world_cam
        if position == 0:
            if gt is not None and self.config.init_from_ground_truth:
                return np.asarray(gt, dtype=np.float64), None
            return np.eye(4), None
        if self.config.tracking.use_ground_truth:
            if gt is None:
                raise InputError(
                    f"tracking.use_ground_truth is set but frame {frame.index} has no pose"
                )
            return np.asarray(gt, dtype=np.float64), None
        name, guess = PREVIOUS, self.poses[-1]
        if self.config.tracking.constant_velocity and position > 1:
            dt_prev = self.timestamps[-1] - self.timestamps[-2]
            dt = frame.timestamp - self.timestamps[-1]
            name, guess = VELOCITY, velocity_guess(self.poses[-1], self.poses[-2], dt_prev, dt)
        elif self.config.tracking.constant_velocity:
            guess = constant_velocity(self.poses[-1], None)
        if self.prestage is not None:  # the map as it stood before the last stage
            inputs, left = self.prestage
            self.prestage = (inputs, left - 1) if left > 1 else None
        else:
            inputs = self.mapper.params.render_inputs()
        valid = int((depth > 0).sum())
        result = None
        reason = gap_reason(frame.timestamp - self.timestamps[-1], self.config.tracking)
        if reason is None:
            result = self._track(inputs, color, depth, guess)
            reason = lost_reason(result, valid, self.track_level.level(), self.config.tracking)
        if reason is not None:
            own = [v.T_world_cam for v in self.keyframes if v.index >= 0]
            result = relocalise(
                lambda guess: self._track(inputs, color, depth, guess),
                relocalisation_guesses((name, guess), self.poses[-1], own),
                Lost(frame.index, frame.timestamp, reason, valid, self.track_level.level()),
                self.config.tracking,
                result,
            )
        assert result is not None
        self.track_level.add(result)
        return result.T_world_cam, result

    def _track(
        self, inputs: RenderInputs, color: torch.Tensor, depth: torch.Tensor, guess: np.ndarray
    ) -> TrackResult:
        return track(
            inputs,
            color,
            depth,
            self.intrinsics,
            guess,
            self.config.tracking,
            backend=self.config.backend,
        )

    def _init_scene_radius(self, depth: np.ndarray) -> None:
        """Scene radius (for the huge-Gaussian cleanup) and PWAS's sigma_d from the first valid
        depth map."""
        if self.mapper.scene_radius is None and np.any(depth > 0):
            ratio = self.config.prune.scene_radius_depth_ratio
            self.mapper.scene_radius = float(depth.max()) / ratio
        if self.sigma_d is None and median_range(depth, self.intrinsics):
            self.sigma_d = resolve_sigma_d(self.config.pwas.sigma_d, [depth], self.intrinsics)

    def _densify(self, current: View) -> int:
        """Add Gaussians for the pixels of the view the map does not explain yet.

        With a received share, a pixel qualifies when the run's own Gaussians leave it
        unexplained, and (with `densify.received_color_error` > 0) the whole map does not
        explain it either: it leaves a hole or new geometry there, or its colour is off by at
        least that mean absolute RGB error. A sparse share then does not stop the run from
        mapping, and where a dense one already shows the frame the run adds no second layer.
        """
        current.load()
        settings = self.config.densify
        depth = current.depth.cpu().numpy()
        mask = depth > 0  # an empty map explains nothing
        with torch.no_grad():
            inputs = self.mapper.params.render_inputs()
            own = self.mapper.params.ids >= self.own_ids_from
            if own.any():  # received Gaussians do not stand in for the run's own
                mask = self._unexplained(RenderInputs(*(x[own] for x in inputs)), current)[0]
            if self.own_ids_from and settings.received_color_error > 0 and len(inputs.means):
                whole, error = self._unexplained(inputs, current)
                mask &= whole | (error >= settings.received_color_error)
        self._init_scene_radius(depth)
        new = gaussians_from_rgbd(
            current.color.cpu().numpy(),
            depth,
            self.intrinsics,
            current.T_world_cam,
            mask=mask,
            stride=settings.stride,
            first_id=self.next_id,
            opacity=settings.opacity,
        )
        if not self.config.isotropic:
            new = new.as_anisotropic()
        return self.add_gaussians(new, renumber=False)

    def _unexplained(self, inputs: RenderInputs, current: View) -> tuple[np.ndarray, np.ndarray]:
        """The densification mask of `inputs` rendered at the view (`densify` rules), and the
        render's [H, W] mean absolute RGB error."""
        settings = self.config.densify
        out = render(*inputs, self.intrinsics, current.T_cam_world(), backend=self.config.backend)
        residual = (out.color - current.color).abs().mean(-1).cpu().numpy()
        footprint = None
        if settings.color_error > 0 and settings.color_min_footprint > 0:
            footprint = rendered_footprint(
                inputs, self.intrinsics, current.T_cam_world(), self.config.backend
            )
        mask = densification_mask(
            out.silhouette.cpu().numpy(),
            out.depth_normalized.cpu().numpy(),
            current.depth.cpu().numpy(),
            silhouette_max=settings.silhouette_max,
            depth_error_factor=settings.depth_error_factor,
            color_residual=residual,
            color_error=settings.color_error,
            footprint=footprint,
            min_footprint=settings.color_min_footprint * settings.stride,
        )
        return mask, residual

    def _refine(
        self, current: View, position: int, pruned: bool, keyframe: bool
    ) -> MappingStats | None:
        """Refinement over all keyframes at constant rates after a pruning stage, and over
        `mapping.final_views` with rates decaying to `mapping.final_lr_fraction` after the last
        frame. A stage on the last frame (a short run) joins its iterations to the final ones."""
        iters = self.config.prune.refine_iters if pruned else 0
        fraction = 1.0
        keyframes = self.keyframes if keyframe else [*self.keyframes, current]
        views = keyframes
        stop, final = None, False
        if self.total_frames is not None and position == self.total_frames - 1:
            final = True
            iters += final_iterations(self.config.mapping, self.total_frames)
            fraction = self.config.mapping.final_lr_fraction
            views = [*self.carried, *self.views] if self.keeps_every_view else keyframes
            stop = self.stop_requested
            if self.config.poses.final:
                self._repose_views()
            if iters:
                log.debug("final refinement: %d iterations over %d views", iters, len(views))
        added = 0
        refill = self.config.prune.refill if pruned else "off"
        if refill != "off":
            added = sum(
                self._densify(v) for v in (keyframes if refill == "keyframes" else [current])
            )
        if iters == 0 and not added:
            return None
        rng = np.random.default_rng([self.config.seed, position, 1])
        self.in_final_refinement = final
        on_step = self._refinement_steps(iters, final)
        try:
            stats = self.mapper.refine(
                views,
                iters,
                rng,
                on_step=on_step,
                lr_final_fraction=fraction,
                stop=stop,
                poses=final and self.config.poses.final,
            )
        finally:
            self.in_final_refinement = False
        if stop is not None and stats.iters < iters and len(self.mapper.params):  # (not emptied)
            log.warning("final refinement stopped after %d of %d iterations", stats.iters, iters)
        stats.added = added
        return stats

    def _refinement_steps(self, iters: int, final: bool) -> Callable[[float], object] | None:
        """The mapper's `on_step` of a refinement: `release` every `RELEASE_EVERY` iterations,
        and in the final refinement the iterations counted to `on_final_step` (None when
        neither is set)."""
        report = self.on_final_step if final and iters else None
        if report is None and self.release is None:
            return None
        if report is not None:
            report(0, iters)
        return counted_steps(iters, report, self.release)

    def _accumulate_pwas(self, current: View) -> float:
        """Add this frame's PWAS terms at the final mapped state; returns the frame's PSNR."""
        params = self.mapper.params
        if len(params) == 0:
            return float("nan")
        with torch.no_grad():
            inputs = params.render_inputs()
            out = render(
                *inputs,
                self.intrinsics,
                current.T_cam_world(),
                backend=self.config.backend,
                want_contribution=True,
            )
            assert out.contribution is not None
            center = torch.as_tensor(current.T_world_cam[:3, 3], device=self.device)
            if self.sigma_d is not None:  # (else no frame so far had valid depth)
                params.sums.accumulate(
                    out.contribution, out.visible, inputs.means, center, self.sigma_d
                )
            mse = float(((out.color.clamp(0, 1) - current.color) ** 2).mean())
        return 10.0 * float(np.log10(1.0 / mse)) if mse > 0 else float("inf")
