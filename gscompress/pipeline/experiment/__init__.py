"""`gsc experiment`: the paper's protocol on any sequence, in one command.

- `protocol`: which runs exist (settings, the split of frames between agents, the run graph);
- `execution`: how they run (in this process or on a pool of workers, reusing finished runs);
- `execution_ray`: as Ray tasks on a cluster (Ray imported only there);
- `cross_agent`: a map scored on A's, B's and all frames at refined poses (a step of the graph);
- `results`: results rows, the rate-distortion curves and the verdicts;
- `report`: the files they are written to: results.json and .csv, results.md (`markdown`) and
  the plots (`plots`);
- `run`: `run_experiment`, which ties the three together.
"""

from gscompress.pipeline.experiment.protocol import (
    MERGE_HOWS,
    SPLITS,
    ExperimentSettings,
    halves,
    plan_size,
    resolve_settings,
)
from gscompress.pipeline.experiment.results import (
    ROW_KEYS,
    paired_difference,
    rate_distortion_curves,
)
from gscompress.pipeline.experiment.run import EXECUTORS, run_experiment

__all__ = [
    "EXECUTORS",
    "MERGE_HOWS",
    "ROW_KEYS",
    "SPLITS",
    "ExperimentSettings",
    "halves",
    "paired_difference",
    "plan_size",
    "rate_distortion_curves",
    "resolve_settings",
    "run_experiment",
]
