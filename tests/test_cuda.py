"""The SLAM run and its evaluation on CUDA (gsplat), against the same run on the CPU.

Skipped without CUDA and gsplat; `gscompress.render`'s kernels are compared with the pure-torch
reference in test_render.py.
"""

from __future__ import annotations

import pytest
from test_render import gpu

from gscompress.datasets.synthetic import write_synthetic_sequence
from gscompress.io.mcap_log import LogReader
from gscompress.pipeline import evaluate_log, slam_file
from gscompress.pipeline.images import ImageOptions
from gscompress.pipeline.slam_run.options import SlamOptions

pytestmark = [pytest.mark.gpu, gpu]


def test_slam_on_cuda_maps_as_well_as_on_the_cpu(tmp_path):
    seq = write_synthetic_sequence(tmp_path / "room", 6, (64, 48))
    runs = {}
    for device in ("cpu", "cuda"):
        log = tmp_path / f"{device}.mcap"
        result = slam_file(seq, log, SlamOptions(preset="tiny"), device=device)
        with LogReader(log) as reader:
            assert reader.metadata.results["device"].startswith(device)
        runs[device] = (result, evaluate_log(log, seq, ImageOptions(device=device, lpips=False)))
    (cpu, cpu_eval), (cuda, cuda_eval) = runs["cpu"], runs["cuda"]
    assert cuda["render_backend"] == "gsplat" and cuda["frames"] == cpu["frames"] == 6
    assert cuda_eval["ate_rmse_cm"] < 1.5 * cpu_eval["ate_rmse_cm"] + 0.5
    assert cuda_eval["psnr"] > cpu_eval["psnr"] - 1.5
    assert cuda_eval["ssim"] > cpu_eval["ssim"] - 0.05
    # the CUDA map evaluated on the CPU renders alike (eval moves the map, not the log)
    cross = evaluate_log(tmp_path / "cuda.mcap", seq, ImageOptions(device="cpu", lpips=False))
    assert cross["psnr"] == pytest.approx(cuda_eval["psnr"], abs=0.5)
