#!/usr/bin/env python3
"""Our pq tool against faiss-cpu on the same generated data, in one process tree (issue 23).

Usage: bench_vs_faiss.py [--n 1000000] [--dim 512] [--m 128] [--queries 5] [--repeat 3]
                         [--pq-bin target/release/pq] [--threads 2] [--quick]

Generates N CLIP-like unit descriptors (class prototypes plus noise, seeded, stored as F16
and read by both sides as the same numbers), writes them as a ``profuse.features`` file,
then measures, pairs interleaved (ours, then faiss, repeated):

* train: ``pq train`` (its ``train_s``: k-means on the same number of sample vectors,
  ``--iters`` Lloyd iterations, M x 256 centroids) vs ``faiss.IndexPQ(d, M, 8,
  METRIC_INNER_PRODUCT).train`` on that many vectors with ``cp.niter`` = the same iterations;
* encode: ``pq train``'s ``encode_s`` (all N) vs ``IndexPQ.add`` (all N);
* one query, k = 100: ``pq query``'s ``query_ms`` (the default ``--scan fast``: a 4-bit
  first pass over every vector, 8-bit ADC of its candidates and an exact re-rank; file
  loading and the once-per-load packing, ``prepare_ms``, excluded, as faiss packs at
  ``add``), and ``--scan exhaustive`` (8-bit ADC over every code, the previous default)
  for reference, vs ``IndexPQ.search`` and
  ``IndexPQFastScan(d, 2M, 4)`` (4-bit sub-quantisers, the same 128 bytes a vector at the
  defaults) ``.search``, each the fastest of ``--repeat`` runs, median over the queries;
* recall@100 of each against the exact inner product with the raw (F16) vectors.

Both sides run on ``--threads`` threads (``RAYON_NUM_THREADS`` for ours,
``faiss.omp_set_num_threads``). Prints one JSON object on stdout: ``train_ratio``,
``encode_ratio``, ``query_ratio_indexpq``, ``query_ratio_fastscan`` (ours / faiss: below 1
means we are faster), ``recall_at_100_ours``, ``recall_at_100_faiss``,
``recall_at_100_fastscan``, and the raw seconds; progress on stderr.
Needs ``pip install -r crates/pq/python/requirements.txt`` and a built ``pq`` binary.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[3]
sys.path.insert(0, str(ROOT / "formats" / "python"))
import profuse_formats as pf  # noqa: E402


def log(msg: str) -> None:
    print(f"bench_vs_faiss: {msg}", file=sys.stderr, flush=True)


def clustered(n: int, d: int, classes: int, noise: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """N unit vectors (F16) around `classes` unit prototypes, and the prototypes."""
    rng = np.random.default_rng(seed)
    protos = rng.standard_normal((classes, d)).astype(np.float32)
    protos /= np.linalg.norm(protos, axis=1, keepdims=True)
    x = np.empty((n, d), np.float16)
    chunk = 65536
    for s in range(0, n, chunk):
        e = min(n, s + chunk)
        c = rng.integers(0, classes, e - s)
        v = protos[c] + noise * rng.standard_normal((e - s, d)).astype(np.float32) / np.sqrt(d)
        v /= np.linalg.norm(v, axis=1, keepdims=True)
        x[s:e] = v.astype(np.float16)
    return x, protos


def run_json(cmd: list[str], threads: int) -> dict:
    env = dict(os.environ, RAYON_NUM_THREADS=str(threads))
    out = subprocess.run(cmd, capture_output=True, env=env, check=False)
    if out.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed:\n{out.stderr.decode()}")
    return json.loads(out.stdout)


def recall(ids: np.ndarray, truth: np.ndarray) -> float:
    return len(set(ids.tolist()) & set(truth.tolist())) / len(truth)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--n", type=int, default=1_000_000, help="descriptors N (default 1M)")
    ap.add_argument("--dim", type=int, default=512, help="dimension D (default 512)")
    ap.add_argument("--m", type=int, default=128, help="8-bit sub-quantisers M (default 128)")
    ap.add_argument("--train", type=int, default=65536, help="training vectors (default 65536)")
    ap.add_argument("--iters", type=int, default=25, help="Lloyd iterations (default 25)")
    ap.add_argument("--queries", type=int, default=5, help="text-like queries (default 5)")
    ap.add_argument("--repeat", type=int, default=3, help="runs per query and side (default 3)")
    ap.add_argument("--k", type=int, default=100, help="results per query (default 100)")
    ap.add_argument("--threads", type=int, default=2, help="threads of both sides (default 2)")
    ap.add_argument("--seed", type=int, default=0, help="data seed (default 0)")
    ap.add_argument("--pq-bin", default=str(ROOT / "target" / "release" / "pq"), help="our pq binary")
    ap.add_argument(
        "--quick",
        action="store_true",
        help="a small run for tests: N 20000, D 128, M 32, 10240 training vectors, 5 iterations",
    )
    a = ap.parse_args()
    if a.quick:
        a.n, a.dim, a.m, a.train, a.iters = min(a.n, 20000), 128, 32, 10240, 5
    if a.dim % a.m != 0 or a.dim % (2 * a.m) != 0:
        raise SystemExit(f"--dim {a.dim} must be a multiple of 2 x --m {a.m}")
    if a.k > a.n:
        raise SystemExit(f"--k {a.k} exceeds --n {a.n}")
    import faiss  # noqa: PLC0415 (after argument errors, so --help works without faiss)

    faiss.omp_set_num_threads(a.threads)
    log(f"generating {a.n} x {a.dim} descriptors")
    x16, protos = clustered(a.n, a.dim, classes=50, noise=0.62, seed=a.seed)
    x = x16.astype(np.float32)
    rng = np.random.default_rng(a.seed + 1)
    # Text-like queries: a prototype's direction plus a different noise.
    q = protos[rng.integers(0, len(protos), a.queries)]
    q = q + 0.5 * rng.standard_normal(q.shape).astype(np.float32) / np.sqrt(a.dim)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    truth = [np.argsort(-(x @ qi), kind="stable")[: a.k] for qi in q]
    sample = x[: a.train]

    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        feats, codes, prompts = tmp / "f.safetensors", tmp / "pq.safetensors", tmp / "p.safetensors"
        pf.write_features(feats, features=x16, valid=np.ones(a.n, np.uint8))
        names = [f"q{i}" for i in range(a.queries)]
        pf.write_prompts(prompts, names=names, embeddings=q)

        log("train + encode, ours then faiss")
        ours = run_json(
            [a.pq_bin, "train", "--features", str(feats), "--out", str(codes), "--m", str(a.m),
             "--iters", str(a.iters), "--sample", str(a.train), "--quiet"],
            a.threads,
        )
        index = faiss.IndexPQ(a.dim, a.m, 8, faiss.METRIC_INNER_PRODUCT)
        index.pq.cp.niter = a.iters
        t = time.perf_counter()
        index.train(sample)
        faiss_train = time.perf_counter() - t
        t = time.perf_counter()
        index.add(x)
        faiss_encode = time.perf_counter() - t
        fast = faiss.IndexPQFastScan(a.dim, 2 * a.m, 4, faiss.METRIC_INNER_PRODUCT)
        fast.pq.cp.niter = a.iters
        fast.train(sample)
        fast.add(x)

        log(f"{a.queries} queries x {a.repeat} runs, interleaved")
        ours_ms, pq_ms, fast_ms, exh_ms, prep_ms = [], [], [], [], []
        r_ours, r_pq, r_fast, r_exh = [], [], [], []
        for i, qi in enumerate(q):
            best = [np.inf, np.inf, np.inf, np.inf, np.inf]
            for _ in range(a.repeat):
                query = [a.pq_bin, "query", "--pq", str(codes), "--prompts", str(prompts),
                         "--prompt", names[i], "--k", str(a.k), "--quiet"]
                o = run_json(query, a.threads)
                best[0] = min(best[0], o["query_ms"])
                best[4] = min(best[4], o["prepare_ms"])
                e = run_json(query + ["--scan", "exhaustive"], a.threads)
                best[3] = min(best[3], e["query_ms"])
                t = time.perf_counter()
                _, ids_pq = index.search(qi[None], a.k)
                best[1] = min(best[1], 1e3 * (time.perf_counter() - t))
                t = time.perf_counter()
                _, ids_fast = fast.search(qi[None], a.k)
                best[2] = min(best[2], 1e3 * (time.perf_counter() - t))
            ours_ms.append(best[0])
            pq_ms.append(best[1])
            fast_ms.append(best[2])
            exh_ms.append(best[3])
            prep_ms.append(best[4])
            r_ours.append(recall(np.asarray(o["ids"]), truth[i]))
            r_exh.append(recall(np.asarray(e["ids"]), truth[i]))
            r_pq.append(recall(ids_pq[0], truth[i]))
            r_fast.append(recall(ids_fast[0], truth[i]))

    med = statistics.median
    report = {
        "train_ratio": ours["train_s"] / faiss_train,
        "encode_ratio": ours["encode_s"] / faiss_encode,
        "query_ratio_indexpq": med(ours_ms) / med(pq_ms),
        "query_ratio_fastscan": med(ours_ms) / med(fast_ms),
        "recall_at_100_ours": float(np.mean(r_ours)),
        "recall_at_100_ours_exhaustive": float(np.mean(r_exh)),
        "recall_at_100_faiss": float(np.mean(r_pq)),
        "recall_at_100_fastscan": float(np.mean(r_fast)),
        "train_s": {"ours": ours["train_s"], "faiss": faiss_train},
        "encode_s": {"ours": ours["encode_s"], "faiss": faiss_encode},
        "query_ms": {"ours": med(ours_ms), "ours_exhaustive": med(exh_ms),
                     "faiss_indexpq": med(pq_ms), "faiss_fastscan": med(fast_ms)},
        "prepare_ms_ours": med(prep_ms),
        "n": a.n,
        "dim": a.dim,
        "m": a.m,
        "train_vectors": a.train,
        "iters": a.iters,
        "queries": a.queries,
        "repeat": a.repeat,
        "k": a.k,
        "threads": a.threads,
        "faiss_version": faiss.__version__,
    }
    print(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
