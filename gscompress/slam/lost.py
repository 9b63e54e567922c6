"""Lost-track detection and re-localisation against the map.

Real recordings drop frames, blur and jump. A frame's track is judged by its depth error after
tracking (the mean absolute depth error over the tracking mask, in metres), against the running
level of the frames accepted before it: geometry is what a wrong pose breaks first, while the
colour error also rises with exposure changes and motion blur on a well-tracked frame. A track
is lost when

- that error exceeds `TrackingConfig.lost_factor` times the level (the median over the last
  `LEVEL_FRAMES` accepted frames, once `LEVEL_MIN_FRAMES` are in),
- less than `lost_coverage` of the frame's valid depth pixels lie on the map, or
- the frame comes more than `max_gap` seconds after the previous one (the velocity guess then
  spans an unknown motion).

A lost frame is tracked again from each of `relocalisation_guesses` and the best result (lowest
depth error among those that cover enough of the frame) is taken when it passes the same test;
otherwise the run stops with `gscompress.errors.TrackingLostError`.
"""

from __future__ import annotations

import logging
from collections import deque
from collections.abc import Callable
from typing import NamedTuple

import numpy as np

from gscompress.errors import TrackingLostError
from gscompress.slam.config import TrackingConfig
from gscompress.slam.poses import orthonormalize
from gscompress.slam.tracker import TrackResult

log = logging.getLogger(__name__)

LEVEL_FRAMES = 10
"""Accepted frames whose depth errors make the running level (their median)."""

LEVEL_MIN_FRAMES = 3
"""Accepted frames needed before the depth error is judged against the level."""

KEYFRAME_GUESSES = 3
"""Latest keyframes whose poses are tried when a track is lost."""

VELOCITY, PREVIOUS = "the velocity guess", "the previous pose"
"""The names of a frame's own guesses (`relocalisation_guesses`)."""


class TrackLevel:
    """The running level of the accepted frames' depth errors."""

    def __init__(self) -> None:
        self.errors: deque[float] = deque(maxlen=LEVEL_FRAMES)

    def add(self, result: TrackResult) -> None:
        """Count an accepted frame's track."""
        self.add_error(result.depth)

    def add_error(self, depth_error: float) -> None:
        """Count an accepted frame's depth error (a resumed run's, from its log's statistics)."""
        if np.isfinite(depth_error):
            self.errors.append(float(depth_error))

    def level(self) -> float | None:
        """The median depth error of the latest accepted frames (None until enough)."""
        if len(self.errors) < LEVEL_MIN_FRAMES:
            return None
        return float(np.median(self.errors))


def lost_reason(
    result: TrackResult, valid_pixels: int, level: float | None, config: TrackingConfig
) -> str | None:
    """Why a track is lost, or None when it is not.

    Args:
        result: the frame's track.
        valid_pixels: the frame's pixels with a depth measurement.
        level: the running level of the depth error (None: too few frames to judge by, and
            the track is not judged).
        config: `lost_factor` and `lost_coverage`.
    """
    if level is None:  # (the run's first frames, or a resumed run's: nothing to judge by)
        return None
    reason = coverage_reason(result, valid_pixels, config)
    if reason is not None:
        return reason
    if config.lost_factor > 0 and level > 0:
        ratio = result.depth / level
        if not ratio <= config.lost_factor:  # (also NaN)
            return f"its depth error is {ratio:.1f}x the running level"
    return None


def coverage_reason(result: TrackResult, valid_pixels: int, config: TrackingConfig) -> str | None:
    """Why a track covers too little of its frame (`lost_coverage`), or None."""
    coverage = result.pixels / valid_pixels if valid_pixels else 0.0
    if coverage < config.lost_coverage or (result.pixels == 0 and config.lost_coverage > 0):
        return f"{coverage:.0%} of its depth lies on the map"
    return None


def gap_reason(dt: float, config: TrackingConfig) -> str | None:
    """Why a frame `dt` seconds after the previous one is treated as lost, or None."""
    if config.max_gap > 0 and dt > config.max_gap:
        return f"it comes {dt:.3f} s after the previous frame"
    return None


def relocalisation_guesses(
    first: tuple[str, np.ndarray], previous: np.ndarray, keyframe_poses: list[np.ndarray]
) -> list[tuple[str, np.ndarray]]:
    """The named starting poses tried for a lost frame: the frame's own guess `first` (the
    velocity guess, or the previous pose), the `previous` frame's pose and the latest
    keyframes' poses (`keyframe_poses`, oldest first)."""
    guesses = [first]
    if first[0] != PREVIOUS:
        guesses.append((PREVIOUS, orthonormalize(previous)))
    for k, T in enumerate(reversed(keyframe_poses[-KEYFRAME_GUESSES:])):
        guesses.append((f"keyframe pose {k + 1} back", orthonormalize(T)))
    return guesses


class Lost(NamedTuple):
    """A frame whose track was judged lost: its index and stamp, why, its pixels with a depth
    measurement and the running level of the depth error (None: not made yet)."""

    frame: int
    timestamp: float
    reason: str
    valid_pixels: int
    level: float | None


def relocalise(
    track: Callable[[np.ndarray], TrackResult],
    guesses: list[tuple[str, np.ndarray]],
    lost: Lost,
    config: TrackingConfig,
    tracked: TrackResult | None = None,
) -> TrackResult:
    """The lost frame tracked again from each named guess (`track(T_world_cam)`): the result
    with the lowest depth error of those that cover enough of the frame, when it passes the
    lost test, marked `relocalised` and reported in a warning. `tracked`: the frame's track
    from the first guess, when it was already run (it is not run again).

    Raises:
        TrackingLostError: no guess gives a track that passes.
    """
    best: tuple[str, TrackResult] | None = None
    for k, (name, guess) in enumerate(guesses):
        result = tracked if k == 0 and tracked is not None else track(guess)
        covered = coverage_reason(result, lost.valid_pixels, config) is None
        if covered and (best is None or result.depth < best[1].depth):
            best = (name, result)
    if best is None or lost_reason(best[1], lost.valid_pixels, lost.level, config) is not None:
        raise TrackingLostError(lost.frame, lost.timestamp, lost.reason)
    log.warning(
        "frame %d (stamp %.3f s): tracking lost (%s); re-localised against the map from %s",
        lost.frame,
        lost.timestamp,
        lost.reason,
        best[0],
    )
    best[1].relocalised = True
    return best[1]
