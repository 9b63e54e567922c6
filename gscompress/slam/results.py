"""What processing one frame did (`FrameResult`) and the `/slam/stats` record it writes."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from gscompress.slam.mapper import MappingStats
from gscompress.slam.tracker import TrackResult

PHASES = ("tracking", "densification", "mapping", "pwas", "pruning", "refinement")
"""The timed phases of a frame (milliseconds in `FrameResult.ms`)."""


@dataclass
class FrameResult:
    """What processing one frame did.

    Attributes:
        position: 0-based processing position (frames processed before this one).
        frame: the frame's index in the sequence.
        timestamp: the frame's timestamp, seconds.
        T_world_cam: [4, 4] estimated camera-to-world pose.
        keyframe: whether the frame became a keyframe.
        gaussians: Gaussians in the map after the frame.
        added: Gaussians added by densification (and by the refill after a pruning stage).
        removed: Gaussians removed (cyclic cleanup and pruning stage).
        event: "prune-stage-K" when the K-th pruning stage ran after this frame,
            "prune-size" when a stage ran because the map outgrew `prune.max_gaussians`,
            else None.
        tracking: the tracking outcome (None for the first frame and for ground-truth poses).
        mapping: the mapping statistics.
        refinement: the refinement after a pruning stage and/or after the last frame
            (`prune.refine_iters`, `mapping.final_iters`), None when there was none.
        psnr: PSNR (dB) of the frame rendered after mapping, all pixels.
        next_id: the id the next new Gaussian will get (for resuming).
        ms: milliseconds per phase (see PHASES) and "total".
    """

    position: int
    frame: int
    timestamp: float
    T_world_cam: np.ndarray
    keyframe: bool
    gaussians: int
    added: int
    removed: int
    event: str | None
    tracking: TrackResult | None
    mapping: MappingStats
    psnr: float
    refinement: MappingStats | None = None
    next_id: int = 0
    ms: dict[str, float] = field(default_factory=dict)

    def stats(self) -> dict[str, Any]:
        """The `/slam/stats` record (schemas/slam_stats.v1.schema.json)."""
        record: dict[str, Any] = {
            "frame": self.frame,
            "timestamp": self.timestamp,
            "gaussians": self.gaussians,
            "added": self.added,
            "removed": self.removed,
            "keyframe": self.keyframe,
            "tracking_iters": self.tracking.iters if self.tracking else 0,
            "mapping_iters": self.mapping.iters,
            "loss_mapping": self.mapping.loss,
            "loss_color": self.mapping.color,
            "loss_depth": self.mapping.depth,
            "loss_illum": self.mapping.illum,
            "w_illum": self.mapping.w_illum,
            "next_id": self.next_id,
            "ms": {k: round(v, 3) for k, v in self.ms.items()},
        }
        if self.refinement is not None:
            record["refine_iters"] = self.refinement.iters
            record["refill_added"] = self.refinement.added
            record["loss_refine"] = self.refinement.loss
            record["loss_refine_last"] = self.refinement.last_loss
        if self.tracking is not None:
            record["loss_tracking"] = self.tracking.loss
            record["loss_tracking_initial"] = self.tracking.first_loss
            record["tracking_depth_error"] = self.tracking.depth
            if self.tracking.relocalised:
                record["relocalised"] = True
        if np.isfinite(self.psnr):
            record["psnr"] = self.psnr
        if self.event:
            record["event"] = self.event
        return {k: v for k, v in record.items() if not isinstance(v, float) or np.isfinite(v)}
