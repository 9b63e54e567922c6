"""A sequence whose images a Gaussian map explains exactly: each frame of SEQ rendered from the
map of LOG at the frame's true pose (colour, and the normalised depth where the silhouette
reaches `--silhouette`, else no depth), written in TUM layout with the true poses.

A run on such a "splat world" tracks against data its own renderer can reproduce, so what is
left of a bias there is the mapping's and tracking's own, and what goes away comes from how the
renderer differs from the camera (docs/drift.md, "On data the renderer explains exactly").
`--color observed` / `--depth observed` keep the sequence's own colour or depth instead, to
tell the two apart. The map should be made at the true poses (`tracking.use_ground_truth`).

    gsc slam ROOM -o gt.mcap --config gt.yaml --no-prune     # use_ground_truth: true
    python bench/splat_world.py gt.mcap ROOM world
    gsc slam world --frames 0:24 -o agent.mcap; python bench/drift.py agent.mcap --at 20
"""

from __future__ import annotations

import argparse
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import torch

from gscompress.camera import invert_transform
from gscompress.datasets import open_sequence
from gscompress.datasets.base import Frame
from gscompress.datasets.tum import write_tum_sequence
from gscompress.io.mcap_log import read_map
from gscompress.render import render
from gscompress.slam.params import GaussianParams, RenderInputs


class SplatWorld:
    """`sequence` with its colour and/or depth replaced by renders of `inputs` at true poses."""

    def __init__(self, sequence: Any, inputs: RenderInputs, args: argparse.Namespace):
        self.sequence, self.inputs, self.args = sequence, inputs, args
        self.intrinsics = sequence.intrinsics

    def __len__(self) -> int:
        return len(self.sequence)

    def __getattr__(self, name: str) -> Any:
        return getattr(self.sequence, name)

    def frame(self, i: int) -> Frame:
        f = self.sequence.frame(i)
        if f.T_world_cam is None:
            raise SystemExit(f"frame {i} has no true pose to render from")
        T = torch.as_tensor(invert_transform(f.T_world_cam), dtype=torch.float32)
        with torch.no_grad():
            out = render(*self.inputs, self.intrinsics, T, backend=self.args.backend)
        color, depth = f.color, f.depth
        if self.args.color == "render":
            color = out.color.clamp(0, 1).double().numpy()
        if self.args.depth == "render":
            covered = out.silhouette.numpy() >= self.args.silhouette
            depth = np.where(covered, out.depth_normalized.double().numpy(), 0.0)
        return Frame(f.index, f.timestamp, color, depth, f.T_world_cam)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("log", help="a gsc log whose last map is rendered")
    parser.add_argument("seq", help="the sequence (poses, timestamps, intrinsics)")
    parser.add_argument("out", type=Path, help="output folder (replaced)")
    parser.add_argument("--color", choices=("render", "observed"), default="render")
    parser.add_argument("--depth", choices=("render", "observed"), default="render")
    parser.add_argument("--silhouette", type=float, default=0.99, help="least coverage for depth")
    parser.add_argument("--depth-scale", type=float, default=5000.0, help="PNG units a metre")
    parser.add_argument("--backend", default="auto", help="renderer backend")
    args = parser.parse_args()
    sequence = open_sequence(args.seq)
    params = GaussianParams.from_map(read_map(args.log))
    inputs = RenderInputs(*(t.detach() for t in params.render_inputs()))
    if args.out.exists():
        shutil.rmtree(args.out)
    write_tum_sequence(SplatWorld(sequence, inputs, args), args.out, args.depth_scale)
    print(f"{args.out}: {len(sequence)} frames rendered from {len(params)} Gaussians")


if __name__ == "__main__":
    main()
