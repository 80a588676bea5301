"""Run the ProFuse pipeline on a Ray cluster.

The per-view work of the fuse stage is split into view shards that run as Ray tasks on
any node; everything else runs as one task each. Tasks run the project's own tools
(`profuse run --until`, `profuse fuse-shard`, `profuse run --fuse-partials`) on files in
a directory every node sees, so the outputs are byte-identical to `profuse run` on one
machine. See README.md, "Running on a cluster".
"""

from .driver import Plan, main, run_pipeline, shard_ranges

__all__ = ["Plan", "main", "run_pipeline", "shard_ranges"]
