"""The Ray driver: `python -m profuse_ray run SCENE ...` (or `profuse-ray run ...`).

Why files in a shared directory and not Ray's object store: every stage of the project
reads and writes memory-mapped safetensors files (Gaussians, masks, proposals, partial
sums of hundreds of MB at scale), and the tools validate and write them atomically. Moving
them through the object store would copy each one into worker memory and back to disk for
the next tool; a shared directory (NFS, Lustre, a cloud file store) lets each task map
exactly what it reads. The object store only carries the small JSON reports.

Why shards of warp-graph and fuse: warp-graph's view pairs are independent (a pair's mask
links come from its two warps alone) and fuse renders every view (about 97% of its time)
into exact fixed-point partial sums that add up associatively. So view-pair shards
(`profuse warp-shard --pairs A..B`) and view shards (`profuse fuse-shard --views A..B`) run
on many machines and merge into byte-identical proposals and features (`profuse run
--warp-partials` / `--fuse-partials`, which refuse shards of other inputs). gs-init, the
warp-graph grouping, pq, query and vertex-transfer run as one task each.

Failures: every task is idempotent (tools write to a temporary file and rename) and is
retried by Ray (`--max-retries`) when its worker dies or the tool fails; a shard whose
file is already there and valid is not recomputed, so a rerun skips finished shards. The
shard files live under OUT/shards/warp-<key>/ and OUT/shards/fuse-<key>/, where the key
hashes the records of the stages the shards depend on and the configuration: shards of
an older upstream are never mixed in (and the merge commands would refuse them).
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
# `<dir>/<stage>_<a>_<b>.<pid>` and waits until `<dir>/release` or `<dir>/release-<stage>`
# exists. Not for production use.
HOLD_ENV = "PROFUSE_RAY_HOLD_DIR"

# Per sharded stage: the `profuse` subcommand, its range flag and the file kind it writes.
SHARD_KINDS = {
    "warp": ("warp-shard", "--pairs", "warp_partial"),
    "fuse": ("fuse-shard", "--views", "fuse_partial"),
}


@dataclass
class Plan:
    """Everything a run needs; every path absolute and visible on every node."""

    scene: Path
    out: Path
    bin_dir: Path
    shard_views: int = 8
    # View pairs per warp-graph shard; 0 runs warp-graph as one task.
    shard_pairs: int = 32
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


def shard_ranges(views: int, shard_views: int, what: str = "views") -> list:
    """Half-open ranges of at most `shard_views` items covering 0..views."""
    if views <= 0:
        raise ValueError(f"the scene has {views} {what}; nothing to shard")
    if shard_views <= 0:
        raise ValueError(f"--shard-{what.replace('view pairs', 'pairs')} must be positive, got {shard_views}")
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


def _hold_if_asked(stage: str, a: int, b: int) -> None:
    hold = os.environ.get(HOLD_ENV)
    if not hold or a == b:
        return
    d = Path(hold)
    (d / f"{stage}_{a}_{b}.{os.getpid()}").write_text("")
    deadline = time.monotonic() + 120
    released = [d / "release", d / f"release-{stage}"]
    while not any(r.exists() for r in released) and time.monotonic() < deadline:
        time.sleep(0.05)


def _valid_kind(plan: Plan, path: str) -> Optional[str]:
    """The kind of a valid file at `path`, else None."""
    if not Path(path).is_file():
        return None
    check = subprocess.run(
        [plan.tool("profuse"), "inspect", path],
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
    )
    try:
        return json.loads(check.stdout).get("kind") if check.returncode == 0 else None
    except json.JSONDecodeError:
        return None


def shard_task(plan: Plan, stage: str, a: int, b: int, partial: str) -> dict:
    """One shard of `stage` (`warp`: view pairs a..b, `fuse`: views a..b); skipped when
    its valid file is already there."""
    command, flag, kind = SHARD_KINDS[stage]
    if _valid_kind(plan, partial) == kind:
        return {"report": None, "seconds": 0.0, "host": socket.gethostname(), "skipped": True}
    _hold_if_asked(stage, a, b)
    argv = [plan.tool("profuse"), command, str(plan.scene), flag, f"{a}..{b}"]
    argv += ["--partial-out", partial] + plan.common_args()
    result = run_tool(argv, plan.threads_per_task)
    result["skipped"] = False
    return result


def view_pair_count(plan: Plan, probe: str) -> int:
    """T, the view pairs of warp-graph, from the empty shard `0..0` (written when missing)."""
    shard_task(plan, "warp", 0, 0, probe)
    report = run_tool([plan.tool("profuse"), "inspect", probe])["report"]
    return int(report["counts"]["view_pairs"])


def _stage_key(plan: Plan, stages: list) -> str:
    """Hash of what shards depend on: the completion records of `stages` (their inputs',
    outputs' and parameters' fingerprints and the code identity) and the configuration
    arguments."""
    h = hashlib.sha256()
    for stage in stages:
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


def gather(plan: Plan, label: str, pending: dict, unit: str = "views") -> list:
    """Waits for the tasks `pending` ({ref: (a, b)}) as they finish, logging `<label> i/n`;
    returns a record per task (range, seconds, host, skipped), in range order."""
    import ray

    shards, total = [], len(pending)
    _log(plan, f"profuse-ray: {label} 0/{total}")
    while pending:
        ready, _ = ray.wait(list(pending), num_returns=1)
        for ref in ready:
            a, b = pending.pop(ref)
            r = ray.get(ref)
            shards.append({unit: [a, b], "seconds": r["seconds"], "host": r["host"], "skipped": r["skipped"]})
            _log(plan, f"profuse-ray: {label} {len(shards)}/{total}")
    shards.sort(key=lambda s: s[unit])
    return shards


def run_shards(plan: Plan, stage: str, ranges: list, shard_dir: Path) -> tuple:
    """Runs one task per range, in parallel; returns the shard files (in range order)
    and a record per shard."""
    task = _remote(shard_task, plan)
    partials = [str(shard_dir / f"{stage}_{a}_{b}.safetensors") for a, b in ranges]
    pending = {task.remote(plan, stage, a, b, p): (a, b) for (a, b), p in zip(ranges, partials)}
    unit = "pairs" if stage == "warp" else "views"
    return partials, gather(plan, f"{stage} shards", pending, unit)


def _warp_graph_sharded(plan: Plan, tool, timing: dict) -> tuple:
    """gs-init (and gs-refine) as one task, warp-graph's view pairs in shards, the merge
    and grouping as one task; returns the records of the first and the last task, the
    shards and their folder."""
    import ray

    t0 = time.monotonic()
    head_argv = [plan.tool("profuse"), "run", str(plan.scene), "--until", "gs-refine"]
    head = ray.get(tool.remote(head_argv + plan.common_args(), plan.threads_per_task))
    timing["gs-init + gs-refine (1 task)"] = time.monotonic() - t0
    t0 = time.monotonic()
    shard_dir = plan.out / "shards" / f"warp-{_stage_key(plan, ['gs-init', 'gs-refine'])}"
    shard_dir.mkdir(parents=True, exist_ok=True)
    probe = str(shard_dir / "warp_0_0.safetensors")
    pairs = ray.get(_remote(view_pair_count, plan).remote(plan, probe))
    ranges = shard_ranges(pairs, plan.shard_pairs, "view pairs")
    partials, shards = run_shards(plan, "warp", ranges, shard_dir)
    timing[f"warp-graph shards ({len(ranges)} tasks)"] = time.monotonic() - t0
    t0 = time.monotonic()
    merge_argv = [plan.tool("profuse"), "run", str(plan.scene), "--until", "warp-graph"]
    merge_argv += ["--warp-partials", probe, *partials]
    merge = ray.get(tool.remote(merge_argv + plan.common_args(), plan.threads_per_task))
    timing["warp-graph merge + grouping (1 task)"] = time.monotonic() - t0
    return head, merge, shards, shard_dir


def run_pipeline(plan: Plan) -> dict:
    """Runs the whole pipeline on the connected Ray cluster; returns `profuse run`'s
    summary with a `ray` section (shards, hosts, per-stage wall seconds)."""
    import ray

    tool = _remote(run_tool, plan)
    t_start = time.monotonic()
    timing = {}
    views_ref = tool.remote([plan.tool("profuse"), "inspect", str(plan.scene / "cameras.safetensors")])
    warp_shards, warp_dir = [], None
    if plan.shard_pairs > 0:
        _, head, warp_shards, warp_dir = _warp_graph_sharded(plan, tool, timing)
    else:
        t0 = time.monotonic()
        head_argv = [plan.tool("profuse"), "run", str(plan.scene), "--until", "warp-graph"]
        head = ray.get(tool.remote(head_argv + plan.common_args(), plan.threads_per_task))
        timing["gs-init + warp-graph (1 task)"] = time.monotonic() - t0
    views = int(ray.get(views_ref)["report"]["counts"]["views"])

    t0 = time.monotonic()
    ranges = shard_ranges(views, plan.shard_views)
    shard_dir = plan.out / "shards" / f"fuse-{_stage_key(plan, ['gs-init', 'gs-refine', 'warp-graph', 'proposals'])}"
    shard_dir.mkdir(parents=True, exist_ok=True)
    partials, shards = run_shards(plan, "fuse", ranges, shard_dir)
    timing[f"fuse shards ({len(ranges)} tasks)"] = time.monotonic() - t0

    t0 = time.monotonic()
    tail_argv = [plan.tool("profuse"), "run", str(plan.scene), "--fuse-partials", *partials]
    tail = ray.get(tool.remote(tail_argv + plan.common_args(), plan.threads_per_task))
    timing["fuse merge + pq + query + vertex-transfer (1 task)"] = time.monotonic() - t0
    timing["total"] = time.monotonic() - t_start

    summary = tail["report"] or {}
    summary["ray"] = {
        "shards": shards,
        "shard_views": plan.shard_views,
        "shard_dir": str(shard_dir),
        "warp_shards": warp_shards,
        "shard_pairs": plan.shard_pairs,
        "warp_shard_dir": str(warp_dir) if warp_dir else None,
        "stages_before_fuse": (head["report"] or {}).get("stages"),
        "wall_s": timing,
        "nodes": len(ray.nodes()),
    }
    if not plan.quiet:
        print(timing_table(timing, shards + warp_shards), file=sys.stderr)
    return summary


def prep_shard_task(plan: Plan, argv: list, out: str) -> dict:
    """One `prep masks|features --shard` task; skipped when its valid masks file exists."""
    if _valid_kind(plan, out) == "masks":
        return {"report": None, "seconds": 0.0, "host": socket.gethostname(), "skipped": True}
    result = run_tool(argv + ["--out", out], plan.threads_per_task)
    result["skipped"] = False
    return result


def _prep_step(plan: Plan, name: str, base: list, ranges: list, shard_dir: Path, out: str, timing: dict) -> list:
    """`base --shard A..B` per view range as Ray tasks, then `prep merge` into `out`."""
    import ray

    task = _remote(prep_shard_task, plan)
    files = [str(shard_dir / f"{name}_{a}_{b}.safetensors") for a, b in ranges]
    t0 = time.monotonic()
    pending = {task.remote(plan, base + ["--shard", f"{a}..{b}"], f): (a, b) for (a, b), f in zip(ranges, files)}
    shards = gather(plan, f"prep {name} shards", pending)
    timing[f"prep {name} shards ({len(ranges)} tasks)"] = time.monotonic() - t0
    t0 = time.monotonic()
    merge = _remote(run_tool, plan).remote([plan.tool("prep"), "--quiet", "merge", "--out", out, *files])
    ray.get(merge)
    timing[f"prep merge {name} (1 task)"] = time.monotonic() - t0
    return shards


def run_prep(plan: Plan, args) -> dict:
    """`prep masks` (and `prep features` when asked) over view shards as Ray tasks, each
    merged with `prep merge`: the masks file of one `prep` run, byte for byte."""
    import ray

    t_start = time.monotonic()
    timing = {}
    cameras = str(plan.scene / "cameras.safetensors")
    views_info = ray.get(_remote(run_tool, plan).remote([plan.tool("profuse"), "inspect", cameras]))
    views = int(views_info["report"]["counts"]["views"])
    ranges = shard_ranges(views, plan.shard_views)
    common = ["--cameras", cameras, "--images", str(plan.scene)]
    prep = [plan.tool("prep"), "--quiet"]
    if plan.threads_per_task:
        prep += ["--threads", str(plan.threads_per_task)]  # results do not depend on it
    masks_argv = prep + ["masks", "--encoder", args.encoder, "--decoder", args.decoder] + common + list(args.masks_arg)
    features_argv = None
    if args.clip_image or args.sam_embedding:
        features_argv = prep + ["features"] + common + list(args.features_arg)
        features_argv += ["--clip-image", args.clip_image] if args.clip_image else ["--sam-embedding", "--encoder", args.encoder]
    h = hashlib.sha256(json.dumps([masks_argv, features_argv]).encode()).hexdigest()[:16]
    shard_dir = plan.out / "shards" / f"prep-{h}"
    shard_dir.mkdir(parents=True, exist_ok=True)
    out = str(Path(args.masks_out).resolve()) if args.masks_out else str(plan.scene / "masks.safetensors")
    raw = out if features_argv is None else str(shard_dir / "masks_merged.safetensors")
    summary = {"views": views, "out": out, "masks_shards": _prep_step(plan, "masks", masks_argv, ranges, shard_dir, raw, timing)}
    if features_argv is not None:
        features_argv += ["--masks", raw]
        summary["features_shards"] = _prep_step(plan, "features", features_argv, ranges, shard_dir, out, timing)
    timing["total"] = time.monotonic() - t_start
    summary["wall_s"] = timing
    summary["nodes"] = len(ray.nodes())
    if not plan.quiet:
        print(timing_table(timing, summary["masks_shards"] + summary.get("features_shards", [])), file=sys.stderr)
    return summary


def timing_table(timing: dict, shards: list) -> str:
    lines = ["", f"{'profuse-ray step':<52} {'wall s':>8}"]
    lines += [f"{k:<52} {v:>8.2f}" for k, v in timing.items()]
    busy = sum(s["seconds"] for s in shards)
    skipped = sum(1 for s in shards if s["skipped"])
    hosts = sorted({s["host"] for s in shards})
    lines.append(f"shard task-seconds {busy:.2f} over {len(hosts)} host(s); {skipped} shard(s) already done")
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
        description="Run `profuse run` on a Ray cluster: warp-graph's view pairs and the fuse stage's "
        "views in shards (Ray tasks), the other stages as one task each, all on files in a directory every node sees. The outputs "
        "are byte-identical to `profuse run` on one machine. Prints the run's JSON summary on stdout; "
        "shard progress and a timing table on stderr.",
    )
    sub = ap.add_subparsers(dest="command", required=True)
    run = sub.add_parser("run", help="run the pipeline on a scene directory")
    _common_args(run)
    run.add_argument(
        "--shard-pairs",
        type=int,
        default=32,
        help="view pairs per warp-graph shard task (default 32); 0 runs warp-graph as one task "
        "(required when the configuration sets fuse.no_proposals)",
    )
    run.add_argument("--config", help="TOML configuration, as for `profuse run`")
    run.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE", help="override one parameter (repeatable)")
    prep = sub.add_parser(
        "prep",
        help="`prep masks` (and `prep features`) over view shards, merged into SCENE/masks.safetensors",
        description="Runs `prep masks --shard A..B` per view range as Ray tasks and merges them with "
        "`prep merge` (then the same for `prep features` when --clip-image or --sam-embedding is given): "
        "the masks file of one `prep` run, byte for byte. Shards go to OUT/shards/prep-<key>/.",
    )
    _common_args(prep)
    prep.add_argument("--encoder", required=True, help="SAM image encoder (ONNX), on every node")
    prep.add_argument("--decoder", required=True, help="SAM prompt decoder (ONNX), on every node")
    desc = prep.add_mutually_exclusive_group()
    desc.add_argument("--clip-image", help="then describe the masks with this CLIP image encoder (ONNX)")
    desc.add_argument("--sam-embedding", action="store_true", help="then describe the masks with the pooled SAM embedding")
    prep.add_argument("--masks-out", help="the masks file to write (default SCENE/masks.safetensors)")
    prep.add_argument("--masks-arg", action="append", default=[], metavar="ARG", help="extra argument of `prep masks`, e.g. --masks-arg=--points-per-side=16 (repeatable)")
    prep.add_argument("--features-arg", action="append", default=[], metavar="ARG", help="extra argument of `prep features` (repeatable)")
    return ap.parse_args(argv)


def _common_args(p) -> None:
    p.add_argument("scene", help="the scene directory (on the shared file system)")
    p.add_argument("--out-dir", help="output directory (default SCENE/out), on the shared file system")
    where = p.add_mutually_exclusive_group()
    where.add_argument("--address", default="auto", help="Ray cluster address (default: auto, the running cluster)")
    where.add_argument("--local-cluster", type=int, metavar="N", help="start a local cluster of N one-CPU nodes instead")
    p.add_argument("--shard-views", type=int, default=8, help="views per fuse (run) or prep (prep) shard task (default 8)")
    p.add_argument("--bin-dir", help="folder of the profuse tools on every node (default: PROFUSE_BIN_DIR, else PATH)")
    p.add_argument("--max-retries", type=int, default=3, help="retries of a failed task (default 3)")
    p.add_argument("--threads-per-task", type=int, help="RAYON_NUM_THREADS of each tool (default: the tool's)")
    p.add_argument("--quiet", action="store_true", help="no progress or timing table on stderr")


def plan_from_args(args) -> Plan:
    scene = Path(args.scene).resolve()
    return Plan(
        scene=scene,
        out=Path(args.out_dir).resolve() if args.out_dir else scene / "out",
        bin_dir=_bin_dir(args.bin_dir),
        shard_views=args.shard_views,
        shard_pairs=getattr(args, "shard_pairs", 0),
        config=Path(args.config).resolve() if getattr(args, "config", None) else None,
        sets=list(getattr(args, "set", [])),
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
        summary = run_pipeline(plan) if args.command == "run" else run_prep(plan, args)
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
