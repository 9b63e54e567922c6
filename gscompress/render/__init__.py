"""Differentiable Gaussian rasterizer: one `render()` call, three backends.

`render(means, quats, scales, opacities, colors, intrinsics, T_cam_world)` draws colour, depth
and silhouette of activated 3D Gaussians and is differentiable w.r.t. all of them, the camera
pose included. Backends: "torch" (pure torch, the oracle), "cpu" (C++/OpenMP kernels built on
first use) and "gsplat" (CUDA); "auto" picks the fastest available.

The rules every backend follows (projection and binning: `gscompress.render.projection`):

- EWA projection with a 0.3 px^2 low-pass dilation, 3-sigma radii, 16x16 tiles, and
  Gaussians with camera depth z < near culled.
- Per pixel, the Gaussians of its tile are composited front to back (by depth) with
  alpha_i = min(0.99, o_i exp(-0.5 d^T conic_i d)), d = pixel centre - projected centre;
  w_i = alpha_i T_i with T_i = prod_{j < i} (1 - alpha_j).
- A Gaussian with alpha_i < 1/255 is skipped (T unchanged).
- Compositing stops at the first Gaussian for which T_i (1 - alpha_i) < 1e-4; that Gaussian is
  NOT composited (as in the reference 3DGS rasterizer), so T_final >= 1e-4 always.
- color = sum_i w_i c_i + T_final * background, depth = sum_i w_i z_i,
  silhouette = sum_i w_i (computed as 1 - T_final), depth_normalized = depth / silhouette.
- contribution_i = sum over pixels of w_i.

The cpu backend's C++ projection and binning repeat the torch code's operations in the same
order (the same values and lists, bit for bit), and its compositing agrees with torch's to
rounding (tested: 1e-10 relative in float64, 1e-5 in float32, values and gradients); its results
do not depend on the number of threads. gsplat differs in corner cases (see
`gscompress.render.gsplat_backend`).
"""

from gscompress.render.core import BACKENDS, RenderOutput, render, resolve_backend, resolve_device

__all__ = ["BACKENDS", "RenderOutput", "render", "resolve_backend", "resolve_device"]
