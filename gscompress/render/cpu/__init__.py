"""C++/OpenMP kernels of the cpu backend: EWA projection and tile compositing, each with its
backward, tile binning, and the mean SSIM of the mapping loss with its gradient.

`build` compiles them on first use into a cache shared by processes (`load_extension`), and
`kernels` wraps them for autograd (`project_cpu`, `bin_tiles_cpu`, `composite_cpu`,
`ssim_mean_cpu`), each the counterpart of a pure-torch function with the same contract.
"""

from gscompress.render.cpu.build import MARCH_ENV, load_extension
from gscompress.render.cpu.kernels import bin_tiles_cpu, composite_cpu, project_cpu, ssim_mean_cpu

__all__ = [
    "MARCH_ENV",
    "bin_tiles_cpu",
    "composite_cpu",
    "load_extension",
    "project_cpu",
    "ssim_mean_cpu",
]
