"""Glue between files and the pure core: each function here is one `gsc` command's work.

Functions take paths and options, read inputs through `gscompress.io`, call the pure operations
in `gscompress.ops`, `gscompress.slam` and `gscompress.metrics`, and write outputs atomically.
They return a small dict of results that the CLI prints. Nothing here prints or exits.

- `offline`: import-ply, prune, share, export-ply, export-traj, info (numpy + mcap only, never
  torch).
- `scoring`: score (PWAS for a map made elsewhere).
- `slam_run`: slam (a sequence into a log; resume; inject).
- `merge`: merge (a share into a receiver's map, refined).
- `evaluate`: eval (ATE and image metrics of a log).
- `experiment`: experiment (the paper's protocol over several runs; import
  `gscompress.pipeline.experiment.run_experiment` from it: it is not re-exported here, so that
  the offline commands do not load what it needs).

Modules that need torch import it inside their functions, so importing this package stays cheap.
"""

from gscompress.pipeline.evaluate import evaluate_log
from gscompress.pipeline.merge import merge_logs
from gscompress.pipeline.offline import (
    export_ply,
    export_trajectory,
    import_ply,
    log_info,
    map_summary,
    prune_log,
    rewrite_map,
    share_log,
)
from gscompress.pipeline.scoring import score_file, view_poses
from gscompress.pipeline.slam_run import slam_file

__all__ = [
    "evaluate_log",
    "export_ply",
    "export_trajectory",
    "import_ply",
    "log_info",
    "map_summary",
    "merge_logs",
    "prune_log",
    "rewrite_map",
    "score_file",
    "share_log",
    "slam_file",
    "view_poses",
]
