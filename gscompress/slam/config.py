"""SLAM hyperparameters: dataclasses with documented defaults, presets, and YAML round trips.

Three presets:

- `tiny`: for tests and smoke runs (a handful of iterations; seconds for a few 64x48 frames).
- `cpu` (the default of `gsc slam`): 160x120 and iteration counts sized for a 2-core CPU
  (40 tracking / 15 mapping iterations; its seconds per frame on the project's 2-core Xeon are
  in docs/performance.md, "Pruning (paper Table 3)"),
  with higher colour and scale learning rates than SplaTAM's because there are 15 mapping
  iterations per frame instead of 30-60 (tuned on the synthetic room and two real sequences
  with bench/slam.py), and a final refinement of 1000 iterations over every frame after the
  last one (at most 150 per frame of a short run), its learning rates decaying to 0.3 of the
  mapping ones (`mapping.final_iters`, `final_iters_per_frame`, `final_views`,
  `final_lr_fraction`; why: docs/design-experiments.md, "The final refinement"). Besides
  SplaTAM's rule it densifies where the map covers a pixel but shows it in the wrong colour
  (`densify.color_error` 0.25) and is coarser there than a new Gaussian. Its pruning stages
  shape what they keep (`prune.shape`: three scales and a rotation from then on; why:
  docs/design-experiments.md, "Shaping at a stage").
- `paper`: SplaTAM's Replica settings (40 tracking / 60 mapping iterations, full resolution),
  for a GPU; `paper-tum` has SplaTAM's TUM settings (200 / 30, camera rotation lr 2e-3).

Learning rates are those of SplaTAM unless noted. Colour is optimised as the SH DC coefficient
(`sh_dc`, the raw form the map stores), but its learning rate is given in RGB units like
SplaTAM's and divided by SH_C0 internally, so that an Adam step moves RGB by about `lr_colors`.

A YAML file holds any subset of `SlamConfig.to_dict()`; `load_config` applies it on top of a
preset (the file's own `preset:` key, else the one asked for). Unknown keys are errors.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any

import yaml

from gscompress.datasets.base import MAX_SIDE, parse_size
from gscompress.errors import InputError, OptionError, clipped
from gscompress.importance import PwasConfig
from gscompress.io.files import read_text, write_text_atomic
from gscompress.selection import STRATEGIES, is_fraction
from gscompress.slam.views import REFINE_VIEWS


@dataclass(frozen=True)
class TrackingConfig:
    """Camera tracking (pose only, Gaussians fixed; paper Eq. 4-5).

    Attributes:
        iters: optimisation iterations per frame.
        lr_rotation: Adam lr of the pose's rotation increment (quaternion vector part).
        lr_translation: Adam lr of the pose's translation increment, metres.
        lr_final_fraction: both learning rates decay geometrically to this fraction of their
            value at the last iteration (1: constant, as SplaTAM), so that large first steps
            can absorb a poor guess and small last steps settle.
        silhouette_min: only pixels whose rendered silhouette exceeds this are used.
        outlier_factor: also leave out pixels whose depth error exceeds this many times the
            median depth error of the mask (SplaTAM's `ignore_outlier_depth_loss`); 0: keep all.
        gamma_color: g_im, colour-error scale of the adaptive weight w_im = g_im/(L_color+g_im).
        gamma_depth: g_d, depth-error scale (metres) of w_depth = g_d/(L_depth+g_d).
        balance_weight: lambda of the balance term lambda (log(w_depth/w_im) - log rho)^2.
        rho: target ratio w_depth / w_im of the balance term.
        constant_velocity: start from the constant-velocity guess (else the previous pose).
        use_ground_truth: skip tracking and use ground-truth poses (mapping-only runs).
        lost_factor: the track is lost when a frame's depth error after tracking exceeds this
            many times its running level (the median of the last 10 accepted frames'); 0: never
            on that ground (`gscompress.slam.lost`).
        lost_coverage: ... or when less than this fraction of the frame's valid depth pixels
            lies on the map (passes the silhouette mask).
        max_gap: ... or when the frame's stamp is more than this many seconds after the
            previous frame's (0: no limit). A lost frame is tracked again from several guesses
            (the velocity guess extrapolated over the gap, the previous pose, the latest
            keyframes' poses); the run stops with `TrackingLostError` when none is accepted.
    """

    iters: int = 40
    lr_rotation: float = 4e-4
    lr_translation: float = 2e-3
    lr_final_fraction: float = 1.0
    silhouette_min: float = 0.99
    outlier_factor: float = 0.0
    gamma_color: float = 0.1
    gamma_depth: float = 0.05
    balance_weight: float = 0.1
    rho: float = 1.0
    constant_velocity: bool = True
    use_ground_truth: bool = False
    lost_factor: float = 3.0
    lost_coverage: float = 0.02
    max_gap: float = 0.5


@dataclass(frozen=True)
class MappingConfig:
    """Map optimisation (Gaussians only, poses fixed; paper Eq. 2-3).

    Attributes:
        iters: iterations per frame (one render of one window view each).
        first_frame_iters: iterations on the first frame.
        lr_means: Adam lr of the centres, metres.
        lr_colors: Adam lr of the colour in RGB units (see module docstring).
        lr_quats: Adam lr of the rotations (anisotropic maps only).
        lr_opacity_logits: Adam lr of the opacity logits.
        lr_log_scales: Adam lr of the log scales.
        color_weight: weight of L_color in L_map.
        depth_weight: weight of L_depth in L_map.
        ssim_weight: share of (1 - SSIM) in L_color = (1-s) L1 + s (1 - SSIM).
        illum_tau: cap tau of w_illum = min(L_illum / (L_color + eps), tau); 0 disables L_illum.
        illum_edge_sigma: relative depth step per pixel at which the pseudo-target I_fuse is
            63% the observed image (see `gscompress.slam.losses.fuse_target`).
        current_frame_share: fraction of the iterations spent on the current frame; the others
            draw a keyframe of the window.
        final_iters: global refinement after the last frame: this many iterations over
            `final_views`, each once per shuffled pass (0: none). Pruned and unpruned runs get
            it alike; its time is the last frame's "refinement" phase.
        final_iters_per_frame: at most this many final iterations per frame of the run, so that
            a short run's refinement stays in proportion to it (0: no limit).
        final_views: what the final refinement runs on: "keyframes" (and the last frame) or
            "frames" (every frame of the run: a system given its `frames` reads each again when
            the refinement visits it; otherwise it keeps every frame's colour and depth on its
            device until the end, 20 bytes a pixel with the depth edges).
        final_lr_fraction: the final refinement's learning rates decay geometrically from the
            mapping ones to this fraction of them by its last iteration (1: constant).
    """

    iters: int = 60
    first_frame_iters: int = 60
    lr_means: float = 1e-4
    lr_colors: float = 2.5e-3
    lr_quats: float = 1e-3
    lr_opacity_logits: float = 5e-2
    lr_log_scales: float = 1e-3
    color_weight: float = 0.5
    depth_weight: float = 1.0
    ssim_weight: float = 0.2
    illum_tau: float = 1.0
    illum_edge_sigma: float = 0.05
    current_frame_share: float = 0.5
    final_iters: int = 0
    final_iters_per_frame: int = 0
    final_views: str = "keyframes"
    final_lr_fraction: float = 1.0


@dataclass(frozen=True)
class KeyframeConfig:
    """Keyframes and the mapping window (SplaTAM's overlap-based selection).

    Attributes:
        every: every `every`-th frame becomes a keyframe (the first one always).
        window: keyframes in the mapping window besides the current frame (the most
            overlapping ones; the latest keyframe is always included).
        overlap_samples: current-frame pixels back-projected to measure overlap.
    """

    every: int = 5
    window: int = 24
    overlap_samples: int = 1600


@dataclass(frozen=True)
class DensifyConfig:
    """New Gaussians where the map does not explain the observed frame (SplaTAM).

    Attributes:
        stride: back-project every `stride`-th pixel in each direction.
        silhouette_max: add where the rendered silhouette is below this.
        depth_error_factor: also add where the observation is in front of the rendered depth by
            more than this many median depth errors.
        opacity: initial opacity of new Gaussians.
        color_error: also add where the map covers the pixel (silhouette at least
            `silhouette_max`) but its render is off from the observed colour by at least this
            mean absolute RGB error (0-1 units): detail the map does not hold yet. The render
            is not divided by its silhouette, so a thinly covered bright pixel can qualify too.
            0: SplaTAM's rule alone (the default, and every preset but cpu, which uses 0.25;
            docs/design-experiments.md, "Densifying where the colour is wrong").
        color_min_footprint: the colour rule adds only where the map's Gaussians are wider
            than this many times the ones it would add (`densify.rendered_footprint`); where
            they are as fine, a new one is a second layer on each revisit. 0: anywhere.
        received_color_error: with a received share (`gsc slam --inject`), do not add where the
            whole map, share included, already explains the pixel: covered, no new geometry,
            and a mean absolute RGB error below this. 0: densify wherever the run's own
            Gaussians leave the pixel unexplained, whatever the share shows there.
    """

    stride: int = 1
    silhouette_max: float = 0.5
    depth_error_factor: float = 50.0
    opacity: float = 0.5
    color_error: float = 0.0
    color_min_footprint: float = 1.0
    received_color_error: float = 0.0


@dataclass(frozen=True)
class PoseConfig:
    """Keyframe poses refined together with the map (a photometric and depth bundle adjustment
    with the mapping loss; MonoGS refines its window's keyframes alike).

    Off in every preset: they do not remove the agent's shortfall (docs/drift.md). The run's
    first frame (the anchor), the frame being mapped and another agent's keyframes (`gsc slam
    --inject`) keep their poses.

    Attributes:
        window: during mapping, optimise the poses of the window's keyframes with the Gaussians.
        final: the final refinement (`mapping.final_iters`) optimises the pose of every view it
            runs on, at rates decaying with the map's (`mapping.final_lr_fraction`).
        lr_rotation: Adam lr of a pose's rotation increment (quaternion vector part).
        lr_translation: Adam lr of a pose's translation increment, metres.
    """

    window: bool = False
    final: bool = False
    lr_rotation: float = 5e-4
    lr_translation: float = 5e-4

    @property
    def enabled(self) -> bool:
        """Whether any pose is refined."""
        return self.window or self.final


REFILL = ("off", "current", "keyframes")
"""Values of `PruneConfig.refill`."""


@dataclass(frozen=True)
class PruneConfig:
    """Cyclic removal and stage-wise PWAS pruning (paper Eq. 9-10).

    Attributes:
        opacity_every: every this many mapping iterations remove opacity < alpha_min and huge
            Gaussians (0: never).
        alpha_min: opacity threshold of the cyclic removal.
        huge_fraction: remove Gaussians whose largest scale exceeds this fraction of the scene
            radius (max first-frame depth / scene_radius_depth_ratio); 0 disables.
        scene_radius_depth_ratio: scene radius = max first-frame depth / this.
        stages: positions in the sequence (fractions of its frames) of the PWAS pruning
            stages; empty for none (`gsc slam --no-prune`).
        keep: fraction of Gaussians kept at each stage (the top ones by `by`).
        by: the score a stage ranks by (`gscompress.selection.STRATEGIES`): "pwas" (the
            paper's), "opacity", "alpha-t" (unweighted alpha*T sum) or "random" (seeded by
            `seed` and the stage); exact counts and ties as `gsc prune`.
        refine_iters: mapping iterations right after each stage over all keyframes so far and
            the current frame, each once per shuffled pass, so that the survivors fill the
            holes left in views the camera will not see again (0: none; off in every preset).
        refill: right after each stage (before its refinement), densify where the pruned map
            leaves a hole (`densify` rules; the added Gaussians count): "off" (every preset),
            "current" (the frame just mapped, so the next one is tracked against no holes) or
            "keyframes" (every keyframe so far too, so views left behind keep no empty patch).
        max_gaussians: also run a stage after any frame that leaves more than this many of the
            run's own Gaussians, so that the map, and the run's memory, stay near this size
            however long the recording (0: never; docs/recordings.md, "Streaming and memory").
        shape: at a stage the survivors take three scales and a rotation each, optimised from
            then on (`Mapper.shape`; later Gaussians start round), as `gsc prune` shapes a
            pruned map: fewer Gaussians, each holding more of the picture
            (docs/design-experiments.md, "Shaping at a stage").
        track_prestage_frames: for this many frames after each stage, track against the map as it
            stood just before the stage (a detached copy, dropped afterwards; not kept across
            `--resume`); mapping, densification, scores and the log use the pruned map (0: off).
            A stage thins the view the camera is in, and tracking against the thinned map drifts.

    Why these values (and what else was tried): docs/design-experiments.md, "Pruning stage
    settings".
    """

    opacity_every: int = 100
    alpha_min: float = 0.005
    huge_fraction: float = 0.1
    scene_radius_depth_ratio: float = 3.0
    stages: tuple[float, ...] = (1 / 3, 2 / 3)
    keep: float = 0.3
    by: str = "pwas"
    refine_iters: int = 0
    refill: str = "off"
    max_gaussians: int = 0
    shape: bool = False
    track_prestage_frames: int = 3


@dataclass(frozen=True)
class SlamConfig:
    """Everything a `gsc slam` run is configured by.

    Attributes:
        preset: the preset these values started from (informational).
        size: working image size (W, H), or None for the sequence's own.
        isotropic: one scale per Gaussian (SplaTAM) instead of three and a rotation. False
            gives higher PSNR unpruned but no smaller PWAS pruning cost
            (docs/design-experiments.md, "Anisotropic Gaussians").
        backend: render backend (`gscompress.render.BACKENDS`).
        seed: seed of the random choices (window views).
        init_from_ground_truth: put the first frame at its ground-truth pose when the sequence
            has one (else identity), so estimated and true trajectories share a frame.
        checkpoint_every: write a `/gaussians` checkpoint snapshot every this many frames
            (0: never), so that a killed run can resume from at most that many frames back.
        tracking, mapping, keyframes, densify, prune, pwas, poses: see their classes. `pwas.sigma_d`
            (YAML `auto` or null, the default of every preset) is scale-aware: the median
            distance from the camera to the surface points of the run's first frame with valid
            depth, where the first Gaussians go (`gscompress.importance.resolve_sigma_d`); a
            number sets it in metres, `inf` turns the proximity weight off. The log records
            the value used in its results (`sigma_d`).
    """

    preset: str = "paper"
    size: tuple[int, int] | None = None
    isotropic: bool = True
    backend: str = "auto"
    seed: int = 0
    init_from_ground_truth: bool = True
    checkpoint_every: int = 20
    tracking: TrackingConfig = field(default_factory=TrackingConfig)
    mapping: MappingConfig = field(default_factory=MappingConfig)
    keyframes: KeyframeConfig = field(default_factory=KeyframeConfig)
    densify: DensifyConfig = field(default_factory=DensifyConfig)
    prune: PruneConfig = field(default_factory=PruneConfig)
    pwas: PwasConfig = field(default_factory=PwasConfig)
    poses: PoseConfig = field(default_factory=PoseConfig)

    def __post_init__(self) -> None:
        check_config(self)

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON/YAML-ready values (tuples as lists; pwas.sigma_d "auto" or "inf" where
        it is not a number)."""
        values: dict[str, Any] = _plain(dataclasses.asdict(self))
        if values["pwas"]["sigma_d"] is None:
            values["pwas"]["sigma_d"] = "auto"
        return values

    @classmethod
    def from_dict(
        cls, values: dict[str, Any], base: SlamConfig | None = None, source: str = "config"
    ) -> SlamConfig:
        """`base` (default: the defaults) with the entries of `values` replaced.

        Args:
            values: nested settings, as in a YAML config.
            base: the config they change.
            source: where `values` came from, to begin an error message with.

        Raises:
            InputError: unknown keys or values of the wrong type.
        """
        try:
            result = _merge(base or cls(), values, "")
        except InputError as exc:
            raise InputError(f"{source}: {exc}") from None
        assert isinstance(result, SlamConfig)
        return result

    def with_overrides(self, **changes: Any) -> SlamConfig:
        """A copy with dotted-path overrides, e.g. `**{"prune.keep": 0.2}`."""
        nested: dict[str, Any] = {}
        for key, value in changes.items():
            node = nested
            *parents, leaf = key.split(".")
            for part in parents:
                node = node.setdefault(part, {})
            node[leaf] = value
        return SlamConfig.from_dict(nested, self)


def _plain(value: Any) -> Any:
    if isinstance(value, float) and math.isinf(value):  # (pwas.sigma_d: JSON has no inf)
        return "inf"
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, tuple | list):
        return [_plain(v) for v in value]
    return value


def _merge(current: Any, values: Any, path: str) -> Any:
    """`current` (a config dataclass) with `values` (a dict) applied, type-checked."""
    if not isinstance(values, dict):
        raise InputError(
            f"{path.rstrip('.') or 'the file'}: expected a mapping, got {clipped(values, 60)}"
        )
    known = {f.name: f for f in fields(current)}
    changes: dict[str, Any] = {}
    for key, value in values.items():
        where = f"{path}{key}"
        if key not in known:
            close = difflib.get_close_matches(str(key), known, n=1)
            hint = f" (did you mean {path + close[0]!r}?)" if close else ""
            within = f" in {path.rstrip('.')}" if path else ""
            raise InputError(
                f"unknown key {clipped(where, 60)}{hint}; known{within}: {', '.join(sorted(known))}"
            )
        old = getattr(current, key)
        if dataclasses.is_dataclass(old):
            changes[key] = _merge(old, value, f"{where}.")
        else:
            changes[key] = _coerce(old, value, where, key)
    return replace(current, **changes)


def _coerce(old: Any, value: Any, where: str, key: str) -> Any:
    """`value` converted to the type of the field's current value, or InputError."""
    if key == "size":
        if value is None:
            return None
        if isinstance(value, str):  # WxH, as on the command line
            value = parse_size(value) or value
        if (
            isinstance(value, list | tuple)
            and len(value) == 2
            and all(isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in value)
        ):
            return (int(value[0]), int(value[1]))
        raise InputError(f"{where}: expected WxH or [W, H] of positive integers, or null")
    if key == "sigma_d":
        return _sigma_d(value, where)
    if key == "refill" and isinstance(value, bool):  # files from before the three modes
        return "keyframes" if value else "off"
    if isinstance(old, bool):
        if not isinstance(value, bool):
            raise InputError(f"{where}: expected true or false, got {clipped(value, 60)}")
        return value
    if isinstance(old, int):
        if isinstance(value, bool) or not isinstance(value, int):
            raise InputError(f"{where}: expected an integer, got {clipped(value, 60)}")
        return value
    if isinstance(old, float):
        if not _finite_number(value):
            raise InputError(f"{where}: expected a finite number, got {clipped(value, 60)}")
        return float(value)
    if isinstance(old, str):
        if not isinstance(value, str):
            raise InputError(f"{where}: expected a string, got {clipped(value, 60)}")
        return value
    if isinstance(old, tuple):
        if not isinstance(value, list | tuple) or not all(_finite_number(v) for v in value):
            raise InputError(
                f"{where}: expected a list of finite numbers, got {clipped(value, 60)}"
            )
        return tuple(float(v) for v in value)
    raise InputError(f"{where}: cannot set this field")  # pragma: no cover


def _sigma_d(value: Any, where: str) -> float | None:
    """pwas.sigma_d from a file: null or "auto" (scale-aware), a number above 0, or inf."""
    if value is None or value == "auto":
        return None
    if isinstance(value, str) and value.strip().lower() in ("inf", ".inf", "infinity"):
        return math.inf
    if _finite_number(value) or value == math.inf:
        if value > 0:
            return float(value)
    raise InputError(
        f"{where}: expected a finite number above 0, inf or auto, got {clipped(value, 60)}"
    )


def _finite_number(value: Any) -> bool:
    """An int or a float (not a bool) that a float holds finitely."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        return False
    try:
        return math.isfinite(value)
    except OverflowError:  # an int beyond float range
        return False


MAX_CONFIG_BYTES = 1 << 20
"""Largest config file read (a full one is about 1.3 KB): YAML takes about 1 KB of memory a
list item, so 64 MiB of them would take tens of GB before a value could be refused."""

MAX_LEARNING_RATE = 1e3
"""Largest learning rate a config takes. An Adam step moves a parameter by about its rate, so
far smaller ones already diverge; far larger ones overflow float32 in the step itself."""


def check_config(config: SlamConfig) -> None:
    """Refuse values that cannot work (negative counts, ratios outside their range, ...)."""
    problems: list[str] = []

    def need(ok: bool, text: str) -> None:
        if not ok:
            problems.append(text)

    t, m, k, d, p = config.tracking, config.mapping, config.keyframes, config.densify, config.prune
    need(is_fraction(t.lr_final_fraction), "tracking.lr_final_fraction must be in (0, 1]")
    need(t.iters >= 0 and m.iters >= 0 and m.first_frame_iters >= 0, "iterations must be >= 0")
    need(config.checkpoint_every >= 0, "checkpoint_every must be >= 0")
    need(config.seed >= 0, "seed must be >= 0")
    need(
        all(v > 0 for v in (t.lr_rotation, t.lr_translation, t.gamma_color, t.gamma_depth, t.rho)),
        "tracking learning rates, gammas and rho must be positive",
    )
    pose_rates = (config.poses.lr_rotation, config.poses.lr_translation)
    need(all(v > 0 for v in pose_rates), "poses.lr_rotation and lr_translation must be positive")
    mapping_rates = (m.lr_means, m.lr_colors, m.lr_quats, m.lr_opacity_logits, m.lr_log_scales)
    need(all(v >= 0 for v in mapping_rates), "mapping learning rates must be >= 0")
    need(
        max(t.lr_rotation, t.lr_translation, *mapping_rates, *pose_rates) <= MAX_LEARNING_RATE,
        f"learning rates must be at most {MAX_LEARNING_RATE:g}",
    )
    need(0.0 <= t.silhouette_min < 1.0, "tracking.silhouette_min must be in [0, 1)")
    need(
        t.lost_factor >= 0 and t.max_gap >= 0 and 0.0 <= t.lost_coverage <= 1.0,
        "tracking.lost_factor and max_gap must be >= 0, tracking.lost_coverage in [0, 1]",
    )
    need(0.0 <= m.ssim_weight <= 1.0, "mapping.ssim_weight must be in [0, 1]")
    need(m.illum_tau >= 0 and m.illum_edge_sigma > 0, "illum_tau >= 0 and illum_edge_sigma > 0")
    need(0.0 <= m.current_frame_share <= 1.0, "mapping.current_frame_share must be in [0, 1]")
    need(k.every >= 1 and k.window >= 0 and k.overlap_samples >= 1, "bad keyframe settings")
    need(d.stride >= 1, "densify.stride must be >= 1")
    need(0.0 < d.opacity < 1.0, "densify.opacity must be in (0, 1)")
    need(
        min(d.color_error, d.received_color_error, d.color_min_footprint) >= 0.0,
        "densify.color_error, color_min_footprint and received_color_error must be >= 0",
    )
    need(p.opacity_every >= 0 and p.alpha_min >= 0 and p.huge_fraction >= 0, "bad prune values")
    need(p.scene_radius_depth_ratio > 0, "prune.scene_radius_depth_ratio must be positive")
    need(is_fraction(p.keep), "prune.keep must be in (0, 1]")
    need(p.by in STRATEGIES, f"prune.by must be one of {', '.join(STRATEGIES)}")
    need(p.refill in REFILL, f"prune.refill must be one of {', '.join(REFILL)}")
    need(
        min(p.track_prestage_frames, p.max_gaussians) >= 0,
        "prune.track_prestage_frames and prune.max_gaussians must be >= 0",
    )
    need(
        min(p.refine_iters, m.final_iters, m.final_iters_per_frame) >= 0,
        "refinement iterations must be >= 0",
    )
    need(is_fraction(m.final_lr_fraction), "mapping.final_lr_fraction must be in (0, 1]")
    need(m.final_views in REFINE_VIEWS, f"mapping.final_views is one of {', '.join(REFINE_VIEWS)}")
    need(all(0.0 < s < 1.0 for s in p.stages), "prune.stages must lie in (0, 1)")
    sigma_d = config.pwas.sigma_d
    need(sigma_d is None or sigma_d > 0, "pwas.sigma_d must be above 0, inf or auto (null)")
    need(config.size is None or max(config.size) <= MAX_SIDE, f"size: at most {MAX_SIDE} a side")
    from gscompress.render import BACKENDS

    need(config.backend in BACKENDS, f"backend must be one of {', '.join(BACKENDS)}")
    if problems:
        raise InputError("bad SLAM config: " + "; ".join(problems))


# ---------------------------------------------------------------------------------------------
# Presets

PRESETS: dict[str, SlamConfig] = {
    "paper": SlamConfig(preset="paper"),
    "paper-tum": SlamConfig(
        preset="paper-tum",
        tracking=TrackingConfig(iters=200, lr_rotation=2e-3),
        mapping=MappingConfig(iters=30, first_frame_iters=30),
    ),
    "cpu": SlamConfig(
        preset="cpu",
        size=(160, 120),
        tracking=TrackingConfig(iters=40, lr_rotation=2e-3, lr_translation=2e-3),
        mapping=MappingConfig(
            iters=15,
            first_frame_iters=100,
            lr_means=2e-4,
            lr_colors=2e-2,
            lr_log_scales=5e-3,
            final_iters=1000,
            final_iters_per_frame=150,
            final_views="frames",
            final_lr_fraction=0.3,
        ),
        keyframes=KeyframeConfig(every=5, window=8, overlap_samples=800),
        densify=DensifyConfig(color_error=0.25),
        prune=PruneConfig(shape=True),
    ),
    "tiny": SlamConfig(
        preset="tiny",
        # (no lost-track detection: its coarse maps' coverage falls to a few per cent after
        # a pruning stage, and 8 iterations leave its depth error too noisy to judge by)
        tracking=TrackingConfig(
            iters=8,
            lr_rotation=1e-3,
            lr_translation=2e-3,
            lost_factor=0.0,
            lost_coverage=0.0,
            max_gap=0.0,
        ),
        mapping=MappingConfig(iters=6, first_frame_iters=15, lr_means=2e-4),
        keyframes=KeyframeConfig(every=2, window=3, overlap_samples=200),
        densify=DensifyConfig(stride=1),
        prune=PruneConfig(opacity_every=20),
    ),
}
"""Named starting points; `gsc slam --preset NAME`."""

DEFAULT_PRESET = "cpu"


def preset(name: str) -> SlamConfig:
    """The preset called `name`.

    Raises:
        InputError: an unknown name.
    """
    try:
        return PRESETS[name]
    except KeyError:
        raise InputError(
            f"unknown SLAM preset {name!r}; choose one of {', '.join(PRESETS)}"
        ) from None


def load_config(path: str | Path, base: str | SlamConfig = DEFAULT_PRESET) -> SlamConfig:
    """A YAML config file applied on top of a preset.

    The file's `preset:` entry, when present, names the base preset; otherwise `base` is used.

    Raises:
        InputError: unreadable YAML, unknown keys or bad values.
    """
    path = Path(path)
    try:
        values = yaml.safe_load(read_text(path, "config", limit=MAX_CONFIG_BYTES))
    except (ValueError, RecursionError, yaml.YAMLError) as exc:  # (ints over 4300 digits)
        raise InputError(f"cannot read config {path}: {' '.join(str(exc).split())}") from None
    values = {} if values is None else values
    if not isinstance(values, dict):
        raise InputError(f"config {path} must hold a mapping of settings")
    start = base if isinstance(base, SlamConfig) else preset(base)
    if "preset" in values:
        if not isinstance(values["preset"], str):
            raise InputError(f"config {path}: preset must be a name")
        start = preset(values["preset"])
    return SlamConfig.from_dict(values, start, f"config {path}")


def save_config(config: SlamConfig, path: str | Path) -> Path:
    """Write the full config as YAML (readable back with `load_config`)."""
    text = yaml.safe_dump(config.to_dict(), sort_keys=False, default_flow_style=False)
    header = "# gscompress SLAM config (gsc slam --config FILE); any subset of keys may be given\n"
    return write_text_atomic(path, header + text)


def resolve_config(
    preset_name: str | None = None,
    config_path: str | Path | None = None,
    *,
    size: tuple[int, int] | None = None,
    keep: float | None = None,
    no_prune: bool = False,
    backend: str | None = None,
) -> SlamConfig:
    """The config of a run: preset, then the YAML file, then the command-line options.

    Args:
        preset_name: base preset; None: the file's `preset:` entry, else `DEFAULT_PRESET`.
        config_path: optional YAML file.
        size: working size (W, H) override.
        keep: PWAS keep ratio of the pruning stages override.
        no_prune: no PWAS pruning stages (the cyclic opacity cleanup still runs).
        backend: render backend override (`gscompress.render.BACKENDS`).

    Raises:
        OptionError: the file names another preset than `preset_name` (which one to start
            from would be a guess: `--save-config` writes the `preset:` entry of every file),
            or `keep` with `no_prune` (no stage to keep at).
    """
    if keep is not None and no_prune:
        raise OptionError(
            "`keep` does not go with `no_prune`: there is no pruning stage",
            options=("keep", "no_prune"),
        )
    if config_path is None:
        config = preset(preset_name or DEFAULT_PRESET)
    else:
        config = load_config(config_path, preset_name or DEFAULT_PRESET)
        if preset_name is not None and config.preset != preset_name:
            raise OptionError(
                f"config {config_path} starts from preset {config.preset!r}, not `preset` "
                f"{preset_name}: drop `preset`, or change the file's `preset:` line",
                options=("preset",),
            )
    overrides: dict[str, Any] = {}
    if size is not None:
        overrides["size"] = size
    if keep is not None:
        overrides["prune.keep"] = keep
    if no_prune:  # (no stage at all: neither the scheduled ones nor one for the map's size)
        overrides.update({"prune.stages": (), "prune.max_gaussians": 0})
    if backend is not None:
        overrides["backend"] = backend
    return config.with_overrides(**overrides) if overrides else config


def stage_positions(total_frames: int, stages: tuple[float, ...]) -> dict[int, int]:
    """{processing position after which to prune: stage number (1-based)} for a run length.

    Stage s at fraction p runs after frame round(p * total) - 1 (at least after the first).
    """
    out: dict[int, int] = {}
    for number, fraction in enumerate(sorted(stages), start=1):
        position = max(round(fraction * total_frames), 1) - 1
        out.setdefault(position, number)
    return out


def final_iterations(mapping: MappingConfig, frames: int) -> int:
    """Iterations of the final refinement of a run of `frames` frames."""
    per_frame = mapping.final_iters_per_frame
    return min(mapping.final_iters, per_frame * frames) if per_frame else mapping.final_iters
