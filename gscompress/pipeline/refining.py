"""Refining a map on the frames of the SLAM log it came from (needs torch).

`gsc merge` refines a merged map on the receiver's frames; `gsc prune --refine` and `gsc share
--refine` refine the Gaussians they kept on the log's keyframes (`KEYFRAME_RULE`). Both open
the log's sequence as its run had it (checked against the first frame the log recorded), match
its frames to the log's estimated poses by time and run `gscompress.ops.refine.refine` on the
chosen views.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from gscompress.errors import LogFormatError, OptionError
from gscompress.gaussians import GaussianMap
from gscompress.io.mcap_log import TOPIC_POSE, LogReader
from gscompress.pipeline.logs import (
    frames_with_poses,
    is_log_keyframe,
    open_log_sequence,
    recorded_keyframes,
    trajectory,
)
from gscompress.selection import is_fraction
from gscompress.slam.views import REFINE_VIEWS

DEFAULT_LR_FINAL = 0.3
"""A refinement's learning rates decay to this fraction over its iterations. Its optimizer is
fresh, so at constant rates its first steps are as large as the last ones and leave a finished
map little better, where decaying rates improve it. In the Table 4 merges of five sequences, 0.3
lifted every merge on tabletop, office and ICL against constant rates and was ahead of 0.5 and
level with or ahead of 0.1 there; on the synthetic room and replica the merged shares ended
slightly below constant rates and 0.5 (measured in docs/design-experiments.md, "Why merges
decay their learning rates")."""


PSEUDO_VIEWS = 3
"""`gsc prune --refine` and `gsc share --refine` also refine on this many pseudo-views between
each two consecutive keyframes: the whole map (the teacher) rendered at poses interpolated
between theirs, its colour and its depth where it is opaque (silhouette above
`PSEUDO_DEPTH_SILHOUETTE`). The keyframes alone let a refinement fit them at the cost of the
views between them: on tabletop, the pseudo-views kept the refined unpruned map's frames off
the keyframes near where they were before the refinement, and a folded prune refined with them
to in-run pruning's count drew those frames as well as `gsc slam`'s in-run pruning (measured in
docs/prune-refine.md, "Isotropic refinement (`--isotropic`)" and "What else was tried on
tabletop")."""


PSEUDO_DEPTH_SILHOUETTE = 0.95
"""A pseudo-view's depth is kept where the teacher's accumulated opacity exceeds this (else 0,
no depth), so that its thin edges do not teach a depth they do not have."""


@dataclass(frozen=True)
class RefineOptions:
    """How to refine a map on a log's frames.

    Attributes:
        iters: iterations (0: no refinement).
        views: "keyframes" (the log's keyframes, `KEYFRAME_RULE`) or "frames" (all of them).
        lr_final: the learning rates (the log's mapping ones) decay geometrically to this
            fraction by the last iteration; 1 keeps them constant.
        frames: the sequence's frame subset (None: the one the log recorded).
        size: working size (None: the log's config's).
        device: torch device, or "auto".
        backend: render backend (None: the log's config's).
        seed: seed of the view order.
        pseudo_views: pseudo-views per gap between consecutive keyframes when a teacher map
            is given (`PSEUDO_VIEWS`; 0: none).
        anisotropic: refine three scales and a rotation per Gaussian: a prune or a share then
            cuts an isotropic map as an anisotropic one (`gscompress.ops.fold.cut_pool`),
            so that what it folds keeps its shape, and the refinement stretches each kept
            Gaussian over the surface it now covers (docs/prune-refine.md).
        recording: a recording's topics, pairing and ground truth
            (`gscompress.datasets.RecordingOptions`; None: those the log's run recorded).
    """

    iters: int
    views: str = "keyframes"
    lr_final: float = DEFAULT_LR_FINAL
    frames: str | None = None
    size: tuple[int, int] | None = None
    device: str = "auto"
    backend: str | None = None
    seed: int = 0
    pseudo_views: int = PSEUDO_VIEWS
    anisotropic: bool = False
    recording: Any = None

    def check(self) -> None:
        """Raise OptionError for an option out of range."""
        if self.iters < 0:
            raise OptionError(f"`iters` must be >= 0, got {self.iters}", options=("iters",))
        if self.views not in REFINE_VIEWS:
            raise OptionError(
                f"`views` is one of {', '.join(REFINE_VIEWS)}, got {self.views!r}",
                options=("views",),
            )
        if not is_fraction(self.lr_final):
            raise OptionError(
                f"`lr_final` must be in (0, 1], got {self.lr_final}", options=("lr_final",)
            )
        if self.pseudo_views < 0:
            raise OptionError(f"pseudo-views must be >= 0, got {self.pseudo_views}")

    def record(self) -> dict[str, Any]:
        """What a provenance step keeps of these options."""
        return {
            "iters": self.iters,
            "views": self.views,
            "lr_final": self.lr_final,
            "seed": self.seed,
            "backend": self.backend,
            "pseudo_views": self.pseudo_views,
            **({"anisotropic": True} if self.anisotropic else {}),
        }


class LogRefiner:
    """Refines maps on the frames of one SLAM log at its estimated poses.

    The log and its sequence are read when it is made (so a wrong sequence is refused before
    any output is written); calling it refines a map and returns it with its statistics.

    Args:
        log_path: the SLAM log (config, `/camera/pose`, `/slam/stats`).
        seq: the sequence the log was made from.
        options: the refinement's settings.
        progress: called with (iterations done, iterations) during a refinement.
        instead: what to do without a refinement, said when it diverges.

    Raises:
        LogFormatError: the log has no estimated poses, or a stats record is not JSON.
        InputError: the sequence is not the log's, or no frame of it has a pose in the log.
        OptionError: options out of range.
    """

    def __init__(
        self,
        log_path: str | Path,
        seq: str | Path,
        options: RefineOptions,
        progress: Callable[[int, int], object] | None = None,
        instead: str = "",
    ) -> None:
        from gscompress.render import resolve_backend, resolve_device
        from gscompress.slam.config import DEFAULT_PRESET, SlamConfig, preset
        from gscompress.slam.keyframes import View

        options.check()
        self.options, self.progress, self.instead = options, progress, instead
        with LogReader(log_path) as reader:
            meta = reader.metadata
            found = trajectory(reader)
            pose_ns, poses = found.times_ns, found.T_world_cam
            keyframe_ns = recorded_keyframes(reader)
        config = SlamConfig.from_dict(meta.config) if meta.config else preset(DEFAULT_PRESET)
        if options.backend is not None:
            config = config.with_overrides(backend=options.backend)
        self.config = config
        if len(pose_ns) == 0:
            raise LogFormatError(f"{log_path} has no {TOPIC_POSE}: refinement needs its poses")
        sequence = open_log_sequence(
            seq, log_path, meta, options.frames, options.size or config.size, options.recording
        )
        positions, pose_index = frames_with_poses(sequence, pose_ns, log_path)
        self.device = resolve_device(options.device, config.backend)
        self.backend = resolve_backend(config.backend, self.device)
        self.intrinsics = sequence.intrinsics

        def chosen(k: int, pose: int) -> bool:
            if options.views == "frames":
                return True
            return is_log_keyframe(k, int(pose_ns[pose]), keyframe_ns, config)

        self.views = [
            View.from_frame(k, sequence.frame(int(p)), poses[i], self.device)
            for k, (p, i) in enumerate(zip(positions, pose_index, strict=True))
            if chosen(k, int(i))
        ]
        self.keyframes_recorded = keyframe_ns is not None
        self.carried: list[Any] = []  # another agent's views (`carry`)

    def carry(self, frames: list[Any]) -> None:
        """Also refine on these frames (`gscompress.io.keyframes.CarriedFrame`s, another
        agent's keyframes at their poses in this log's world frame), taken with this log's
        camera (the caller checks)."""
        from gscompress.slam.keyframes import carried_views

        self.carried += carried_views(frames, self.device, -1 - len(self.carried))

    def record(self) -> dict[str, Any]:
        """What a provenance step records of this refinement (its options)."""
        return self.options.record()

    @property
    def anisotropic(self) -> bool:
        """Whether the maps given should be cut anisotropic (`RefineOptions.anisotropic`)."""
        return self.options.anisotropic

    def __call__(
        self,
        gaussians: GaussianMap,
        rates: Any = None,
        teacher: GaussianMap | None = None,
        iters: int | None = None,
    ) -> tuple[GaussianMap, dict[str, Any]]:
        """`gaussians` refined, and {"iters", "loss_before", "loss_after", "views",
        "pseudo_views", "backend"} (the mean mapping loss over the views before and after).
        `rates`: per-Gaussian factors on the steps (`gscompress.ops.refine.refine`). `teacher`:
        the map `gaussians` was cut from, whose renders between the keyframes are refined on
        too (`PSEUDO_VIEWS`; only with the keyframes as views). `iters`: this many iterations
        instead of the options' (a share's probe, `gscompress.pipeline.share.cut.PROBE_ITERS`),
        shown on the progress as they run."""
        from gscompress.ops.refine import refine

        done, iters = 0, self.options.iters if iters is None else min(iters, self.options.iters)

        def step(n: int) -> None:
            nonlocal done
            done += n
            if self.progress is not None:
                self.progress(done, iters)

        pseudo: list[Any] = []
        if teacher is not None and self.options.views == "keyframes" and iters > 0:
            poses = pseudo_poses([v.T_world_cam for v in self.views], self.options.pseudo_views)
            pseudo = teacher_views(teacher, poses, self.intrinsics, self.backend, self.device)
        refined, stats = refine(
            gaussians,
            self.views + self.carried + pseudo,
            self.intrinsics,
            self.config,
            iters,
            device=self.device,
            seed=self.options.seed,
            lr_final_fraction=self.options.lr_final,
            progress=step,
            rates=rates,
            **({"instead": self.instead} if self.instead else {}),
        )
        stats["views"] = len(self.views) + len(self.carried)
        stats["pseudo_views"] = len(pseudo)
        stats["carried_views"] = len(self.carried)
        stats["backend"] = self.backend
        stats["anisotropic"] = not refined.isotropic
        return refined, stats

    def contributions(self, gaussians: GaussianMap) -> Any:
        """[N] how much this log's views (and those carried) see of each Gaussian
        (`view_contributions`)."""
        views = self.views + self.carried
        return view_contributions(gaussians, views, self.intrinsics, self.backend, self.device)


def pseudo_poses(keyframe_poses: list[np.ndarray], per_gap: int) -> list[np.ndarray]:
    """`per_gap` poses evenly between each two consecutive keyframe poses (in the order given;
    `interpolate_pose`), none at the keyframes themselves."""
    from gscompress.camera import interpolate_pose

    fractions = [k / (per_gap + 1) for k in range(1, per_gap + 1)]
    return [
        interpolate_pose(a, b, t) for a, b in itertools.pairwise(keyframe_poses) for t in fractions
    ]


def teacher_views(
    teacher: GaussianMap, poses: list[np.ndarray], intrinsics: Any, backend: str, device: Any
) -> list[Any]:
    """Views whose observations are `teacher`'s renders at `poses`: its colour, and its
    expected depth where its silhouette exceeds `PSEUDO_DEPTH_SILHOUETTE` (0 elsewhere)."""
    import torch

    from gscompress.ops.score import activated_tensors, render_at
    from gscompress.slam.keyframes import View

    params = activated_tensors(teacher, device)
    views = []
    for k, T_world_cam in enumerate(poses):
        out = render_at(params, T_world_cam, intrinsics, backend)
        opaque = out.silhouette > PSEUDO_DEPTH_SILHOUETTE
        depth = torch.where(opaque, out.depth_normalized, torch.zeros_like(out.depth_normalized))
        color = out.color.clamp(0.0, 1.0).contiguous()
        views.append(View(-1 - k, color, depth.contiguous(), np.asarray(T_world_cam)))
    return views


def view_contributions(
    gaussians: GaussianMap, views: list[Any], intrinsics: Any, backend: str, device: Any
) -> Any:
    """[N] each Gaussian's alpha*T summed over the pixels of every view (how much the views
    see of it; 0 for one they never see)."""
    import torch

    from gscompress.render import render
    from gscompress.slam.params import GaussianParams

    total = torch.zeros(len(gaussians), dtype=torch.float64)
    if not len(gaussians):
        return total.numpy()
    params = GaussianParams.from_map(gaussians, device)
    with torch.no_grad():
        inputs = params.render_inputs()
        for view in views:
            out = render(
                *inputs, intrinsics, view.T_cam_world(), backend=backend, want_contribution=True
            )
            assert out.contribution is not None
            total += out.contribution.detach().cpu().to(torch.float64)
    return total.numpy()
