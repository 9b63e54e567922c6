"""The local step of a registration: ICP between two clouds from a transform close to the answer.

Registration sees a map as a `Cloud` (Gaussian centres, colours, normals where known) and works
on it on a voxel grid (`grid_cloud`: one point per cell, with a unit normal). From a given
transform, `local_icp` refines it by ICP in stages of shrinking correspondence distance, with
one of the implementations in `ICP`:

- "builtin": coloured ICP in numpy and scipy (Park, Zhou and Koltun, "Colored Point Cloud
  Registration Revisited", ICCV 2017): each source point is paired with its nearest target
  point within the stage's distance, and one Gauss-Newton step minimises, over the pairs, the
  point-to-plane distance and the difference between the source point's intensity and the
  target's intensity carried along its tangent plane by its colour gradient, weighted
  `LAMBDA_GEOMETRIC` to the rest; repeated until the pairs stop changing.
- "open3d": the same objective through Open3D's `registration_colored_icp` (the optional
  `[align]` extra, imported at the point of use).

Both see the same grid and stop by the same rule, and agree to within a micrometre on the
test scenes; docs/align.md compares them on real agents. Inputs and outputs are numpy arrays.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from gscompress.camera import transform_points
from gscompress.errors import InputError, MissingDependencyError

INSTALL_HINT = "pip install 'gscompress[align]'"

LAMBDA_GEOMETRIC = 0.968
"""Weight of the geometric residual of coloured ICP, the photometric one getting the rest (Park
et al.'s value and Open3D's default)."""

NEIGHBOURS = 30
"""Nearest neighbours that fit a point's normal and its colour gradient."""

CONVERGED = 1e-6
"""A stage stops when an iteration changes neither the fraction of source points paired nor
their RMS distance (m) by this much."""

Stages = tuple[tuple[float, int], ...]
"""ICP stages: (correspondence distance in voxels, most iterations), in order."""


@dataclass(frozen=True)
class Cloud:
    """What registration sees of a map.

    Attributes:
        points: [N, 3] Gaussian centres (m).
        colors: [N, 3] RGB in [0, 1].
        normals: [N, 3] unit normals where known (flat Gaussians), rows of zeros elsewhere;
            None: none known. Missing normals are estimated from the neighbours.
        viewpoints: [M, 3] camera centres the map was seen from, to orient normals towards
            (None: towards the points' centroid).
    """

    points: np.ndarray
    colors: np.ndarray
    normals: np.ndarray | None = None
    viewpoints: np.ndarray | None = None

    def __post_init__(self) -> None:
        n = len(self.points)
        arrays = {"points": self.points, "colors": self.colors, "normals": self.normals}
        for name, a in arrays.items():
            if a is not None and (a.ndim != 2 or a.shape != (n, 3)):
                raise InputError(f"a cloud's {name} must be [{n}, 3], got {a.shape}")
            if a is not None and not np.all(np.isfinite(a)):
                raise InputError(f"a cloud's {name} hold non-finite values")
        if self.viewpoints is not None and (
            self.viewpoints.ndim != 2 or self.viewpoints.shape[1] != 3
        ):
            raise InputError(f"a cloud's viewpoints must be [M, 3], got {self.viewpoints.shape}")


def open3d_module(needed_for: str, options: tuple[str, ...] = ()) -> Any:
    """The open3d module, or MissingDependencyError saying what `needed_for` it (naming the
    parameters `options`, as `GscError`'s) and how to get it (its Linux build also needs the
    system's libusb-1.0)."""
    try:
        import open3d
    except ImportError as exc:
        fix = (
            "Open3D's Linux build loads libusb-1.0 (Debian/Ubuntu: apt-get install libusb-1.0-0)"
            if "libusb" in str(exc)
            else f"install it with {INSTALL_HINT}"
        )
        raise MissingDependencyError(
            f"{needed_for} needs Open3D ({exc}); {fix}", options=options
        ) from None
    open3d.utility.set_verbosity_level(open3d.utility.VerbosityLevel.Error)  # (no stdout chatter)
    return open3d


def _neighbours(points: np.ndarray, tree: Any, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """[N, K] indices of each point's `NEIGHBOURS` nearest points within `radius` (itself
    first) and [N, K] whether each is one (K = min(NEIGHBOURS, N); missing ones index 0)."""
    k = min(NEIGHBOURS, tree.n)
    d, j = tree.query(points, k=k, distance_upper_bound=radius)
    near = np.isfinite(np.reshape(d, (len(points), k)))
    return np.where(near, np.reshape(j, (len(points), k)), 0), near


def estimate_normals(points: np.ndarray, radius: float) -> np.ndarray:
    """[N, 3] unit normals: the least principal axis of each point's `NEIGHBOURS` nearest
    points within `radius` (itself included); +z where fewer than three are."""
    from scipy.spatial import cKDTree

    j, near = _neighbours(points, cKDTree(points), radius)
    count = near.sum(axis=1)
    weight = near[..., None]
    centre = (points[j] * weight).sum(axis=1) / count[:, None]
    spread = (points[j] - centre[:, None]) * weight  # [N, K, 3]
    _, axes = np.linalg.eigh(spread.transpose(0, 2, 1) @ spread)
    normals = axes[:, :, 0]
    normals[count < 3] = (0.0, 0.0, 1.0)
    return normals


def grid_cloud(cloud: Cloud, voxel: float) -> Cloud:
    """`cloud` on a grid of `voxel` (m), as registration works on it: one point per occupied
    cell (the mean of its points and colours) with a unit normal, turned towards the nearest
    viewpoint (or the centroid).

    A cell's normal is the mean of its points' known normals where that mean is longer than a
    half (flat Gaussians that agree), else estimated from the grid (`estimate_normals` within
    2.5 cells). The grid starts half a cell below the points' lowest corner, as Open3D's
    `voxel_down_sample` does, so that both ICP implementations can be handed the same grid.
    """
    corner = cloud.points.min(axis=0) - voxel / 2.0
    cells = np.floor((cloud.points - corner) / voxel).astype(np.int64)
    _, inverse, counts = np.unique(cells, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.ravel()  # (numpy 2.0 returns it with the input's shape)

    def mean(values: np.ndarray) -> np.ndarray:
        sums = [np.bincount(inverse, values[:, k], len(counts)) for k in range(3)]
        return np.stack(sums, axis=1) / counts[:, None]

    points = mean(cloud.points)
    known = None if cloud.normals is None else mean(cloud.normals)
    return gridded(
        points, mean(cloud.colors), estimate_normals(points, 2.5 * voxel), known, cloud.viewpoints
    )


def gridded(
    points: np.ndarray,
    colors: np.ndarray,
    estimated: np.ndarray,
    known: np.ndarray | None,
    viewpoints: np.ndarray | None,
) -> Cloud:
    """A grid's cloud from its cells' mean points and colours ([M, 3] each): each cell's normal
    the mean of its points' `known` normals where that mean is longer than a half, else the
    `estimated` one, turned towards the nearest of `viewpoints` (or the centroid)."""
    normals = np.array(estimated, dtype=np.float64)
    if known is not None:
        length = np.linalg.norm(known, axis=1)
        flat = length > 0.5
        normals[flat] = known[flat] / length[flat, None]
    if viewpoints is not None and len(viewpoints):
        from scipy.spatial import cKDTree

        _, nearest = cKDTree(viewpoints).query(points)
        towards = viewpoints[nearest] - points
    else:
        towards = points.mean(axis=0) - points
    flip = np.einsum("ij,ij->i", normals, towards) < 0
    normals[flip] *= -1.0
    return Cloud(points, colors, normals, viewpoints)


def color_gradients(target: Cloud, tree: Any, radius: float) -> np.ndarray:
    """[M, 3] the gradient of each target point's intensity (the mean of its RGB) in its
    tangent plane: the least-squares fit to the intensity differences of its `NEIGHBOURS`
    nearest points within `radius`, their offsets projected onto the plane, with a row that
    holds the gradient in the plane; zero where fewer than four points are near."""
    assert target.normals is not None  # (a grid_cloud)
    points, normals = target.points, target.normals
    intensity = target.colors.mean(axis=1)
    j, near = _neighbours(points, tree, radius)
    count = near.sum(axis=1)
    offsets = points[j] - points[:, None]  # [M, K, 3]; (itself: a row of zeros)
    along = np.einsum("mki,mi->mk", offsets, normals)
    tangent = (offsets - along[..., None] * normals[:, None]) * near[..., None]
    rise = (intensity[j] - intensity[:, None]) * near
    held = (count - 1.0) ** 2  # (the in-plane row, weighted as the neighbours together)
    AtA = tangent.transpose(0, 2, 1) @ tangent + held[:, None, None] * (
        normals[:, :, None] * normals[:, None, :]
    )
    Atb = np.einsum("mki,mk->mi", tangent, rise)
    gradients = np.zeros_like(points)
    fitted = count >= 4
    gradients[fitted] = np.einsum(
        "mij,mj->mi", np.linalg.pinv(AtA[fitted], hermitian=True), Atb[fitted]
    )
    return gradients


def _increment(x: np.ndarray) -> np.ndarray:
    """The [4, 4] transform of a Gauss-Newton step x = (rotations about x, y, z (radians),
    translation): the rotations applied in that order."""
    from scipy.spatial.transform import Rotation

    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", x[:3]).as_matrix()
    T[:3, 3] = x[3:]
    return T


def _icp_step(
    moved: np.ndarray,
    source: Cloud,
    target: Cloud,
    pairs: tuple[np.ndarray, np.ndarray],
    gradients: np.ndarray | None,
) -> np.ndarray:
    """One Gauss-Newton step over the pairs (source rows `moved`, already transformed): the
    [4, 4] transform that lowers the point-to-plane residual, and with `gradients` the
    photometric one (weighted by `LAMBDA_GEOMETRIC`); the identity where the system is
    singular."""
    assert target.normals is not None
    i, j = pairs
    p, q, n = moved[i], target.points[j], target.normals[j]
    along = np.einsum("ki,ki->k", p - q, n)
    J = np.hstack([np.cross(p, n), n])  # [K, 6]: d(residual) / d(rotation, translation)
    r = along
    if gradients is not None:
        g, w = gradients[j], np.sqrt(LAMBDA_GEOMETRIC)
        in_plane = p - along[:, None] * n
        predicted = target.colors[j].mean(axis=1) + np.einsum("ki,ki->k", g, in_plane - q)
        slope = np.einsum("ki,ki->k", g, n)[:, None] * n - g  # (minus g's in-plane part)
        w_color = np.sqrt(1.0 - LAMBDA_GEOMETRIC)
        J = np.vstack([w * J, w_color * np.hstack([np.cross(p, slope), slope])])
        r = np.concatenate([w * along, w_color * (source.colors[i].mean(axis=1) - predicted)])
    try:
        x = np.linalg.solve(J.T @ J, -(J.T @ r))
    except np.linalg.LinAlgError:
        return np.eye(4)
    return _increment(x)


def _pairs(
    tree: Any, moved: np.ndarray, distance: float
) -> tuple[tuple[np.ndarray, np.ndarray], float, float]:
    """Each moved source point's nearest target point within `distance`: the (source, target)
    index pairs, the fraction of source points paired and their RMS distance."""
    d, j = tree.query(moved, distance_upper_bound=distance)
    near = np.isfinite(d)
    if not near.any():
        return (np.zeros(0, np.int64), np.zeros(0, np.int64)), 0.0, 0.0
    rms = float(np.sqrt(np.mean(d[near] ** 2)))
    return (np.flatnonzero(near), j[near]), float(near.mean()), rms


def icp_builtin(
    source: Cloud, target: Cloud, T: np.ndarray, voxel: float, stages: Stages, colored: bool
) -> np.ndarray:
    """ICP in numpy and scipy from `T`, stage by stage: point-to-plane, or with `colored` Park
    et al.'s coloured ICP. A stage that pairs no point leaves the transform where it was."""
    from scipy.spatial import cKDTree

    tree = cKDTree(target.points)
    for scale, iters in stages:
        distance = scale * voxel
        gradients = color_gradients(target, tree, 2.0 * distance) if colored else None
        moved = transform_points(T, source.points)
        pairs, fitness, rmse = _pairs(tree, moved, distance)
        found = T
        for _ in range(iters):
            if not fitness:
                break
            step = _icp_step(moved, source, target, pairs, gradients)
            found, moved = step @ found, transform_points(step, moved)
            before = fitness, rmse
            pairs, fitness, rmse = _pairs(tree, moved, distance)
            if abs(fitness - before[0]) < CONVERGED and abs(rmse - before[1]) < CONVERGED:
                break
        if fitness > 0:
            T = found
    return T


def to_open3d(cloud: Cloud) -> Any:
    """An Open3D point cloud of a `grid_cloud` (points, colours, normals)."""
    o3d = open3d_module("Open3D's registration")
    vectors = o3d.utility.Vector3dVector
    pcd = o3d.geometry.PointCloud()
    pcd.points = vectors(np.ascontiguousarray(cloud.points, dtype=np.float64))
    pcd.colors = vectors(np.ascontiguousarray(cloud.colors, dtype=np.float64))
    if cloud.normals is not None:
        pcd.normals = vectors(np.ascontiguousarray(cloud.normals, dtype=np.float64))
    return pcd


def icp_open3d(
    source: Cloud, target: Cloud, T: np.ndarray, voxel: float, stages: Stages, colored: bool
) -> np.ndarray:
    """`icp_builtin`'s stages through Open3D's `registration_colored_icp` (or its
    point-to-plane ICP)."""
    o3d = open3d_module("the local step with icp 'open3d'")
    reg = o3d.pipelines.registration
    src, tgt = to_open3d(source), to_open3d(target)
    for scale, iters in stages:
        criteria = reg.ICPConvergenceCriteria(
            relative_fitness=CONVERGED, relative_rmse=CONVERGED, max_iteration=iters
        )
        if colored:
            try:
                result = reg.registration_colored_icp(
                    src,
                    tgt,
                    scale * voxel,
                    T,
                    reg.TransformationEstimationForColoredICP(lambda_geometric=LAMBDA_GEOMETRIC),
                    criteria,
                )
            except RuntimeError as exc:  # (Open3D's coloured ICP raises where others return 0)
                if "No correspondences" not in str(exc):
                    raise
                break
        else:
            result = reg.registration_icp(
                src, tgt, scale * voxel, T, reg.TransformationEstimationPointToPlane(), criteria
            )
        if result.fitness > 0:
            T = np.asarray(result.transformation)
    return T


LocalStep = Callable[[Cloud, Cloud, np.ndarray, float, Stages, bool], np.ndarray]

ICP: dict[str, LocalStep] = {"builtin": icp_builtin, "open3d": icp_open3d}
"""The implementations of the local step, by name (`AlignOptions.icp`, `MergeOptions.icp`,
`gsc align --icp`, `gsc merge --icp`): "builtin" needs nothing beyond gscompress's own
dependencies, "open3d" the `[align]` extra."""

DEFAULT_ICP = "builtin"


def local_icp(
    source: Cloud,
    target: Cloud,
    T: np.ndarray,
    voxel: float,
    stages: Stages,
    colored: bool = True,
    icp: str = DEFAULT_ICP,
) -> np.ndarray:
    """`T` (source -> target, [4, 4]) refined by ICP between two `grid_cloud`s (the target's
    normals are used; with `colored`, both clouds' colours), by the implementation `icp`.

    Raises:
        InputError: an unknown `icp`.
        MissingDependencyError: "open3d" without Open3D.
    """
    if icp not in ICP:
        raise InputError(f"icp is one of {', '.join(ICP)}, got {icp!r}")
    return ICP[icp](source, target, np.asarray(T, dtype=np.float64), voxel, stages, colored)
