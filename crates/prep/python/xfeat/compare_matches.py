#!/usr/bin/env python3
"""Compares two folders of keypoint-pair files (`<stem_i>_<stem_j>.npz`, float32 kpts_i /
kpts_j in the original photos' pixels) on a capture with a transforms.json: per pair the
match counts, the fraction of OURS matches with a THEIRS match within 1 px (both points),
and each folder's median Sampson error against the transforms.json poses (after undistorting
with its k1 k2 p1 p2; the formula of the fox's matches_xfeat/make_matches.py).

    pip install numpy opencv-python-headless
    python3 crates/prep/python/xfeat/compare_matches.py CAPTURE/transforms.json OURS THEIRS [--json OUT]
"""
import argparse
import json
import os
import sys

try:
    import cv2
    import numpy as np
except ImportError as e:
    sys.exit(f"compare_matches.py: {e}; install with: pip install numpy opencv-python-headless")


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("transforms")
    ap.add_argument("ours")
    ap.add_argument("theirs")
    ap.add_argument("--json")
    a = ap.parse_args()
    d = json.load(open(a.transforms))
    root = os.path.dirname(os.path.abspath(a.transforms))
    frames = {os.path.splitext(os.path.basename(f["file_path"]))[0]: np.array(f["transform_matrix"])
              for f in d["frames"] if os.path.exists(os.path.join(root, f["file_path"]))}
    K = np.array([[d["fl_x"], 0, d["cx"]], [0, d["fl_y"], d["cy"]], [0, 0, 1]])
    dist = np.array([d.get("k1", 0), d.get("k2", 0), d.get("p1", 0), d.get("p2", 0)])

    def w2c(stem):  # OpenGL c2w -> OpenCV w2c
        m = frames[stem].copy()
        m[:3, 1:3] *= -1
        return np.linalg.inv(m)

    def sampson(si, sj, a_, b_):
        if len(a_) == 0:
            return np.zeros(0)
        ua = cv2.undistortPoints(a_.reshape(-1, 1, 2).astype(np.float64), K, dist).reshape(-1, 2)
        ub = cv2.undistortPoints(b_.reshape(-1, 1, 2).astype(np.float64), K, dist).reshape(-1, 2)
        T = w2c(sj) @ np.linalg.inv(w2c(si))
        R, t = T[:3, :3], T[:3, 3]
        E = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]]) @ R
        x1 = np.c_[ua, np.ones(len(ua))]
        x2 = np.c_[ub, np.ones(len(ub))]
        Ex1, Etx2 = x1 @ E.T, x2 @ E
        num = (x2 * Ex1).sum(1) ** 2
        den = Ex1[:, 0] ** 2 + Ex1[:, 1] ** 2 + Etx2[:, 0] ** 2 + Etx2[:, 1] ** 2
        return np.sqrt(num / np.maximum(den, 1e-18)) * d["fl_x"]

    rows = []
    for name in sorted(f for f in os.listdir(a.theirs) if f.endswith(".npz")):
        if not os.path.exists(os.path.join(a.ours, name)):
            rows.append({"pair": name[:-4], "missing_in_ours": True})
            continue
        si, sj = name[:-4].split("_")
        o, t = np.load(os.path.join(a.ours, name)), np.load(os.path.join(a.theirs, name))
        oa, ob, ta, tb = o["kpts_i"], o["kpts_j"], t["kpts_i"], t["kpts_j"]
        near = 0
        if len(oa) and len(ta):
            tt = np.concatenate([ta, tb], 1)
            oo = np.concatenate([oa, ob], 1)
            for r in oo:
                near += int((np.abs(tt - r).max(1) <= 1.0).any())
        so, st = sampson(si, sj, oa, ob), sampson(si, sj, ta, tb)
        rows.append({"pair": name[:-4], "ours": int(len(oa)), "theirs": int(len(ta)),
                     "ours_within_1px_of_theirs": near / max(len(oa), 1),
                     "median_sampson_ours": float(np.median(so)) if len(so) else None,
                     "median_sampson_theirs": float(np.median(st)) if len(st) else None,
                     "inlier_2px_ours": float((so < 2).mean()) if len(so) else None,
                     "inlier_2px_theirs": float((st < 2).mean()) if len(st) else None})
    ok = [r for r in rows if "ours" in r]
    med = lambda k: float(np.median([r[k] for r in ok if r[k] is not None])) if ok else None
    summary = {
        "pairs": len(rows), "compared": len(ok), "missing_in_ours": len(rows) - len(ok),
        "matches_ours": sum(r["ours"] for r in ok), "matches_theirs": sum(r["theirs"] for r in ok),
        "count_ratio_min_max": [min(r["ours"] / max(r["theirs"], 1) for r in ok),
                                max(r["ours"] / max(r["theirs"], 1) for r in ok)] if ok else None,
        "within_1px_median_min": [med("ours_within_1px_of_theirs"),
                                  min(r["ours_within_1px_of_theirs"] for r in ok)] if ok else None,
        "median_sampson_median_ours": med("median_sampson_ours"),
        "median_sampson_median_theirs": med("median_sampson_theirs"),
        "inlier_2px_median_ours": med("inlier_2px_ours"),
        "inlier_2px_median_theirs": med("inlier_2px_theirs"),
    }
    if a.json:
        json.dump({"summary": summary, "pairs": rows}, open(a.json, "w"), indent=1)
    print(json.dumps(summary, indent=1))


if __name__ == "__main__":
    try:
        main()
    except (OSError, KeyError, ValueError) as e:
        sys.exit(f"compare_matches.py: {e}")
