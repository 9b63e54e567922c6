"""Registration of two agents' maps: the rigid transform from one map's world frame to another's.

Agents that start wherever they are map in frames of their own; before a share can be merged,
the transform between the frames must be known. `align_clouds` estimates it from the maps
alone: a global step that needs no initial guess (FPFH features matched under RANSAC, on a voxel
grid of the Gaussian centres), then a local refinement (coloured ICP on a finer grid), and checks
that the answer can be trusted before returning it:

- overlap: the fraction of each map that lies on the other once aligned (`fitness`); too little
  and the maps share too little to be placed;
- ambiguity: the best distinct alternative (another RANSAC run, or the answer turned by a
  quarter or half turn about the map's principal axes and refined again) fitting nearly as well
  means a symmetric scene, where any of them may be the wrong one;
- degeneracy: the point-to-plane information of the aligned overlap with a direction it hardly
  constrains (a plane slides in itself, a sphere or cylinder turns in itself).

`refine_alignment` is the local step alone, from a given transform (an initial guess, or two
maps believed to share a frame that still sit centimetres apart).

The global step is Open3D's (`pip install 'gscompress[align]'`), imported at the point of use;
the local step is `gscompress.ops.icp`'s, coloured ICP in numpy by default (`AlignOptions.icp`),
so that a local refinement, and the merge's alignment that is one, needs no extra. docs/align.md
says why. Inputs and outputs are numpy arrays.
"""

from __future__ import annotations

import logging
import time
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from gscompress.camera import rotation_angle_deg, transform_points
from gscompress.errors import GscError, InputError
from gscompress.ops.icp import (
    DEFAULT_ICP,
    ICP,
    Cloud,
    Stages,
    grid_cloud,
    gridded,
    local_icp,
    open3d_module,
    to_open3d,
)

log = logging.getLogger(__name__)

COLOR_AGREEMENT = 0.12
"""Colours agree when their channels differ by less than this on average (of 1): two agents
see one surface under one light, a symmetric twin of it is seldom painted alike."""

MIN_POINTS = 30
"""Fewest opaque Gaussians a map needs to be aligned (fewer cannot carry features)."""


class AlignmentError(GscError):
    """Two maps whose alignment cannot be trusted (too little overlap, a symmetric or
    degenerate scene): refused rather than a transform that may be wrong.

    Attributes:
        alignment: the refused result with its figures (None when none was found).
    """

    def __init__(self, message: str, alignment: Alignment | None = None) -> None:
        super().__init__(message)
        self.alignment = alignment


@dataclass(frozen=True)
class AlignOptions:
    """How two maps are aligned and when the result is refused.

    Attributes:
        voxel: grid (m) of the global step's features; None: from the maps (`auto_voxel`).
        min_overlap: refuse when neither map has this fraction of itself on the other once
            aligned (within one voxel).
        max_ambiguity: refuse when a distinct alternative transform reaches this fraction of
            the best one's overlap.
        min_conditioning: refuse when the weakest direction of the aligned overlap's
            point-to-plane information is below this fraction of the strongest (rotations
            measured at the overlap's radius).
        min_inliers: refuse when fewer feature matches than this agree with the result
            (global step only).
        ransac_runs: independent RANSAC runs of the global step (each a hypothesis, beside
            the one of Fast Global Registration on the same feature matches).
        ransac_iterations: iterations of each run.
        seed: seed of RANSAC.
        colored: refine with coloured ICP (geometry and colour); False: point-to-plane ICP.
        icp: the local step's implementation (`gscompress.ops.icp.ICP`): "builtin" (numpy,
            no extra) or "open3d" (Open3D's, the `[align]` extra). The global step is
            Open3D's either way.
        distinct_translation: alternatives are distinct when they place the source's centroid
            this many voxels apart ...
        distinct_rotation_deg: ... or differ by this rotation (degrees).
    """

    voxel: float | None = None
    min_overlap: float = 0.15
    max_ambiguity: float = 0.85
    min_conditioning: float = 0.02
    min_inliers: int = 12
    ransac_runs: int = 1
    ransac_iterations: int = 30_000
    seed: int = 0
    colored: bool = True
    icp: str = DEFAULT_ICP
    distinct_translation: float = 3.0
    distinct_rotation_deg: float = 10.0

    def check(self) -> None:
        """Refuse options outside what they take (InputError)."""
        if self.voxel is not None and not (np.isfinite(self.voxel) and self.voxel > 0):
            raise InputError(f"the alignment voxel must be a positive length, got {self.voxel}")
        for name in ("min_overlap", "max_ambiguity", "min_conditioning"):
            value = getattr(self, name)
            if not 0.0 <= value <= 1.0:
                raise InputError(f"{name} must be in [0, 1], got {value}")
        if self.ransac_runs < 1 or self.ransac_iterations < 1 or self.min_inliers < 0:
            raise InputError("ransac_runs and ransac_iterations must be >= 1, min_inliers >= 0")
        if self.icp not in ICP:
            raise InputError(f"icp is one of {', '.join(ICP)}, got {self.icp!r}")


@dataclass
class Alignment:
    """A transform between two maps and what it rests on.

    Attributes:
        T_target_source: [4, 4] maps points of the source's world frame into the target's.
        overlap: the larger of `source_overlap` and `target_overlap`.
        source_overlap / target_overlap: fraction of each map (on the refinement's grid)
            within one voxel of the other once aligned.
        residual: RMS distance (m) from the source's Gaussians within one voxel of the
            target's to their nearest target Gaussian (so about half the Gaussians' spacing
            for maps that agree).
        inliers: feature matches that agree with the transform (within 1.5 voxels), and
            `inlier_ratio` their fraction of all mutual matches (global step; None with an
            initial guess).
        ambiguity: best distinct alternative's overlap over the result's (0: none found).
        conditioning: weakest over strongest direction of the point-to-plane information.
        voxel: the global step's grid (m); the refinement works on half of it.
        global_step: "ransac-fpfh", or "init" when an initial guess replaced it.
        icp: the local step's implementation (`AlignOptions.icp`).
        seconds: wall time of the alignment.
        refused: why the result cannot be trusted ("" when it can).
        hypotheses: the agreement of every hypothesis tried (global step and rivals).
    """

    T_target_source: np.ndarray
    overlap: float
    source_overlap: float
    target_overlap: float
    residual: float
    inliers: int | None
    inlier_ratio: float | None
    ambiguity: float
    conditioning: float
    voxel: float
    global_step: str
    icp: str = DEFAULT_ICP
    seconds: float = 0.0
    refused: str = ""
    hypotheses: list[float] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready (the transform as a nested list)."""
        out = asdict(self)
        out["T_target_source"] = np.asarray(self.T_target_source).tolist()
        return out


def transform_error(T_est: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    """Translation (m) and rotation (degrees) of `T_est` relative to `T_true`."""
    D = np.linalg.inv(T_true) @ T_est
    return float(np.linalg.norm(D[:3, 3])), rotation_angle_deg(D[:3, :3])


def auto_voxel(*clouds: Cloud, points: int = 4000) -> float:
    """The global step's grid: 1.5 times the median spacing of the denser map's centres, or
    coarser where that would leave more than about `points` points of the larger map (the
    global step's time grows with them; a surface of N Gaussians at spacing s covers about
    N s^2, so a grid of s sqrt(N / points) leaves about `points`)."""
    from scipy.spatial import cKDTree

    spacings = []
    for cloud in clouds:
        pts = cloud.points
        if len(pts) > 20_000:  # (the median of a sample is the median)
            pts = pts[np.random.default_rng(0).choice(len(pts), 20_000, replace=False)]
        d, _ = cKDTree(pts).query(pts, k=2)
        spacings.append(float(np.median(d[:, 1])))
    largest = max(len(c.points) for c in clouds)
    return max(min(spacings), 1e-6) * max(1.5, float(np.sqrt(largest / points)))


GLOBAL_STEP = "the global step of an alignment (used without `init`)"

FINE_STAGES: Stages = ((1.0, 30), (0.5, 30))
"""The local step's ICP on the half-voxel grid: pairs within one voxel, then within half of one."""

COARSE_STAGES: Stages = ((1.5, 20),)
"""The point-to-plane ICP that settles each hypothesis of the global step on its grid."""


def _fpfh(pcd: Any, voxel: float) -> Any:
    o3d = open3d_module(GLOBAL_STEP, ("init",))
    return o3d.pipelines.registration.compute_fpfh_feature(
        pcd, o3d.geometry.KDTreeSearchParamHybrid(radius=5.0 * voxel, max_nn=100)
    )


def points_fit(
    src_pts: np.ndarray, tgt_tree: Any, T: np.ndarray, dist: float
) -> tuple[float, float]:
    """Fraction of the source points within `dist` of the target (a cKDTree of its points) once
    moved by `T`, and their RMS distance (0 where none is)."""
    d, _ = tgt_tree.query(transform_points(T, src_pts), distance_upper_bound=dist)
    near = np.isfinite(d)
    return float(near.mean()), float(np.sqrt(np.mean(d[near] ** 2))) if near.any() else 0.0


def surface_fit(
    source: Cloud, target: Cloud, transforms: list[np.ndarray], distance: float
) -> list[float]:
    """For each transform T, the fraction of `source`'s points within `distance` of a `target`
    point once moved by T: how much of the source T lays on the target's surfaces."""
    from scipy.spatial import cKDTree

    tree = cKDTree(target.points)
    return [points_fit(source.points, tree, T, distance)[0] for T in transforms]


def _agreement(
    src_pts: np.ndarray,
    src_colors: np.ndarray,
    tgt_tree: Any,
    tgt_colors: np.ndarray,
    T: np.ndarray,
    dist: float,
) -> float:
    """How well `T` explains the source: the fraction of its points with a target point within
    `dist` whose colour agrees (mean channel difference under `COLOR_AGREEMENT`)."""
    d, j = tgt_tree.query(transform_points(T, src_pts), distance_upper_bound=dist)
    near = np.isfinite(d)
    same = np.abs(src_colors[near] - tgt_colors[j[near]]).mean(axis=1) < COLOR_AGREEMENT
    return float(same.sum() / len(src_pts))


def _conditioning(
    src_pts: np.ndarray,
    tgt_pts: np.ndarray,
    tgt_normals: np.ndarray,
    tgt_tree: Any,
    T: np.ndarray,
    dist: float,
) -> float:
    """Weakest over strongest eigenvalue of the point-to-plane information of the overlap, with
    rotations scaled by the overlap's radius (so both are metres)."""
    moved = transform_points(T, src_pts)
    d, j = tgt_tree.query(moved, distance_upper_bound=dist)
    near = np.isfinite(d)
    if near.sum() < 6:
        return 0.0
    p, n = tgt_pts[j[near]], tgt_normals[j[near]]
    c = p.mean(axis=0)
    radius = float(np.sqrt(np.mean(np.sum((p - c) ** 2, axis=1)))) or 1.0
    J = np.hstack([np.cross(p - c, n) / radius, n])  # [K, 6]
    eig = np.linalg.eigvalsh(J.T @ J)
    return float(max(eig[0], 0.0) / eig[-1]) if eig[-1] > 0 else 0.0


def _distinct(
    T1: np.ndarray, T2: np.ndarray, centroid: np.ndarray, o: AlignOptions, voxel: float
) -> bool:
    shift = np.linalg.norm(
        transform_points(T1, centroid[None]) - transform_points(T2, centroid[None])
    )
    _, rot = transform_error(T1, T2)
    return bool(shift > o.distinct_translation * voxel or rot > o.distinct_rotation_deg)


def _probes(points: np.ndarray) -> list[np.ndarray]:
    """Quarter and half turns about the principal axes through the centroid of `points`: where
    a scene is symmetric, one of them lands on an alternative that fits as well."""
    from scipy.spatial.transform import Rotation

    c = points.mean(axis=0)
    _, _, axes = np.linalg.svd(points - c, full_matrices=False)
    out = []
    for axis in axes:
        for angle in (90.0, 180.0, 270.0):
            R = Rotation.from_rotvec(np.radians(angle) * axis).as_matrix()
            P = np.eye(4)
            P[:3, :3], P[:3, 3] = R, c - R @ c
            out.append(P)
    return out


def align_clouds(
    source: Cloud,
    target: Cloud,
    options: AlignOptions | None = None,
    init: np.ndarray | None = None,
) -> Alignment:
    """The transform that maps `source`'s world frame into `target`'s.

    Args:
        source, target: the two maps (see `map_cloud`).
        options: settings and refusal thresholds.
        init: [4, 4] initial guess of the transform; given, the global step (and the search
            for alternatives, which the guess decides between) is skipped.

    Returns:
        The alignment, `refused` empty.

    Raises:
        AlignmentError: the result cannot be trusted (`refused` says why, in one line; the
            alignment with its figures is the exception's `alignment`).
        MissingDependencyError: Open3D is not installed and the global step (no `init`) or
            `options.icp` "open3d" needs it.
    """
    o = options or AlignOptions()
    o.check()
    alignment = _align(source, target, o, init)
    if alignment.refused:
        raise AlignmentError(alignment.refused, alignment)
    return alignment


def refine_alignment(
    source: Cloud, target: Cloud, T_target_source: np.ndarray, options: AlignOptions | None = None
) -> Alignment:
    """The local step alone: `T_target_source` refined by ICP, with its figures (never
    refused: `refused` says what would be wrong, for the caller to judge). With the builtin
    ICP (the default) it needs no optional dependency."""
    o = options or AlignOptions()
    o.check()
    return _align(source, target, o, np.asarray(T_target_source, dtype=np.float64))


def _align(source: Cloud, target: Cloud, o: AlignOptions, init: np.ndarray | None) -> Alignment:
    from scipy.spatial import cKDTree

    started = time.perf_counter()
    for name, cloud in (("source", source), ("target", target)):
        if len(cloud.points) < MIN_POINTS:
            raise AlignmentError(
                f"the {name} map has {len(cloud.points)} opaque Gaussians; aligning needs at "
                f"least {MIN_POINTS}"
            )
    voxel = o.voxel or auto_voxel(source, target)
    src_fine, tgt_fine = grid_cloud(source, voxel / 2.0), grid_cloud(target, voxel / 2.0)
    tgt_tree = cKDTree(tgt_fine.points)
    found = None if init is None else _Hypotheses(np.asarray(init, dtype=np.float64))
    if found is None:
        found = _global_step(source, target, src_fine, tgt_fine, tgt_tree, voxel, o)
    T = local_icp(src_fine, tgt_fine, found.T, voxel, FINE_STAGES, o.colored, o.icp)
    inliers, inlier_ratio = found.inliers(T, voxel)
    fit, _ = points_fit(src_fine.points, tgt_tree, T, voxel)
    _, rms = points_fit(source.points, cKDTree(target.points), T, voxel)  # (every Gaussian)
    tgt_fit, _ = points_fit(tgt_fine.points, cKDTree(src_fine.points), np.linalg.inv(T), voxel)
    assert tgt_fine.normals is not None
    conditioning = _conditioning(
        src_fine.points, tgt_fine.points, tgt_fine.normals, tgt_tree, T, voxel
    )
    alignment = Alignment(
        T_target_source=T,
        overlap=max(fit, tgt_fit),
        source_overlap=fit,
        target_overlap=tgt_fit,
        residual=rms,
        inliers=inliers,
        inlier_ratio=inlier_ratio,
        ambiguity=found.ambiguity,
        conditioning=conditioning,
        voxel=voxel,
        global_step="ransac-fpfh" if init is None else "init",
        icp=o.icp,
        hypotheses=found.agreements,
    )
    alignment.refused = refusal(alignment, o)
    alignment.seconds = time.perf_counter() - started
    log.debug(
        "aligned: overlap %.3f, residual %.4f m, inliers %s, ambiguity %.3f, conditioning %.4f, "
        "%.2f s",
        alignment.overlap,
        rms,
        inliers,
        found.ambiguity,
        conditioning,
        alignment.seconds,
    )
    return alignment


@dataclass
class _Hypotheses:
    """Where the local step starts: the global step's best transform, how well its distinct
    rivals fit (`ambiguity`), every hypothesis's agreement, and the feature matches (source
    and target points, [K, 3] each); an initial guess alone has none of these."""

    T: np.ndarray
    ambiguity: float = 0.0
    agreements: list[float] = field(default_factory=list)
    matches: tuple[np.ndarray, np.ndarray] | None = None

    def inliers(self, T: np.ndarray, voxel: float) -> tuple[int | None, float | None]:
        """The feature matches that `T` brings within 1.5 voxels, and their fraction."""
        if self.matches is None:
            return None, None
        src, tgt = self.matches
        err = np.linalg.norm(transform_points(T, src) - tgt, axis=1)
        inliers = int(np.sum(err < 1.5 * voxel))
        return inliers, inliers / len(src)


def _open3d_grid(cloud: Cloud, voxel: float) -> Cloud:
    """`cloud` on a `voxel` grid as Open3D draws it (`voxel_down_sample`, `estimate_normals`),
    normals as `grid_cloud` keeps and turns them. The global step works on this grid rather than
    `grid_cloud`'s: its FPFH bins and RANSAC's samples follow the last digits of the normals and
    the order of the cells, and on Open3D's grid it finds what docs/align.md measured."""
    o3d = open3d_module(GLOBAL_STEP, ("init",))
    pcd = o3d.geometry.PointCloud()
    pcd.points = o3d.utility.Vector3dVector(cloud.points)
    pcd.colors = o3d.utility.Vector3dVector(cloud.colors)
    if cloud.normals is not None:
        pcd.normals = o3d.utility.Vector3dVector(cloud.normals)
    down = pcd.voxel_down_sample(voxel)
    estimated = o3d.geometry.PointCloud(down)
    estimated.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2.5 * voxel, max_nn=30))
    known = None if cloud.normals is None else np.asarray(down.normals)
    return gridded(
        np.asarray(down.points),
        np.asarray(down.colors),
        np.asarray(estimated.normals),
        known,
        cloud.viewpoints,
    )


def _global_step(
    source: Cloud,
    target: Cloud,
    src_fine: Cloud,
    tgt_fine: Cloud,
    tgt_tree: Any,
    voxel: float,
    o: AlignOptions,
) -> _Hypotheses:
    """Hypotheses without an initial guess (FPFH matches under Fast Global Registration and
    RANSAC, then the best one turned about its principal axes), each settled by point-to-plane
    ICP on the `voxel` grid and scored by its agreement on the fine grids. Needs Open3D."""
    o3d = open3d_module(GLOBAL_STEP, ("init",))
    reg = o3d.pipelines.registration
    src_down, tgt_down = _open3d_grid(source, voxel), _open3d_grid(target, voxel)
    src_o3d, tgt_o3d = to_open3d(src_down), to_open3d(tgt_down)

    def settled(T: np.ndarray) -> tuple[np.ndarray, float]:
        T = local_icp(src_down, tgt_down, T, voxel, COARSE_STAGES, colored=False, icp=o.icp)
        return T, _agreement(
            src_fine.points, src_fine.colors, tgt_tree, tgt_fine.colors, T, voxel / 2.0
        )

    f_src, f_tgt = _fpfh(src_o3d, voxel), _fpfh(tgt_o3d, voxel)
    matches = np.asarray(reg.correspondences_from_features(f_src, f_tgt, True))  # (mutual)
    if len(matches) < 3:
        raise AlignmentError("no transform found: the maps' features have nothing in common")
    pairs = o3d.utility.Vector2iVector(matches)
    fgr = reg.FastGlobalRegistrationOption(maximum_correspondence_distance=1.5 * voxel)
    found = [reg.registration_fgr_based_on_correspondence(src_o3d, tgt_o3d, pairs, fgr)]
    checkers = [
        reg.CorrespondenceCheckerBasedOnEdgeLength(0.9),
        reg.CorrespondenceCheckerBasedOnDistance(1.5 * voxel),
    ]
    for run in range(o.ransac_runs):
        o3d.utility.random.seed(o.seed + run)
        found.append(
            reg.registration_ransac_based_on_correspondence(
                src_o3d,
                tgt_o3d,
                pairs,
                1.5 * voxel,
                reg.TransformationEstimationPointToPoint(False),
                3,
                checkers,
                reg.RANSACConvergenceCriteria(o.ransac_iterations, 0.9999),
            )
        )
    hypotheses = [settled(np.asarray(f.transformation)) for f in found]
    best = max(hypotheses, key=lambda h: h[1])
    hypotheses += [settled(best[0] @ P) for P in _probes(src_down.points)]
    best = max(hypotheses, key=lambda h: h[1])
    centroid = src_down.points.mean(axis=0)
    rivals = [h[1] for h in hypotheses if _distinct(h[0], best[0], centroid, o, voxel)]
    return _Hypotheses(
        T=best[0],
        ambiguity=max(rivals) / best[1] if rivals and best[1] > 0 else 0.0,
        agreements=[h[1] for h in hypotheses],
        matches=(src_down.points[matches[:, 0]], tgt_down.points[matches[:, 1]]),
    )


def refusal(a: Alignment, o: AlignOptions) -> str:
    """Why `a` cannot be trusted, in one line ("" when it can)."""
    figures = f"overlap {a.overlap:.0%}, residual {a.residual * 100:.1f} cm"
    if a.overlap < o.min_overlap:
        return f"too little overlap: {figures} (at least {o.min_overlap:.0%} needed)"
    if a.ambiguity >= o.max_ambiguity:
        return (
            f"ambiguous: a distinct transform fits {a.ambiguity:.0%} as well as the best "
            f"({figures}); the scene looks symmetric"
        )
    if a.conditioning < o.min_conditioning:
        return (
            f"degenerate geometry: the overlap constrains one direction {a.conditioning:.3f} as "
            f"much as the strongest ({figures}); a plane or a surface of revolution can slide"
        )
    if a.inliers is not None and a.inliers < o.min_inliers:
        return f"too few feature matches agree: {a.inliers} ({figures})"
    return ""


def map_cloud(
    means: np.ndarray,
    colors: np.ndarray,
    opacities: np.ndarray,
    scales: np.ndarray | None = None,
    rotations: np.ndarray | None = None,
    viewpoints: np.ndarray | None = None,
    min_opacity: float = 0.3,
) -> Cloud:
    """The cloud of a Gaussian map's opaque Gaussians: centres, colours, and the normal of each
    flat Gaussian (smallest scale under a third of the middle one) as its shortest axis.

    Args:
        means: [N, 3]; colors: [N, 3] in [0, 1]; opacities: [N].
        scales: [N, 3] standard deviations (None or isotropic: no normals).
        rotations: [N, 3, 3] rotation matrices of anisotropic Gaussians.
        viewpoints: [M, 3] camera centres of the map's frames.
        min_opacity: Gaussians below this opacity are left out.
    """
    keep = np.asarray(opacities) >= min_opacity
    normals = None
    if scales is not None and rotations is not None and len(means):
        s = np.asarray(scales, dtype=np.float64)
        order = np.sort(s, axis=1)
        flat = order[:, 0] < order[:, 1] / 3.0
        axis = np.argmin(s, axis=1)
        normals = np.asarray(rotations, dtype=np.float64)[np.arange(len(s)), :, axis]
        normals[~flat] = 0.0
        normals = normals[keep]
    return Cloud(
        np.asarray(means, dtype=np.float64)[keep],
        np.asarray(colors, dtype=np.float64)[keep],
        normals,
        None if viewpoints is None else np.asarray(viewpoints, dtype=np.float64),
    )
