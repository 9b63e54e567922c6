"""gscompress: compact 3D Gaussian Splatting maps and bandwidth-aware map sharing.

The package is importable without torch: the offline path (logs, PLY, selection) needs only
numpy, mcap and protobuf. SLAM and rendering import torch where they are used.
"""

from gscompress.errors import GscError
from gscompress.gaussians import GaussianMap

__version__ = "0.2.0"

__all__ = ["GaussianMap", "GscError", "__version__"]
