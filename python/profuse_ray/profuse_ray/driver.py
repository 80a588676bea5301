"""The Ray driver: `python -m profuse_ray run SCENE ...` (or `profuse-ray run ...`).

Why files in a shared directory and not Ray's object store: every stage of the project
reads and writes memory-mapped safetensors files (Gaussians, masks, proposals, partial
sums of hundreds of MB at scale), and the tools validate and write them atomically. Moving
them through the object store would copy each one into worker memory and back to disk for
the next tool; a shared directory (NFS, Lustre, a cloud file store) lets each task map
exactly what it reads. The object store only carries the small JSON reports.

Why shards of the fuse stage: registration renders every view (about 97% of its time)
into exact fixed-point partial sums that add up associatively, so view shards on many
machines merge into byte-identical features (`profuse fuse-shard` + `profuse run
--fuse-partials`, which refuses shards of other inputs). gs-init, warp-graph, pq, query
and vertex-transfer run as one task each.

Failures: every task is idempotent (tools write to a temporary file and rename) and is
retried by Ray (`--max-retries`) when its worker dies or the tool fails; a shard whose
partial-sums file is already there and valid is not recomputed, so a rerun skips finished
shards. The shard files live under OUT/shards/fuse-<key>/, where the key hashes the
records of the stages the shards depend on and the configuration: shards of an older
upstream are never mixed in.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

# A test can hold shard tasks at their start (to kill a worker mid-run): the task writes
# `<dir>/<a>_<b>.<pid>` and waits until `<dir>/release` exists. Not for production use.
HOLD_ENV = "PROFUSE_RAY_HOLD_DIR"


@dataclass
class Plan:
    """Everything a run needs; every path absolute and visible on every node."""

    scene: Path
    out: Path
    bin_dir: Path
    shard_views: int = 8
    config: Optional[Path] = None
    sets: list = field(default_factory=list)
    max_retries: int = 3
    threads_per_task: Optional[int] = None
    quiet: bool = False

    def tool(self, name: str) -> str:
        return str(self.bin_dir / name)

    def common_args(self) -> list:
        args = ["--out-dir", str(self.out), "--quiet"]
        if self.config is not None:
            args += ["--config", str(self.config)]
        for s in self.sets:
            args += ["--set", s]
        return args


class ToolError(RuntimeError):
    """A tool exited with a non-zero status; carries its command and stderr."""


def shard_ranges(views: int, shard_views: int) -> list:
    """Half-open view ranges of at most `shard_views` views covering 0..views."""
    if views <= 0:
        raise ValueError(f"the scene has {views} views; nothing to shard")
    if shard_views <= 0:
        raise ValueError(f"--shard-views must be positive, got {shard_views}")
    return [(a, min(a + shard_views, views)) for a in range(0, views, shard_views)]


def _die_with_parent() -> None:
    """Makes a tool die with the Ray worker that started it (Linux), so a killed worker
    leaves no orphan computing the same shard."""
    try:
        import ctypes

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


def run_tool(argv: list, threads: Optional[int] = None) -> dict:
    """Runs one tool; returns its JSON report, wall seconds and host."""
    env = dict(os.environ)
    if threads:
        env["RAYON_NUM_THREADS"] = str(threads)
    t0 = time.monotonic()
    proc = subprocess.run(
        argv,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
        preexec_fn=_die_with_parent if sys.platform.startswith("linux") else None,
    )
    seconds = time.monotonic() - t0
    if proc.returncode != 0:
        raise ToolError(
            f"{' '.join(argv)} exited with {proc.returncode}:\n{proc.stderr.strip()[-4000:]}"
        )
    try:
        report = json.loads(proc.stdout) if proc.stdout.strip() else None
    except json.JSONDecodeError:
        report = None
    return {"report": report, "seconds": seconds, "host": socket.gethostname(), "pid": os.getpid()}


def _hold_if_asked(a: int, b: int) -> None:
    hold = os.environ.get(HOLD_ENV)
    if not hold:
        return
    d = Path(hold)
    (d / f"{a}_{b}.{os.getpid()}").write_text("")
    deadline = time.monotonic() + 120
    while not (d / "release").exists() and time.monotonic() < deadline:
        time.sleep(0.05)


def fuse_shard_task(plan: Plan, a: int, b: int, partial: str) -> dict:
    """One view shard; skipped when its valid partial-sums file is already there."""
    if Path(partial).is_file():
        check = subprocess.run(
            [plan.tool("profuse"), "inspect", partial],
            stdout=subprocess.PIPE,
            stderr=subprocess.DEVNULL,
            text=True,
        )
        try:
            kind = json.loads(check.stdout).get("kind") if check.returncode == 0 else None
        except json.JSONDecodeError:
            kind = None
        if kind == "fuse_partial":
            return {"report": None, "seconds": 0.0, "host": socket.gethostname(), "skipped": True}
    _hold_if_asked(a, b)
    argv = [plan.tool("profuse"), "fuse-shard", str(plan.scene), "--views", f"{a}..{b}"]
    argv += ["--partial-out", partial] + plan.common_args()
    result = run_tool(argv, plan.threads_per_task)
    result["skipped"] = False
    return result


def _stage_key(plan: Plan) -> str:
    """Hash of what the fuse shards depend on: the completion records of gs-init and of
    the proposals (their inputs', outputs' and parameters' fingerprints) and the
    configuration arguments."""
    h = hashlib.sha256()
    for stage in ["gs-init", "warp-graph", "proposals"]:
        p = plan.out / ".stamps" / f"{stage}.json"
        h.update(stage.encode() + b"\0")
        if p.is_file():
            h.update(p.read_bytes())
    h.update(json.dumps([str(plan.config), plan.sets]).encode())
    return h.hexdigest()[:16]


def _log(plan: Plan, msg: str) -> None:
    if not plan.quiet:
        print(msg, file=sys.stderr, flush=True)


def _remote(fn, plan: Plan):
    import ray

    return ray.remote(num_cpus=1, max_retries=plan.max_retries, retry_exceptions=True)(fn)


def run_pipeline(plan: Plan) -> dict:
    """Runs the whole pipeline on the connected Ray cluster; returns `profuse run`'s
    summary with a `ray` section (shards, hosts, per-stage wall seconds)."""
    import ray

    tool = _remote(run_tool, plan)
    shard_task = _remote(fuse_shard_task, plan)
    t_start = time.monotonic()
    timing = {}

    t0 = time.monotonic()
    head_argv = [plan.tool("profuse"), "run", str(plan.scene), "--until", "warp-graph"]
    head = tool.remote(head_argv + plan.common_args(), plan.threads_per_task)
    views_ref = tool.remote([plan.tool("profuse"), "inspect", str(plan.scene / "cameras.safetensors")])
    head, views_info = ray.get([head, views_ref])
    timing["gs-init + warp-graph (1 task)"] = time.monotonic() - t0
    views = int(views_info["report"]["counts"]["views"])

    ranges = shard_ranges(views, plan.shard_views)
    shard_dir = plan.out / "shards" / f"fuse-{_stage_key(plan)}"
    shard_dir.mkdir(parents=True, exist_ok=True)
    partials = [str(shard_dir / f"views_{a}_{b}.safetensors") for a, b in ranges]
    t0 = time.monotonic()
    pending = {shard_task.remote(plan, a, b, p): (a, b) for (a, b), p in zip(ranges, partials)}
    shards, done = [], 0
    _log(plan, f"profuse-ray: fuse shards 0/{len(ranges)}")
    while pending:
        ready, _ = ray.wait(list(pending), num_returns=1)
        for ref in ready:
            a, b = pending.pop(ref)
            r = ray.get(ref)
            shards.append({"views": [a, b], "seconds": r["seconds"], "host": r["host"], "skipped": r["skipped"]})
            done += 1
            _log(plan, f"profuse-ray: fuse shards {done}/{len(ranges)}")
    timing[f"fuse shards ({len(ranges)} tasks)"] = time.monotonic() - t0

    t0 = time.monotonic()
    tail_argv = [plan.tool("profuse"), "run", str(plan.scene), "--fuse-partials", *partials]
    tail = ray.get(tool.remote(tail_argv + plan.common_args(), plan.threads_per_task))
    timing["fuse merge + pq + query + vertex-transfer (1 task)"] = time.monotonic() - t0
    timing["total"] = time.monotonic() - t_start

    summary = tail["report"] or {}
    shards.sort(key=lambda s: s["views"])
    summary["ray"] = {
        "shards": shards,
        "shard_views": plan.shard_views,
        "shard_dir": str(shard_dir),
        "stages_before_fuse": (head["report"] or {}).get("stages"),
        "wall_s": timing,
        "nodes": len(ray.nodes()),
    }
    if not plan.quiet:
        print(timing_table(timing, shards), file=sys.stderr)
    return summary


def timing_table(timing: dict, shards: list) -> str:
    lines = ["", f"{'profuse-ray step':<52} {'wall s':>8}"]
    lines += [f"{k:<52} {v:>8.2f}" for k, v in timing.items()]
    busy = sum(s["seconds"] for s in shards)
    skipped = sum(1 for s in shards if s["skipped"])
    hosts = sorted({s["host"] for s in shards})
    lines.append(f"fuse shard task-seconds {busy:.2f} over {len(hosts)} host(s); {skipped} shard(s) already done")
    return "\n".join(lines)


def _connect(args):
    import ray

    if args.local_cluster:
        from ray.cluster_utils import Cluster

        cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": 1})
        for _ in range(args.local_cluster - 1):
            cluster.add_node(num_cpus=1)
        ray.init(address=cluster.address, log_to_driver=False)
        return cluster
    ray.init(address=args.address, log_to_driver=False)
    return None


def _bin_dir(given: Optional[str]) -> Path:
    if given:
        return Path(given).resolve()
    if os.environ.get("PROFUSE_BIN_DIR"):
        return Path(os.environ["PROFUSE_BIN_DIR"]).resolve()
    found = shutil.which("profuse")
    if found:
        return Path(found).resolve().parent
    raise SystemExit("profuse-ray: no `profuse` binary: give --bin-dir, set PROFUSE_BIN_DIR or put it on PATH")


def parse_args(argv=None):
    ap = argparse.ArgumentParser(
        prog="profuse-ray",
        description="Run `profuse run` on a Ray cluster: the fuse stage's views in shards (Ray tasks), "
        "the other stages as one task each, all on files in a directory every node sees. The outputs "
        "are byte-identical to `profuse run` on one machine. Prints the run's JSON summary on stdout; "
        "shard progress and a timing table on stderr.",
    )
    sub = ap.add_subparsers(dest="command", required=True)
    run = sub.add_parser("run", help="run the pipeline on a scene directory")
    run.add_argument("scene", help="the scene directory (on the shared file system)")
    run.add_argument("--out-dir", help="output directory (default SCENE/out), on the shared file system")
    where = run.add_mutually_exclusive_group()
    where.add_argument("--address", default="auto", help="Ray cluster address (default: auto, the running cluster)")
    where.add_argument("--local-cluster", type=int, metavar="N", help="start a local cluster of N one-CPU nodes instead")
    run.add_argument("--shard-views", type=int, default=8, help="views per fuse shard task (default 8)")
    run.add_argument("--bin-dir", help="folder of the profuse tools on every node (default: PROFUSE_BIN_DIR, else PATH)")
    run.add_argument("--config", help="TOML configuration, as for `profuse run`")
    run.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE", help="override one parameter (repeatable)")
    run.add_argument("--max-retries", type=int, default=3, help="retries of a failed task (default 3)")
    run.add_argument("--threads-per-task", type=int, help="RAYON_NUM_THREADS of each tool (default: the tool's)")
    run.add_argument("--quiet", action="store_true", help="no progress or timing table on stderr")
    return ap.parse_args(argv)


def plan_from_args(args) -> Plan:
    scene = Path(args.scene).resolve()
    return Plan(
        scene=scene,
        out=Path(args.out_dir).resolve() if args.out_dir else scene / "out",
        bin_dir=_bin_dir(args.bin_dir),
        shard_views=args.shard_views,
        config=Path(args.config).resolve() if args.config else None,
        sets=list(args.set),
        max_retries=args.max_retries,
        threads_per_task=args.threads_per_task,
        quiet=args.quiet or not sys.stderr.isatty(),
    )


def main(argv=None) -> int:
    args = parse_args(argv)
    plan = plan_from_args(args)
    try:
        import ray  # noqa: F401
    except ImportError:
        print("profuse-ray: Ray is not installed (pip install 'ray[default]')", file=sys.stderr)
        return 1
    cluster = _connect(args)
    try:
        summary = run_pipeline(plan)
    except Exception as e:  # the tool's own message names the file and field
        print(f"profuse-ray: {e}", file=sys.stderr)
        return 1
    finally:
        import ray

        ray.shutdown()
        if cluster is not None:
            cluster.shutdown()
    print(json.dumps(summary, indent=2))
    return 0
