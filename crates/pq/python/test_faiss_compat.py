#!/usr/bin/env python3
"""faiss compatibility of a profuse pq file (SPEC.md 4.8).

Usage: test_faiss_compat.py FEATURES.safetensors PQ.safetensors

Loads our centroids into ``faiss.ProductQuantizer(d, M, 8)`` and checks, for every valid
descriptor of the features file the pq file was encoded from, that

* faiss's codes equal ours; a differing code is allowed only when the two centroids are
  equidistant from the sub-vector within float rounding (faiss's AVX2 kernel fuses
  multiply-adds, ours does not), and such near-ties are counted (expected: 0);
* faiss's decode of our codes equals our decode (the concatenation of the selected
  centroids, SPEC.md 4.8) to 1e-6, and our stored norms are the decoded norms;
* invalid rows have codes 0 and norm 0.

Prints ``key=value`` lines (code_mismatches, near_tie_mismatches, decode_max_abs_diff,
reconstruction_cosine, ...) and exits 1 on any failure. Run by the Rust integration test
``crates/pq/tests/pq.rs``; needs ``pip install -r crates/pq/python/requirements.txt``.
"""

import sys

import faiss
import numpy as np
from safetensors import safe_open
from safetensors.numpy import load_file

# Relative distance gap under which two centroids count as equidistant (f32 rounding of
# a sum of a few squares is ~1e-7 relative).
TIE_RTOL = 1e-5


def load(path, kind):
    with safe_open(path, framework="numpy") as f:
        meta = f.metadata() or {}
    if meta.get("format") != f"profuse.{kind}":
        raise SystemExit(f"{path}: format is {meta.get('format')!r}, expected profuse.{kind}")
    return load_file(path), meta


def main(features_path, pq_path):
    feats, _ = load(features_path, "features")
    pqf, meta = load(pq_path, "pq")
    assert meta["metric"] == "inner_product" and meta["nbits"] == "8", meta
    centroids = pqf["centroids"].astype(np.float32)  # [M, 256, dsub]
    codes = pqf["codes"]  # [N, M]
    norms = pqf["norms"]
    valid = pqf["valid"].astype(bool)
    m, ksub, dsub = centroids.shape
    d = m * dsub
    x_all = feats["features"].astype(np.float32)
    assert x_all.shape == (codes.shape[0], d), (x_all.shape, codes.shape)
    assert np.array_equal(feats["valid"].astype(bool), valid), "valid flags differ"

    pq = faiss.ProductQuantizer(d, m, 8)
    faiss.copy_array_to_vector(np.ascontiguousarray(centroids).ravel(), pq.centroids)

    x = np.ascontiguousarray(x_all[valid])
    ours = codes[valid]
    theirs = pq.compute_codes(x)
    assert theirs.shape == ours.shape, (theirs.shape, ours.shape)

    failures = []
    rows, subs = np.nonzero(theirs != ours)
    near_ties = 0
    for r, s in zip(rows, subs):
        xs = x[r, s * dsub:(s + 1) * dsub].astype(np.float64)
        d_ours = np.sum((xs - centroids[s, ours[r, s]].astype(np.float64)) ** 2)
        d_theirs = np.sum((xs - centroids[s, theirs[r, s]].astype(np.float64)) ** 2)
        if abs(d_ours - d_theirs) <= TIE_RTOL * max(d_ours, d_theirs, 1e-12):
            near_ties += 1
        else:
            failures.append(
                f"row {r} sub {s}: ours {ours[r, s]} (d={d_ours}) faiss {theirs[r, s]} (d={d_theirs})")
    code_mismatches = len(failures)

    # Our decode, independently: concatenate the selected centroids.
    ours_dec = centroids[np.arange(m)[None, :], ours].reshape(-1, d)
    faiss_dec = pq.decode(np.ascontiguousarray(ours))
    decode_diff = float(np.max(np.abs(faiss_dec - ours_dec))) if len(x) else 0.0
    if decode_diff > 1e-6:
        failures.append(f"faiss decode differs from ours by {decode_diff}")
    norm_diff = float(np.max(np.abs(np.linalg.norm(ours_dec.astype(np.float64), axis=1) - norms[valid])))
    if norm_diff > 1e-5:
        failures.append(f"stored norms differ from decoded norms by {norm_diff}")
    if np.any(codes[~valid] != 0) or np.any(norms[~valid] != 0):
        failures.append("invalid rows must have codes 0 and norm 0")

    xd = x.astype(np.float64)
    yd = ours_dec.astype(np.float64)
    cos = np.sum(xd * yd, axis=1) / (np.linalg.norm(xd, axis=1) * np.linalg.norm(yd, axis=1))
    print(f"faiss_version={faiss.__version__}")
    print(f"vectors={len(x)} m={m} dsub={dsub}")
    print(f"code_mismatches={code_mismatches}")
    print(f"near_tie_mismatches={near_ties}")
    print(f"decode_max_abs_diff={decode_diff}")
    print(f"norm_max_abs_diff={norm_diff}")
    print(f"reconstruction_cosine={float(np.mean(cos)) if len(x) else 0.0}")
    print(f"reconstruction_cosine_min={float(np.min(cos)) if len(x) else 0.0}")
    for f in failures[:20]:
        print(f"FAIL: {f}", file=sys.stderr)
    return 1 if failures else 0


if __name__ == "__main__":
    if len(sys.argv) != 3:
        raise SystemExit(__doc__)
    sys.exit(main(sys.argv[1], sys.argv[2]))
