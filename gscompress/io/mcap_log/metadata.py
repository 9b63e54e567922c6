"""The log profile's names (topics, frames, the metadata record's name) and its metadata record
(`LogMetadata`: what wrote a log, from what, and how it was derived)."""

from __future__ import annotations

import json
import re
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from gscompress import __version__
from gscompress.errors import LogFormatError
from gscompress.io.files import safe_text, safe_value, sha256
from gscompress_schemas import PROFILE_VERSION

TOPIC_GAUSSIANS = "/gaussians"
TOPIC_POSE = "/camera/pose"
TOPIC_POSE_GT = "/camera/pose_gt"
TOPIC_POSE_REFINED = "/camera/pose_refined"
TOPIC_TF = "/tf"
TOPIC_CALIBRATION = "/camera/calibration"
TOPIC_STATS = "/slam/stats"


def seconds_to_ns(seconds: float) -> int:
    """Integer nanoseconds (log times) from seconds."""
    return round(float(seconds) * 1e9)


METADATA_NAME = "gscompress"
WORLD_FRAME = "world"
CAMERA_FRAME = "camera"
STATS_SCHEMA = "slam_stats.v1.schema.json"

POSES_ESTIMATED = "estimated"
POSES_GROUND_TRUTH = "ground-truth"
"""What `LogMetadata.pose_origin` says of a log's poses (or a trajectory file's name)."""


@dataclass
class LogMetadata:
    """The `gscompress` metadata record of a log.

    Attributes:
        profile_version: log profile version the file was written with ("major.minor").
        tool_version: gscompress version that wrote the file.
        command: the command line that produced the file.
        config: full configuration of the run (JSON-serialisable).
        sequence: name of the recorded sequence, if any.
        frames: frame subset of the sequence ("all", "odd", "even", "A:B:C").
        world_frame: what the map's world frame is anchored to, so that maps of two agents
            are only merged when their frames agree: "ground-truth:<sequence>" (first frame at
            its ground-truth pose), "first-camera:<sequence>:<frame>" (first camera at the
            identity), or "" when unknown (e.g. a PLY from another tool).
        provenance: oldest first, one entry per derivation step: {"operation", "parent",
            "parent_sha256", ...parameters}.
        results: what the operation that wrote this file reports (e.g. selected / total counts).
    """

    profile_version: str = PROFILE_VERSION
    tool_version: str = __version__
    command: str = ""
    config: dict[str, Any] = field(default_factory=dict)
    sequence: str = ""
    frames: str = ""
    world_frame: str = ""
    provenance: list[dict[str, Any]] = field(default_factory=list)
    results: dict[str, Any] = field(default_factory=dict)

    _JSON_FIELDS = ("config", "provenance", "results")

    def to_record(self) -> dict[str, str]:
        """The MCAP metadata map (string -> string; structured values as JSON), its text valid
        UTF-8 whatever the names it records (`safe_text`: a file name that is not UTF-8 is
        written with `\\xNN` escapes)."""
        return {
            key: json.dumps(safe_value(value), sort_keys=True)
            if key in self._JSON_FIELDS
            else safe_text(str(value))
            for key, value in asdict(self).items()
        }

    @classmethod
    def from_record(cls, record: dict[str, str], source: str = "log") -> LogMetadata:
        """Parse a metadata map, refusing profile versions newer than this reader's major."""
        version = record.get("profile_version", "")
        if not re.fullmatch(r"[0-9]+\.[0-9]+", version):  # (ASCII digits: str.isdigit is wider)
            raise LogFormatError(f"{source}: bad profile_version {version!r}")
        major = int(version.split(".")[0])
        if major > int(PROFILE_VERSION.split(".")[0]):
            raise LogFormatError(
                f"{source} was written with log profile {version}, newer than this gscompress "
                f"({__version__}, profile {PROFILE_VERSION}); upgrade gscompress to read it"
            )
        values: dict[str, Any] = {}
        for key in (
            "profile_version",
            "tool_version",
            "command",
            "sequence",
            "frames",
            "world_frame",
        ):
            values[key] = record.get(key, "")
        try:
            for key in cls._JSON_FIELDS:
                if key in record:
                    values[key] = json.loads(record[key])
        except json.JSONDecodeError as exc:
            raise LogFormatError(f"{source}: metadata field is not JSON ({exc})") from None
        except RecursionError:
            raise LogFormatError(f"{source}: metadata field is JSON nested too deep") from None
        steps = values.get("provenance", [])
        well_formed = isinstance(steps, list) and all(
            isinstance(step, dict)
            and isinstance(step.get("operation"), dict)
            and isinstance(step.get("parent"), str)
            and isinstance(step.get("parent_sha256"), str)
            for step in steps
        )
        if not well_formed or not all(
            isinstance(values.get(key, {}), dict) for key in ("config", "results")
        ):
            raise LogFormatError(
                f"{source}: metadata config and results must be JSON objects, provenance a list "
                "of steps {operation, parent, parent_sha256}"
            )
        return cls(**values)

    def pose_origin(self) -> str:
        """Where the log's `/camera/pose` messages came from: "ground-truth" (the sequence's,
        as `gsc score` of a PLY or a SLAM run with `tracking.use_ground_truth` writes them),
        "estimated" (tracked), or the name of the trajectory file they were read from.

        Said by `results["poses"]`, else by the newest provenance step that names its poses
        (`gsc score`'s), else by the SLAM config the log carries.
        """
        said = self.results.get("poses")
        if said is None:
            steps = (step["operation"] for step in reversed(self.provenance))
            said = next((op["poses"] for op in steps if "poses" in op), None)
        if isinstance(said, str) and said:
            return said
        tracking = self.config.get("tracking")
        if isinstance(tracking, dict) and tracking.get("use_ground_truth") is True:
            return POSES_GROUND_TRUTH
        return POSES_ESTIMATED

    def derive(
        self, operation: dict[str, Any], parent: str | Path, command: str | None = None
    ) -> LogMetadata:
        """Metadata for a file derived from `parent` by `operation`, run as `command` (None:
        this metadata's): the sequence, config and world frame carried over, the provenance
        step appended."""
        parent = Path(parent)
        step = {"operation": operation, "parent": parent.name, "parent_sha256": sha256(parent)}
        return LogMetadata(
            command=self.command if command is None else command,
            config=self.config,
            sequence=self.sequence,
            frames=self.frames,
            world_frame=self.world_frame,
            provenance=[*self.provenance, step],
        )
