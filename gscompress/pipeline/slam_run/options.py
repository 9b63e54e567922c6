"""A fresh SLAM run's settings (`SlamOptions`): what `gsc slam`, the experiment's runs and the
benchmarks start a run with, and what `--resume` takes from the log instead."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from gscompress.errors import OptionError
from gscompress.selection import check_ratio


@dataclass(frozen=True)
class SlamOptions:
    """What defines a fresh run of `gsc slam` (the options of these names): its config, frames
    and the share it starts with. None (False) everywhere: the config's and all frames.

    Attributes:
        preset: starting configuration (`gscompress.slam.config.PRESETS`; None: the config
            file's `preset:` entry, else `DEFAULT_PRESET`).
        config_path: a YAML config applied on top of the preset.
        frames: frame subset (all, odd, even, START:STOP:STEP; None: all).
        size: working size (W, H), overriding the config's.
        keep: PWAS keep ratio of the pruning stages, overriding the config's.
        no_prune: skip the PWAS pruning stages (cyclic opacity cleanup still runs).
        backend: render backend (`gscompress.render.BACKENDS`), overriding the config's.
        inject: a share log whose Gaussians (with ids and PWAS sums) start the map; its world
            frame must be the run's, unless `share_transform` is given.
        share_transform: a file with the rigid transform from the share's world frame to the
            run's (4x4 or TUM `tx ty tz qx qy qz qw`).
        recording: a recording's `RecordingOptions` (topics, pairing, ground truth; None:
            chosen). The topics read are recorded in the log's results (`recording`), where
            `resume_slam_file` and the commands that reopen the log's sequence take them from.
    """

    preset: str | None = None
    config_path: str | Path | None = None
    frames: str | None = None
    size: tuple[int, int] | None = None
    keep: float | None = None
    no_prune: bool = False
    backend: str | None = None
    inject: str | Path | None = None
    share_transform: str | Path | None = None
    recording: Any = None

    def check(self) -> None:
        """Refuse a keep ratio out of range, a keep ratio without pruning stages and a share
        transform without a share.

        Raises:
            InputError: `keep` not in (0, 1]. OptionError: `keep` with `no_prune`, or
                `share_transform` without `inject`.
        """
        if self.keep is not None:
            check_ratio(self.keep, "`keep`", ("keep",))
            if self.no_prune:
                raise OptionError(
                    "`keep` does not go with `no_prune`: there is no pruning stage",
                    options=("keep", "no_prune"),
                )
        if self.share_transform is not None and self.inject is None:
            raise OptionError("a share transform needs `inject`", options=("inject",))

    @property
    def kept(self) -> tuple[Any, ...]:
        """The values of the settings `--resume` takes from the log, in the order of
        `gscompress.pipeline.slam_run.RESUME_KEEPS` (None: not given), for
        `refuse_own_settings`."""
        return (
            self.preset,
            self.config_path,
            self.frames,
            self.size,
            self.backend,
            self.keep,
            self.inject,
            self.share_transform,
        )

    @property
    def settings(self) -> dict[str, Any]:
        """The settings applied on top of the preset and the config file (`resolve_config`'s
        keyword arguments)."""
        return {
            "size": self.size,
            "keep": self.keep,
            "no_prune": self.no_prune,
            "backend": self.backend,
        }
