"""Beyond one fit on one machine: batches of fits and multi-start, as Ray tasks.

A batch spec (TOML) lists fits as captures x fit configs x seeds (`fit/batch/spec.py`):
```toml
configs = ["glaze.toml", "cup-fit.toml"]   # fit configs, relative to the spec
captures = ["shelf/bowl", "shelf/vase"]    # optional: replace each config's capture
seeds = [0, 1]                             # optional: replace each config's fit.seed
out = "out/shelf"                          # the batch folder (default out/batch)
cpus_per_fit = 1                           # Ray CPUs and Dr.Jit threads per fit
kernel_cache = "~/.drjit/{host}"           # Dr.Jit's kernel cache on each node
```
`layerfit batch SPEC` writes one run folder per fit (`<config>__<capture>__seed<s>/`, as
`layerfit fit` writes them) and `index.json`, `index.csv`, `index.html` (`runner.py`).
`layerfit fit --starts K` (or `fit.starts`) runs one fit from K starts (`starts.py`).
"""

from ..cluster import Cancelled, connect
from .runner import run_batch, write_index
from .spec import Batch, BatchSpec, Job, load_batch

__all__ = [
    "Batch",
    "BatchSpec",
    "Cancelled",
    "Job",
    "connect",
    "load_batch",
    "run_batch",
    "write_index",
]
