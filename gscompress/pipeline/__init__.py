"""Glue between files and the pure core: each function here is one `gsc` command's work.

Functions take paths and options, read inputs through `gscompress.io`, call the pure operations
in `gscompress.ops`, `gscompress.slam` and `gscompress.metrics`, and write outputs atomically.
They return a small dict of results that the CLI prints. Nothing here prints or exits.

One module per command, side by side (none imports another: an import-linter contract):

- `import_map`, `export_map`, `export_traj`, `info`, `prune`, `share` (a package: the cut,
  the byte-budget solver, the receiver's request, the reference formats): import-ply,
  export-ply, export-traj, info, prune, share (numpy + mcap only, never torch unless asked to
  refine or solve).
- `score`: score (PWAS for a map made elsewhere).
- `slam_run`: slam (a sequence into a log; resume; inject; a package: `start` is how a run
  starts).
- `merge`: merge (a share into a receiver's map, refined).
- `align`: align (the transform between two agents' world frames).
- `evaluate`: eval and render (ATE and image metrics of a log).
- `recordings`: convert, and the recording side of info.

Below them, the helpers several commands share: `logs` (a log's poses, sequence and keyframes,
rewriting its map, reading a share), `refining` (a map refined on a log's frames), `aligning`
(two logs' world frames registered) and `images` (pictures of rendered views).

Above them, `experiment` (the paper's protocol over several runs; import
`gscompress.pipeline.experiment.run_experiment` from it: it is not re-exported here, so that the
offline commands do not load what it needs).

Modules that need torch import it inside their functions, so importing this package stays cheap.
"""

from gscompress.pipeline.evaluate import evaluate_log
from gscompress.pipeline.export_map import export_ply
from gscompress.pipeline.export_traj import export_trajectory
from gscompress.pipeline.import_map import import_ply
from gscompress.pipeline.info import log_info, map_summary
from gscompress.pipeline.logs import rewrite_map
from gscompress.pipeline.merge import merge_logs
from gscompress.pipeline.prune import prune_log
from gscompress.pipeline.score import score_file, view_poses
from gscompress.pipeline.share import share_log
from gscompress.pipeline.slam_run import resume_slam_file, slam_file

__all__ = [
    "evaluate_log",
    "export_ply",
    "export_trajectory",
    "import_ply",
    "log_info",
    "map_summary",
    "merge_logs",
    "prune_log",
    "resume_slam_file",
    "rewrite_map",
    "score_file",
    "share_log",
    "slam_file",
    "view_poses",
]
