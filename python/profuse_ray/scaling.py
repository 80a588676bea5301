"""Scaling of the Ray driver's fuse shards with the number of worker processes.

    PROFUSE_BIN_DIR=target/release python3 python/profuse_ray/scaling.py SCENE [--workers 1,2,4]
        [--shard-views 25] [--set pq.m=16 ...]

Runs the driver once (gs-init and warp-graph then stay up to date), then for each worker
count starts a local Ray cluster of that many one-CPU nodes, removes the fuse shards and
the fuse stage's record, and runs the driver again, timing each step. Prints one JSON
object: per worker count the wall seconds of the shard step and of the whole run, and
whether the features equal the first run's bytes.
"""

import argparse
import hashlib
import json
import os
import shutil
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
os.environ["PYTHONPATH"] = str(HERE) + os.pathsep + os.environ.get("PYTHONPATH", "")

from profuse_ray import driver  # noqa: E402


def run_with_workers(plan: driver.Plan, workers: int) -> dict:
    import ray
    from ray.cluster_utils import Cluster

    cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": 1})
    for _ in range(workers - 1):
        cluster.add_node(num_cpus=1)
    ray.init(address=cluster.address, log_to_driver=False)
    try:
        t0 = time.monotonic()
        summary = driver.run_pipeline(plan)
        return {"summary": summary, "wall_s": time.monotonic() - t0}
    finally:
        ray.shutdown()
        cluster.shutdown()


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("scene")
    ap.add_argument("--workers", default="1,2,4")
    ap.add_argument("--shard-views", type=int, default=25)
    ap.add_argument("--threads-per-task", type=int)
    ap.add_argument("--set", action="append", default=[])
    args = ap.parse_args()
    scene = Path(args.scene).resolve()
    plan = driver.Plan(
        scene=scene,
        out=scene / "out",
        bin_dir=Path(os.environ["PROFUSE_BIN_DIR"]).resolve(),
        shard_views=args.shard_views,
        sets=args.set,
        threads_per_task=args.threads_per_task,
        quiet=True,
    )
    first = run_with_workers(plan, 2)
    features = scene / "out" / "features.safetensors"
    reference = hashlib.sha256(features.read_bytes()).hexdigest()
    rows = []
    for n in [int(w) for w in args.workers.split(",")]:
        shutil.rmtree(scene / "out" / "shards", ignore_errors=True)
        (scene / "out" / ".stamps" / "fuse.json").unlink(missing_ok=True)
        r = run_with_workers(plan, n)
        wall = r["summary"]["ray"]["wall_s"]
        shards = r["summary"]["ray"]["shards"]
        rows.append(
            {
                "workers": n,
                "shards": len(shards),
                "shard_step_s": next(v for k, v in wall.items() if k.startswith("fuse shards")),
                "shard_task_s": sum(s["seconds"] for s in shards),
                "run_s": wall["total"],
                "features_identical": hashlib.sha256(features.read_bytes()).hexdigest() == reference,
            }
        )
        print(json.dumps(rows[-1]), file=sys.stderr, flush=True)
    stages = first["summary"]["ray"]["stages_before_fuse"]
    print(json.dumps({"first_run_s": first["wall_s"], "stages_before_fuse": stages, "rows": rows}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
