"""Versioned schema files of the gscompress MCAP log profile (package `gscompress_schemas`).

`PROFILE_VERSION` is the version of the log profile this release writes. A reader accepts logs of
the same major version and refuses newer major versions.

History: 1.0 float32 `/gaussians` fields. 1.1 adds precision fp16: bounded attributes may be
stored as uint16 `<name>_f16` fields holding float16 bit patterns (a 1.0 reader then reports the
plain fields as missing instead of misreading them); float32 logs are unchanged. 1.2 adds the
compact codec: a `/gaussians` message may be a `gscompress.CompactGaussians`
(compact_gaussians.v1.proto; a 1.1 reader refuses its schema by name), on a channel of its own.
"""

from __future__ import annotations

import json
from importlib import resources
from typing import Any

PROFILE = "gscompress"
PROFILE_VERSION = "1.2"


def schema_bytes(name: str) -> bytes:
    """The raw bytes of schema file `name` (e.g. "slam_stats.v1.schema.json")."""
    return resources.files(__name__).joinpath(name).read_bytes()


def load_schema(name: str) -> dict[str, Any]:
    """Schema file `name` parsed as JSON."""
    result: dict[str, Any] = json.loads(schema_bytes(name))
    return result
