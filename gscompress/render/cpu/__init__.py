"""C++/OpenMP kernels of the cpu backend: EWA projection and tile compositing, each with its
backward, tile binning, and the mean SSIM of the mapping loss with its gradient.

The extension is compiled on first use with `torch.utils.cpp_extension.load` into a cache
directory keyed on the sources and their location, the flags, torch, Python and (for the
-march=native build on x86-64) the CPU model and feature flags (`$GSCOMPRESS_CACHE_DIR` or
`$XDG_CACHE_HOME/gscompress`, default `~/.cache/gscompress`); later processes import the finished
build directly. Each new build removes the builds no process has loaded for 30 days. Without a
C++ compiler `load_extension()` returns None and the caller falls back to the pure-torch backend.

`$GSCOMPRESS_MARCH` picks another target than the build machine's: `generic` for portable
flags, or a compiler target such as `x86-64-v3` (AVX2 with FMA) to build, test or time another
vector width than the CPU's widest (`bench/render.py --march`). A target whose instructions the
CPU lacks builds, but the process dies with an illegal instruction on the first render.
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import importlib.util
import logging
import os
import platform
import re
import shutil
import sys
import time
import warnings
from collections.abc import Iterator
from pathlib import Path
from types import ModuleType
from typing import Any

import torch

from gscompress.camera import Intrinsics
from gscompress.errors import InputError
from gscompress.metrics import gaussian_window, ssim_constants
from gscompress.render.projection import Projection, TileBins, tile_grid

logger = logging.getLogger(__name__)

_SOURCES = tuple(Path(__file__).with_name(n) for n in ("composite.cpp", "project.cpp", "ssim.cpp"))
# -ffp-contract=off keeps the forward, the backward and the torch oracle rounding alike.
_CFLAGS = ("-O3", "-fopenmp", "-ffp-contract=off")
_LDFLAGS = ("-fopenmp",)  # tuples: torch's loader appends its libraries to the lists it is given


def _cpu_signature() -> str | None:
    """The CPU's model and feature flags (Linux), or None when they cannot be read."""
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        return None
    lines = [ln for ln in text.splitlines() if ln.startswith(("flags", "model name"))]
    return "\n".join(sorted(set(lines))) or None


MARCH_ENV = "GSCOMPRESS_MARCH"
"""Environment variable naming the `-march` target of the build: `native` (the default),
`generic` (portable flags) or a target of the compiler's, e.g. `x86-64-v3` (AVX2 and FMA)."""


def _build_flags() -> tuple[list[str], str]:
    """Compiler flags and the CPU part of the cache key.

    The kernels are vectorised for the build machine (-march=native, e.g. AVX2 / AVX-512), so
    the cache key includes the CPU's model and feature flags: a home directory shared between
    different machines then holds one build per CPU type instead of a build that crashes.
    Elsewhere (not x86-64, or the CPU cannot be identified) the build uses portable flags.
    `$GSCOMPRESS_MARCH` overrides the target (see `MARCH_ENV`): a named one is keyed by its
    name alone, as it does not depend on the CPU that builds it.

    Raises:
        InputError: a `$GSCOMPRESS_MARCH` that is not a plain target name.
    """
    march = os.environ.get(MARCH_ENV, "").strip() or "native"
    if not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9_.+-]*", march):
        raise InputError(
            f"{MARCH_ENV}={march!r} is not a -march target; use native, generic or a name "
            "such as x86-64-v3"
        )
    if march == "generic":
        return list(_CFLAGS), "generic"
    if march != "native":
        return [*_CFLAGS, f"-march={march}"], f"march={march}"
    cpu = _cpu_signature() if platform.machine() in ("x86_64", "AMD64") else None
    if cpu is None:
        return list(_CFLAGS), "generic"
    return [*_CFLAGS, "-march=native"], cpu


@contextlib.contextmanager
def _build_lock(build_dir: Path) -> Iterator[None]:
    """Hold an OS lock on a build directory and clear the `lock` file a killed build left.

    torch's build waits forever on a `lock` file, which a build killed midway (Ctrl-C on the
    first run) leaves behind. Our builds take `gsc.lock` with flock first, which the OS releases
    when a process dies, so a `lock` found while holding it is stale and is removed.
    """
    try:
        import fcntl
    except ImportError:  # not POSIX: torch's own lock only
        yield
        return
    with open(build_dir / "gsc.lock", "w") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        try:
            (build_dir / "lock").unlink(missing_ok=True)
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


def _cache_root() -> Path:
    """Where the compiled extensions are kept."""
    if "GSCOMPRESS_CACHE_DIR" in os.environ:
        return Path(os.environ["GSCOMPRESS_CACHE_DIR"])
    xdg = os.environ.get("XDG_CACHE_HOME")
    return (Path(xdg) if xdg else Path.home() / ".cache") / "gscompress"


def _cache_key(sources: tuple[Path, ...], cflags: list[str], cpu: str, compiler: str) -> str:
    """16 hex digits naming one build: the sources' bytes and location, flags, toolchain, CPU.

    The location counts because the build directory's ninja file names the sources by path: two
    checkouts of the same sources sharing one cache would otherwise rebuild in turn, 1-2 minutes
    each time (seen when alternating runs of two worktrees).
    """
    key = hashlib.sha256()
    for source in sources:
        key.update(source.read_bytes())
        key.update(str(source.resolve()).encode())
    key.update(" ".join([*cflags, *_LDFLAGS]).encode())
    key.update(f"{torch.__version__}|{sys.version}|{platform.machine()}|{compiler}".encode())
    key.update(cpu.encode())
    return key.hexdigest()[:16]


# Written once a build has loaded. A link killed midway leaves a truncated library, and loading
# one kills the process (SIGBUS), so only a marked build is imported directly.
_BUILT = "gsc.built"


def _load_built(build_dir: Path, name: str) -> ModuleType | None:
    """The extension of a finished earlier build, imported directly; None if there is none.

    The directory's name already fixes the sources' bytes, flags, toolchain and CPU, so there
    is nothing for torch's loader to check: going through it costs 0.2-0.3 s per process
    (importing setuptools, running ninja), this well under 0.01 s.
    """
    path = build_dir / f"{name}.so"
    if not (build_dir / _BUILT).exists() or not path.exists():
        return None
    try:
        spec = importlib.util.spec_from_file_location(name, path)
        if spec is None or spec.loader is None:
            return None
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
    except ImportError:  # e.g. a library it links against has moved: torch's loader decides
        return None
    with contextlib.suppress(OSError):  # the time of last use, for `_prune_cache`
        os.utime(build_dir / _BUILT)
    return module


def _prune_cache(root: Path, keep: Path, unused_days: float = 30.0) -> None:
    """Remove the builds in `root` other than `keep` that no process has loaded for this long.

    Every change of the sources, flags, torch or CPU makes a new build of about 2 MB, and a
    checkout whose sources are edited makes one per edit. Runs only when torch's loader was used
    (a new build, or a build made before the marker existed), so rarely.
    A build's last use is its marker's time (touched at each direct load), else its library's.
    """
    limit = time.time() - unused_days * 86400
    for old in root.glob("ext-*"):
        if old == keep or not re.fullmatch(r"ext-[0-9a-f]{16}", old.name) or not old.is_dir():
            continue
        with contextlib.suppress(OSError):  # e.g. removed meanwhile by another process
            stamps = [old / _BUILT, *old.glob("*.so")]
            times = [p.stat().st_mtime for p in stamps if p.exists()]
            if max(times, default=0.0) < limit:
                shutil.rmtree(old, ignore_errors=True)


@functools.cache
def load_extension() -> ModuleType | None:
    """The compiled kernels, building them on first use; None when no compiler is available.

    A missing compiler or a failed build is reported once with a warning.
    """
    compiler = os.environ.get("CXX", "c++")
    if shutil.which(compiler) is None:
        warnings.warn(
            f"no C++ compiler ({compiler!r}) found: the cpu render backend falls back to pure "
            "torch (slower); install g++ to enable it",
            RuntimeWarning,
            stacklevel=3,
        )
        return None
    cflags, cpu = _build_flags()
    digest = _cache_key(_SOURCES, cflags, cpu, compiler)
    build_dir = _cache_root() / f"ext-{digest}"
    name = f"gsc_composite_{digest}"
    built = _load_built(build_dir, name)
    if built is not None:
        return built
    if not (build_dir / f"{name}.so").exists():
        logger.info("building the C++ render kernels in %s (first use, under a minute)", build_dir)
    try:
        from torch.utils import cpp_extension

        build_dir.mkdir(parents=True, exist_ok=True)
        with _build_lock(build_dir):
            (build_dir / _BUILT).unlink(missing_ok=True)  # until this build has loaded
            module = cpp_extension.load(
                name=name,
                sources=[str(source) for source in _SOURCES],
                extra_cflags=list(cflags),
                extra_ldflags=list(_LDFLAGS),
                build_directory=str(build_dir),
                verbose=False,
            )
            (build_dir / _BUILT).write_text(f"{name}.so\n")
        _prune_cache(build_dir.parent, keep=build_dir)
        return module
    except Exception as exc:  # a build failure must not take rendering down
        first_line = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        target = f" for {MARCH_ENV}={os.environ[MARCH_ENV]}" if os.environ.get(MARCH_ENV) else ""
        warnings.warn(
            f"building the C++ render kernels{target} failed ({first_line}): the cpu render "
            "backend falls back to pure torch",
            RuntimeWarning,
            stacklevel=3,
        )
        return None


class _Composite(torch.autograd.Function):
    """Autograd wrapper: C++ forward, C++ backward."""

    @staticmethod
    def forward(
        ctx: Any,
        ext: ModuleType,
        means2d: torch.Tensor,
        conics: torch.Tensor,
        opacities: torch.Tensor,
        features: torch.Tensor,
        bins: TileBins,
        width: int,
        height: int,
        want_contribution: bool,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        geometry = (width, height, bins.tiles_x, bins.tiles_y)
        image, T_final, last, contribution, packed = ext.composite_forward(
            means2d, conics, opacities, features, bins.offsets, bins.ids, *geometry,
            want_contribution,
        )  # fmt: skip
        ctx.ext, ctx.geometry, ctx.n = ext, geometry, len(means2d)
        # The packed per-entry parameters are reused, so the backward reads no Gaussian twice.
        ctx.save_for_backward(packed, bins.offsets, bins.ids, T_final, last)
        ctx.mark_non_differentiable(contribution)
        return image, T_final, contribution

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(
        ctx: Any, grad_image: torch.Tensor, grad_T: torch.Tensor, _grad_contribution: Any
    ) -> tuple[Any, ...]:
        packed, offsets, ids, T_final, last = ctx.saved_tensors
        g_means2d, g_conics, g_opacities, g_features = ctx.ext.composite_backward(
            packed, offsets, ids, ctx.n, *ctx.geometry, T_final, last,
            grad_image.contiguous(), grad_T.contiguous(),
        )  # fmt: skip
        return None, g_means2d, g_conics, g_opacities, g_features, None, None, None, None


def composite_cpu(
    ext: ModuleType,
    means2d: torch.Tensor,
    conics: torch.Tensor,
    opacities: torch.Tensor,
    features: torch.Tensor,
    bins: TileBins,
    width: int,
    height: int,
    want_contribution: bool,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """C++ counterpart of `gscompress.render.torch_backend.composite_torch` (same contract)."""
    image, T_final, contribution = _Composite.apply(
        ext, means2d.contiguous(), conics.contiguous(), opacities.contiguous(),
        features.contiguous(), bins, width, height, want_contribution,
    )  # fmt: skip
    return image, T_final, (contribution if want_contribution else None)


class _Project(torch.autograd.Function):
    """Autograd wrapper of the C++ projection: the backward recomputes it per Gaussian."""

    @staticmethod
    def forward(
        ctx: Any,
        ext: ModuleType,
        camera: tuple[float, float, float, float, int, int, float],
        means: torch.Tensor,
        quats: torch.Tensor,
        scales: torch.Tensor,
        T_cam_world: torch.Tensor,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        means2d, conics, depths, radii = ext.project_forward(
            means, quats, scales, T_cam_world, *camera
        )
        ctx.ext, ctx.camera = ext, camera
        ctx.save_for_backward(means, quats, scales, T_cam_world)
        ctx.mark_non_differentiable(radii)
        return means2d, conics, depths, radii

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(
        ctx: Any, g_means2d: torch.Tensor, g_conics: torch.Tensor, g_depths: torch.Tensor, _: Any
    ) -> tuple[Any, ...]:
        # tracking renders detached Gaussians: then only the camera's gradient is computed
        want_params = any(ctx.needs_input_grad[2:5])
        d_means, d_quats, d_scales, d_T = ctx.ext.project_backward(
            *ctx.saved_tensors, *ctx.camera,
            g_means2d.contiguous(), g_conics.contiguous(), g_depths.contiguous(), want_params,
        )  # fmt: skip
        if not want_params:
            d_means = d_quats = d_scales = None
        return None, None, d_means, d_quats, d_scales, d_T


def project_cpu(
    ext: ModuleType,
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    T_cam_world: torch.Tensor,
    intrinsics: Intrinsics,
    near: float,
) -> Projection:
    """C++ counterpart of `gscompress.render.projection.project_gaussians` (same contract)."""
    i = intrinsics
    camera = (i.fx, i.fy, i.cx, i.cy, i.width, i.height, near)
    means2d, conics, depths, radii = _Project.apply(
        ext, camera, means.contiguous(), quats.contiguous(), scales.contiguous(),
        T_cam_world.contiguous(),
    )  # fmt: skip
    return Projection(means2d=means2d, conics=conics, depths=depths, radii=radii)


class _Ssim(torch.autograd.Function):
    """Autograd wrapper of the fused C++ mean SSIM; the gradient reaches the first image only."""

    @staticmethod
    def forward(
        ctx: Any, ext: ModuleType, x: torch.Tensor, y: torch.Tensor, k: torch.Tensor,
        constants: tuple[float, float],
    ) -> torch.Tensor:  # fmt: skip
        mean, filtered = ext.ssim_forward(x, y, k, *constants)
        ctx.ext, ctx.constants = ext, constants
        ctx.save_for_backward(x, y, k, filtered)
        return mean

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx: Any, grad: torch.Tensor) -> tuple[Any, ...]:
        x, y, k, filtered = ctx.saved_tensors
        dx = ctx.ext.ssim_backward(x, y, k, filtered, grad, *ctx.constants)
        return None, dx, None, None, None


@functools.cache
def _ssim_window(dtype: torch.dtype) -> torch.Tensor:
    """SSIM's window in `dtype`, made once (the mapping loss asks at every iteration); the
    kernels only read it."""
    return gaussian_window().to(dtype=dtype).contiguous()


def ssim_mean_cpu(ext: ModuleType, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """C++ counterpart of `gscompress.metrics.ssim_maps(x[None], y[None])[0].mean()` for [C, H,
    W] images in [0, 1], differentiable in x; y (the observation) gets no gradient."""
    if y.requires_grad:
        raise ValueError("ssim_mean_cpu differentiates only its first image")
    k = _ssim_window(x.dtype)
    return _Ssim.apply(ext, x.contiguous(), y.to(x.dtype).contiguous(), k, ssim_constants(1.0))


def bin_tiles_cpu(ext: ModuleType, projection: Projection, width: int, height: int) -> TileBins:
    """C++ counterpart of `gscompress.render.projection.bin_tiles` (the same lists)."""
    tiles_x, tiles_y = tile_grid(width, height)
    offsets, ids = ext.bin_tiles(
        projection.means2d.detach().contiguous(), projection.radii.contiguous(),
        projection.depths.detach().contiguous(), tiles_x, tiles_y,
    )  # fmt: skip
    return TileBins(tiles_x=tiles_x, tiles_y=tiles_y, offsets=offsets, ids=ids)
