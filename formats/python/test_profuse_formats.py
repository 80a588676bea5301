"""Tests of profuse_formats.py (stdlib unittest; run ``python3 test_profuse_formats.py``).

* Golden vectors (``formats/vectors``, written by the Rust side): every valid file reads
  with the kind, counts, metadata and tensor values of ``expected.json``; every invalid
  file fails with the listed error code and field.
* Python-only bad inputs built in a temporary directory, for every kind: container
  defects, wrong kind/version, missing tensor, dtype, shape, ids out of range, non-finite
  values, and each kind's value rules; plus JSON and number-parsing corner cases.
* The ``inspect`` command line, as a subprocess.
* With ``PROFUSE_RUST_INSPECT=/path/to/profuse``: for every golden vector and every file
  the tests build, ``profuse inspect`` and the Python command print byte-identical stdout
  and exit with the same code.
"""

from __future__ import annotations

import contextlib
import json
import os
import random
import struct
import subprocess
import sys
import tempfile
import unittest
from pathlib import Path
from typing import Any, Callable

import numpy as np
from safetensors.numpy import save_file

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

import profuse_formats as pf  # noqa: E402

MODULE = HERE / "profuse_formats.py"
VECTORS = HERE.parent / "vectors"
EXPECTED = VECTORS / "expected.json"
RUST = os.environ.get("PROFUSE_RUST_INSPECT")

_DTYPE_NAMES = {
    np.dtype(np.bool_): "BOOL",
    np.dtype("uint8"): "U8",
    np.dtype("int8"): "I8",
    np.dtype("uint16"): "U16",
    np.dtype("int16"): "I16",
    np.dtype("uint32"): "U32",
    np.dtype("int32"): "I32",
    np.dtype("uint64"): "U64",
    np.dtype("int64"): "I64",
    np.dtype("float16"): "F16",
    np.dtype("float32"): "F32",
    np.dtype("float64"): "F64",
}
U16_NONE = 2**16 - 1
U32_NONE = 2**32 - 1


# --------------------------------------------------------------------------------------
# Running both command lines
# --------------------------------------------------------------------------------------


def run_python_cli(arg: str, cwd: Path) -> subprocess.CompletedProcess:
    """``python3 profuse_formats.py inspect ARG`` in ``cwd``."""
    return subprocess.run(
        [sys.executable, str(MODULE), "inspect", arg], cwd=cwd, capture_output=True, timeout=120
    )


def run_rust_cli(arg: str, cwd: Path) -> subprocess.CompletedProcess:
    """``profuse inspect ARG`` in ``cwd`` (only when PROFUSE_RUST_INSPECT is set)."""
    assert RUST is not None
    return subprocess.run(
        [os.path.abspath(RUST), "inspect", arg], cwd=cwd, capture_output=True, timeout=120
    )


class ParityMixin:
    """Asserts that the Rust and Python ``inspect`` agree byte for byte."""

    def assert_rust_agrees(self, arg: str, cwd: Path, subprocess_python: bool = False) -> None:
        """With PROFUSE_RUST_INSPECT set: ``profuse inspect ARG`` and the Python command
        print the same bytes and exit with the same code. The Python side runs as a
        subprocess, or (faster, same code path as ``main``) in this process."""
        if RUST is None:
            return
        if subprocess_python:
            py = run_python_cli(arg, cwd)
            py_out, py_rc = py.stdout, py.returncode
        else:
            with contextlib.chdir(cwd):
                report, err = pf.inspect(arg)
            py_out = (pf.report_json(report) + "\n").encode("utf-8")
            py_rc = 0 if err is None else 1
        rs = run_rust_cli(arg, cwd)
        self.assertEqual(
            rs.stdout.decode("utf-8", "replace"),
            py_out.decode("utf-8", "replace"),
            f"stdout of `inspect {arg}` differs (cwd {cwd})",
        )
        self.assertEqual(rs.stdout, py_out)
        self.assertEqual(rs.returncode, py_rc, f"exit code of `inspect {arg}` differs")


# --------------------------------------------------------------------------------------
# Building files
# --------------------------------------------------------------------------------------


def unit_rows(rows: list[list[float]], dtype: Any = np.float32) -> np.ndarray:
    a = np.asarray(rows, dtype=np.float64)
    return (a / np.linalg.norm(a, axis=1, keepdims=True)).astype(dtype)


def sample(kind: str) -> tuple[dict[str, np.ndarray], dict[str, str]]:
    """A small valid file of ``kind``: (tensors, kind-specific metadata)."""
    f32, u32 = np.float32, np.uint32
    if kind == "cameras":
        rot = [[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]]
        w2c = np.zeros((2, 3, 4))
        w2c[0, :, :3] = np.eye(3)
        w2c[1, :, :3] = rot
        w2c[:, 2, 3] = 4.0
        return {
            "image_size": np.array([[8, 6], [8, 6]], u32),
            "intrinsics": np.array([[10, 10, 4, 3], [12, 11, 4.5, 3]], np.float64),
            "world_to_camera": w2c,
            "distortion": np.array([[0, 0, 0, 0], [-0.01, 0.002, 0.0005, -0.0003]], np.float64),
        }, {"image_names": json.dumps(["images/a.png", "images/b.png"])}
    if kind == "gaussians":
        n = 3
        return {
            "means": np.arange(n * 3, dtype=f32).reshape(n, 3),
            "sh_rest": np.linspace(-0.1, 0.1, n * 9, dtype=f32).reshape(n, 3, 3),
            "log_scales": np.full((n, 3), -2.0, f32),
            "rotations": np.array([[1, 0, 0, 0], [0, 1, 0, 0], [0.5, 0.5, 0.5, 0.5]], f32),
            "opacity_logits": np.array([0.0, 2.0, -1.0], f32),
            "sh_dc": np.full((n, 3), 0.25, f32),
            "class_ids": np.array([0, -1, 2], np.int32),
        }, {"sh_degree": "1"}
    if kind == "masks":
        n = U16_NONE
        labels = np.array(
            [[[0, 0, 1], [2, n, 1]], [[0, 0, n], [n, 1, 1]]], np.uint16
        )  # V=2, H=2, W=3; 3 + 2 masks
        feats = unit_rows([[1, 0, 0, 0], [0, 1, 1, 0], [1, 2, 3, 4], [0, 0, 0, 1], [1, -1, 1, -1]])
        return {
            "labels": labels,
            "mask_offsets": np.array([0, 3, 5], u32),
            "features": feats,
        }, {"view_names": json.dumps(["a.png", "b.png"])}
    if kind == "matches":
        p, h, w = 2, 2, 3
        return {
            "pairs": np.array([[0, 1], [1, 0]], u32),
            "warp": np.linspace(-1, 1, p * h * w * 2, dtype=f32).reshape(p, h, w, 2),
            "certainty": (np.arange(p * h * w) % 5 / 4).astype(f32).reshape(p, h, w),
        }, {"num_views": "2", "coords": "normalized"}
    if kind == "sparse_matches":
        return {
            "pairs": np.array([[0, 1], [2, 0]], u32),
            "pair_offsets": np.array([0, 3, 5], np.uint64),
            "points_i": np.arange(10, dtype=f32).reshape(5, 2) + 0.5,
            "points_j": np.arange(10, dtype=f32).reshape(5, 2) + 1.5,
            "certainty": np.array([1.0, 0.5, 0.25, 1.0, 0.0], f32),
        }, {"num_views": "3"}
    if kind == "proposals":
        return {
            "mask_proposal": np.array([0, 1, U32_NONE, 1, 0], u32),
            "proposal_size": np.array([2, 2], u32),
            "proposal_views": np.array([2, 1], u32),
        }, {"tau_iou": "0.2"}
    if kind == "features":
        feats = unit_rows([[1, 0, 0, 0], [1, 1, 0, 0], [1, 1, 1, 1], [1, -2, 2, 4]])
        feats[2] = 0
        return {
            "features": feats,
            "valid": np.array([1, 1, 0, 1], np.uint8),
            "weight_sum": np.array([0.5, 2.0, 0.0, 1e-3], f32),
        }, {}
    if kind == "pq":
        return {
            "centroids": np.linspace(-1, 1, 2 * 256 * 2, dtype=f32).reshape(2, 256, 2),
            "codes": np.array([[0, 255], [17, 3], [0, 0]], np.uint8),
            "norms": np.array([1.0, 0.875, 0.0], f32),
            "valid": np.array([1, 1, 0], np.uint8),
        }, {"metric": "inner_product", "nbits": "8"}
    if kind == "prompts":
        return {
            "embeddings": unit_rows([[1, 0.1, 0, 0], [0, 1, 0.2, 0], [0.5, 0.5, 0.5, 0.5]]),
            "class_ids": np.array([3, 7, -1], np.int32),
        }, {"names": json.dumps(["chair", "red mug", "object"])}
    if kind == "selection":
        return {
            "gaussian_ids": np.array([1, 4, 9], u32),
            "scores": np.array([0.31, 0.27, 0.5], f32),
        }, {"prompt": "red mug", "num_gaussians": "10"}
    if kind == "vertex_labels":
        return {
            "labels": np.array([1, 2, -1, 5, 1], np.int32),
            "confidence": np.array([0.9, 0.5, 0.0, 1.0, 0.75], f32),
        }, {"label_space": "nyu40"}
    if kind == "mesh":
        return {
            "vertices": np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], f32),
            "colors": np.array([[255, 0, 0], [0, 255, 0], [0, 0, 255], [9, 9, 9]], np.uint8),
            "faces": np.array([[0, 1, 2], [0, 2, 3]], u32),
            "labels": np.array([1, 1, 2, 0], u32),
            "instances": np.array([1, 1, 2, 0], u32),
        }, {"label_space": "nyu40"}
    if kind == "view_maps":
        return {
            "depth": np.array([1, 1.5, 2, 0, 2.5, 3, 4, 4, 4.25, 0.5, 0.75, 0], f32).reshape(2, 2, 3),
            "object_ids": np.array([0, 0, 1, U32_NONE, 2, 2, 1, 1, 1, 0, 0, U32_NONE], u32).reshape(
                2, 2, 3
            ),
        }, {"view_names": json.dumps(["a.png", "b.png"]), "num_objects": "3"}
    if kind == "topk":
        n = U32_NONE
        return {
            "ids": np.array([0, 1, 2, 3, n, n, n, n, n, 6, 5, 4, 2, n, n, 1, 0, n], u32).reshape(2, 3, 3),
            "weights": np.array(
                [0.5, 0.25, 0.125, 0.9, 0, 0, 0, 0, 0, 0.4, 0.3, 0.2, 0.75, 0, 0, 0.5, 0.5, 0], f32
            ).reshape(2, 3, 3),
            "transmittance": np.array([0.125, 0.1, 1.0, 0.1, 0.25, 0.0], f32).reshape(2, 3),
        }, {"num_gaussians": "7"}
    if kind == "fuse_partial":
        n = U32_NONE
        return {
            "views": np.array([0, 2], u32),
            "mask_group": np.array([0, n, 2], u32),
            "mask_proposal": np.array([0, n, 0], u32),
            "mask_features": np.array([[1, 0], [0.6, 0.8], [0, 1]], f32),
            "mask_mass": np.array([[5 << 40, 0], [0, 0], [7 << 40, 1]], np.uint64),
            "w_offsets": np.array([0, 2, 2, 3, 4], np.uint64),
            "w_groups": np.array([0, 2, 0, 2], u32),
            "w_sums": np.array([[3 << 40, 0], [1 << 40, 0], [2 << 40, 0], [0, 1]], np.uint64),
        }, {
            "num_gaussians": "4", "num_views": "3", "k": "2", "grouping": "blend",
            "orphans": "ignore", "num_groups": "3", "pixels": "10", "hits": "15",
        }
    if kind == "warp_partial":
        meta = {"num_views": "3", "num_masks": "6", "num_view_pairs": "4", "first_pair": "1"}
        meta.update({key: str(i) for i, key in enumerate(pf.WARP_COUNTERS)})
        meta.update({key: "id" for key in pf.WARP_INPUTS})
        return {
            "pairs": np.array([[0, 2], [1, 2]], u32),
            "edge_offsets": np.array([0, 2, 2], np.uint64),
            "edge_masks": np.array([[0, 4], [1, 5]], u32),
            "edge_scores": np.array([[0.75, 0.5], [0.1, 1.0]], np.float64),
        }, meta
    if kind == "semantic_index":
        return {
            "descriptors": np.array([[1, 0], [0, 0], [0.6, 0.8]], f32),
            "index": np.array([0, 2, 65535, 1], np.uint16),
            "share": np.array([255, 90, 0, 200], np.uint8),
        }, {"min_share": "128"}
    raise KeyError(kind)


# Per kind: the tensor the generic defects act on, a float tensor for the non-finite test
# (None if the kind has none), and two tensors that share a dimension (shape test).
GENERIC = {
    "cameras": ("intrinsics", "intrinsics", ("image_size", "intrinsics")),
    "gaussians": ("means", "means", ("means", "log_scales")),
    "masks": ("features", "features", ("labels", "mask_offsets")),
    "matches": ("warp", "warp", ("warp", "certainty")),
    "sparse_matches": ("points_i", "points_i", ("points_i", "points_j")),
    "proposals": ("mask_proposal", None, ("proposal_size", "proposal_views")),
    "features": ("features", "features", ("features", "valid")),
    "pq": ("norms", "norms", ("codes", "norms")),
    "prompts": ("embeddings", "embeddings", ("embeddings", "class_ids")),
    "selection": ("scores", "scores", ("gaussian_ids", "scores")),
    "vertex_labels": ("labels", "confidence", ("labels", "confidence")),
    "mesh": ("vertices", "vertices", ("vertices", "colors")),
    "view_maps": ("depth", "depth", ("depth", "object_ids")),
    "topk": ("weights", "weights", ("ids", "weights")),
    "fuse_partial": ("w_sums", "mask_features", ("mask_group", "mask_mass")),
    "warp_partial": ("edge_scores", "edge_scores", ("edge_masks", "edge_scores")),
    "semantic_index": ("share", "descriptors", ("index", "share")),
}

# Per kind: a mutation putting an id or value out of range, and the field it names.
OUT_OF_RANGE: dict[str, tuple[Callable[[dict], None], str]] = {
    "cameras": (lambda t: t["image_size"].__setitem__((1, 0), 0), "image_size"),
    "gaussians": (lambda t: t["class_ids"].__setitem__(1, -2), "class_ids"),
    "masks": (lambda t: t["labels"].__setitem__((1, 0, 0), 2), "labels"),
    "matches": (lambda t: t["pairs"].__setitem__((1, 0), 2), "pairs"),
    "sparse_matches": (lambda t: t["pairs"].__setitem__((1, 1), 3), "pairs"),
    "proposals": (lambda t: t["mask_proposal"].__setitem__(2, 2), "mask_proposal"),
    "features": (lambda t: t["valid"].__setitem__(0, 2), "valid"),
    "pq": (lambda t: t["valid"].__setitem__(0, 2), "valid"),
    "prompts": (lambda t: t["class_ids"].__setitem__(0, -2), "class_ids"),
    "selection": (lambda t: t["gaussian_ids"].__setitem__(2, 10), "gaussian_ids"),
    "vertex_labels": (lambda t: t["labels"].__setitem__(0, -2), "labels"),
    "mesh": (lambda t: t["faces"].__setitem__((1, 2), 4), "faces"),
    "view_maps": (lambda t: t["object_ids"].__setitem__((0, 0, 0), 3), "object_ids"),
    "topk": (lambda t: t["ids"].__setitem__((0, 0, 1), 7), "ids"),
    "fuse_partial": (lambda t: t["mask_group"].__setitem__(2, 3), "mask_group"),
    "warp_partial": (lambda t: t["edge_masks"].__setitem__((1, 1), 6), "edge_masks"),
    "semantic_index": (lambda t: t["index"].__setitem__(0, 3), "index"),
}


def other_dtype(arr: np.ndarray) -> np.ndarray:
    """The array in a dtype no kind accepts for it."""
    if arr.dtype.kind == "f":
        return arr.astype(np.float64 if arr.dtype != np.float64 else np.float32)
    return arr.astype(np.int64)


def write_file(path: Path, tensors: dict[str, np.ndarray], metadata: dict[str, str]) -> Path:
    """Writes with the safetensors reference writer."""
    save_file({k: np.require(v, requirements="C") for k, v in tensors.items()}, str(path), metadata=metadata)
    return path


def write_kind(path: Path, kind: str, tensors: dict, meta: dict, version: str = "1.0") -> Path:
    full = {"format": f"profuse.{kind}", "format_version": version, **meta}
    return write_file(path, tensors, full)


def split_file(data: bytes) -> tuple[dict, bytes]:
    (n,) = struct.unpack("<Q", data[:8])
    return json.loads(data[8 : 8 + n]), data[8 + n :]


def join_file(header: Any, body: bytes, pad: bool = True) -> bytes:
    text = (header if isinstance(header, str) else json.dumps(header)).encode("utf-8")
    if pad:
        text += b" " * ((-(8 + len(text))) % 8)
    return struct.pack("<Q", len(text)) + text + body


def edit_header(path: Path, edit: Callable[[dict], None]) -> Path:
    header, body = split_file(path.read_bytes())
    edit(header)
    path.write_bytes(join_file(header, body))
    return path


def last_tensor(header: dict) -> str:
    return max((n for n in header if n != "__metadata__"), key=lambda n: header[n]["data_offsets"])


def mutate(rng: random.Random, data: bytes) -> bytes:
    """One random edit of a valid file (for the Rust parity test)."""
    header, body = split_file(data)
    names = [k for k in header if k != "__metadata__"]
    r = rng.random()
    if r < 0.35:
        b = bytearray(body)
        for _ in range(rng.randint(1, 3)):
            if b:
                b[rng.randrange(len(b))] = rng.choice([0, 0xFF, 0x7F, 0x80, 0x3C, 0x7C, rng.randrange(256)])
        return join_file(header, bytes(b))
    if r < 0.55:
        meta = header.setdefault("__metadata__", {})
        key = rng.choice(list(meta) + ["format", "format_version"])
        if rng.random() < 0.2:
            meta.pop(key, None)
        else:
            meta[key] = rng.choice(
                ["", "0", "1", "+2", "2", "-1", "[]", '["a"]', '["a",""]', '["x","y","z"]',
                 "normalized", "1.0", "1.9", "8", meta.get(key, "x") + " ", "profuse.mesh",
                 "99999999999999999999"]
            )
        return join_file(header, body)
    if r < 0.75:
        entry = header[rng.choice(names)]
        if rng.random() < 0.5:
            entry["dtype"] = rng.choice(["U8", "U16", "U32", "I32", "F16", "F32", "F64", "U64", "BOOL"])
        elif entry["shape"]:
            i = rng.randrange(len(entry["shape"]))
            entry["shape"][i] = max(0, entry["shape"][i] + rng.choice([-1, 1]))
        return join_file(header, body)
    if r < 0.85:
        drop = rng.choice(names)
        new_header: dict = {"__metadata__": header.get("__metadata__", {})}
        new_body = b""
        for k in sorted(names, key=lambda k: header[k]["data_offsets"]):
            if k == drop:
                continue
            b0, e0 = header[k]["data_offsets"]
            new_header[k] = dict(header[k], data_offsets=[len(new_body), len(new_body) + e0 - b0])
            new_body += body[b0:e0]
        return join_file(new_header, new_body)
    b = bytearray(data)
    for _ in range(rng.randint(1, 2)):
        b[rng.randrange(len(b))] = rng.randrange(256)
    return bytes(b)


# --------------------------------------------------------------------------------------
# Golden vectors
# --------------------------------------------------------------------------------------


@unittest.skipUnless(EXPECTED.exists(), "formats/vectors/expected.json not present")
class GoldenVectorTests(ParityMixin, unittest.TestCase):
    @classmethod
    def setUpClass(cls) -> None:
        cls.expected = json.loads(EXPECTED.read_text(encoding="utf-8"))

    def test_every_vector_is_listed(self) -> None:
        on_disk = {
            f"{sub}/{p.name}" for sub in ("valid", "invalid") for p in (VECTORS / sub).glob("*.safetensors")
        }
        listed = set(self.expected["valid"]) | set(self.expected["invalid"])
        self.assertEqual(on_disk, listed)

    def test_valid_vectors(self) -> None:
        self.assertTrue(self.expected["valid"])
        for name, exp in sorted(self.expected["valid"].items()):
            with self.subTest(vector=name):
                rec = pf.read_any(VECTORS / name)
                self.assertEqual(rec.KIND, exp["kind"])
                self.assertEqual(rec.counts(), exp["counts"])
                self.assertEqual(rec.metadata, exp["metadata"])
                arrays = rec.arrays()
                self.assertEqual(set(arrays), set(exp["tensors"]))
                for tname, t in exp["tensors"].items():
                    arr = arrays[tname]
                    self.assertEqual(_DTYPE_NAMES[arr.dtype], t["dtype"], tname)
                    self.assertEqual(list(arr.shape), t["shape"], tname)
                    if arr.dtype.kind == "f":
                        want = np.array(t["values"], dtype=np.float64)
                        got = arr.astype(np.float64).ravel()
                        self.assertTrue(np.array_equal(got, want), f"values of {tname}")
                    else:
                        self.assertEqual(arr.ravel().tolist(), t["values"], f"values of {tname}")
                # the kind-specific reader agrees with read_any
                again = getattr(pf, f"read_{exp['kind']}")(VECTORS / name)
                self.assertEqual(again.counts(), exp["counts"])

    def test_invalid_vectors(self) -> None:
        self.assertTrue(self.expected["invalid"])
        for name, exp in sorted(self.expected["invalid"].items()):
            with self.subTest(vector=name):
                with self.assertRaises(pf.FormatError) as ctx:
                    pf.read_any(VECTORS / name)
                self.assertEqual((ctx.exception.code, ctx.exception.field), (exp["code"], exp["field"]))
                self.assertIn(str(VECTORS / name), str(ctx.exception))

    def test_inspect_reports(self) -> None:
        for name, exp in self.expected["valid"].items():
            report, err = pf.inspect(VECTORS / name)
            self.assertIsNone(err)
            self.assertTrue(report["valid"])
            self.assertEqual(report["counts"], exp["counts"])
            self.assertEqual(report["kind"], exp["kind"])
            self.assertEqual(report["size_bytes"], (VECTORS / name).stat().st_size)
        for name, exp in self.expected["invalid"].items():
            report, err = pf.inspect(VECTORS / name)
            self.assertFalse(report["valid"])
            self.assertEqual(report["counts"], {})
            self.assertEqual(report["error"], {"code": exp["code"], "field": exp["field"]})

    def test_cli(self) -> None:
        valid = next(iter(sorted(self.expected["valid"])))
        invalid = next(iter(sorted(self.expected["invalid"])))
        ok = run_python_cli(valid, VECTORS)
        self.assertEqual(ok.returncode, 0, ok.stderr)
        self.assertTrue(ok.stdout.endswith(b"}\n"))
        self.assertIs(json.loads(ok.stdout)["valid"], True)
        self.assertEqual(json.loads(ok.stdout)["file"], valid)
        self.assertEqual(ok.stderr, b"")
        bad = run_python_cli(invalid, VECTORS)
        self.assertEqual(bad.returncode, 1)
        self.assertIs(json.loads(bad.stdout)["valid"], False)
        self.assertTrue(bad.stderr.startswith(b"error: "))

    @unittest.skipIf(RUST is None, "PROFUSE_RUST_INSPECT not set")
    def test_rust_parity_on_every_vector(self) -> None:
        # Every vector against the Rust binary; the Python side runs in-process (the same
        # code path as the CLI's main) except for every valid vector and every 8th invalid
        # one, which go through the real Python CLI. Starting an interpreter per vector
        # would cost a minute of CI for no extra coverage.
        valid = sorted(self.expected["valid"])
        invalid = sorted(self.expected["invalid"])
        for i, name in enumerate(valid + invalid):
            with self.subTest(vector=name):
                through_cli = name in valid or i % 8 == 0
                self.assert_rust_agrees(name, VECTORS, subprocess_python=through_cli)

    @unittest.skipIf(RUST is None, "PROFUSE_RUST_INSPECT not set")
    def test_rust_parity_on_random_mutations(self) -> None:
        """Seeded random one-edit mutations of the valid vectors (data bytes, metadata
        values, dtypes, shapes, dropped tensors, raw bytes): same report and exit code."""
        rng = random.Random(20240601)
        sources = [(VECTORS / n).read_bytes() for n in sorted(self.expected["valid"])]
        with tempfile.TemporaryDirectory() as tmp:
            for i in range(400):
                data = mutate(rng, rng.choice(sources))
                name = f"m{i}.safetensors"
                (Path(tmp) / name).write_bytes(data)
                with self.subTest(mutation=i):
                    self.assert_rust_agrees(name, Path(tmp))


# --------------------------------------------------------------------------------------
# Python-only bad inputs
# --------------------------------------------------------------------------------------


class TempDirTest(ParityMixin, unittest.TestCase):
    def setUp(self) -> None:
        self._tmp = tempfile.TemporaryDirectory()
        self.dir = Path(self._tmp.name)
        self.count = 0

    def tearDown(self) -> None:
        self._tmp.cleanup()

    def fresh(self, stem: str = "f") -> Path:
        self.count += 1
        return self.dir / f"{stem}_{self.count}.safetensors"

    def build(self, kind: str, edit: Callable[[dict, dict], None] | None = None, version: str = "1.0") -> Path:
        tensors, meta = sample(kind)
        if edit is not None:
            edit(tensors, meta)
        return write_kind(self.fresh(kind), kind, tensors, meta, version)

    def assert_rejects(
        self, path: Path, code: str, field: str | None, kind: str | None = None, any_kind: bool = True
    ) -> pf.FormatError:
        """The reader of ``kind`` (or ``read_any``) fails with ``code``/``field``; unless
        ``any_kind`` is False (the file is fine as another kind), so do ``read_any``,
        ``inspect`` and, when configured, the Rust ``profuse inspect``."""
        reader = pf.read_any if kind is None else getattr(pf, f"read_{kind}")
        with self.assertRaises(pf.FormatError) as ctx:
            reader(path)
        err = ctx.exception
        self.assertEqual((err.code, err.field), (code, field), err.message)
        self.assertIn(str(path), err.message)
        if field is not None:
            self.assertIn(field, err.message)
        if not any_kind:
            return err
        report, rerr = pf.inspect(path)
        self.assertFalse(report["valid"])
        self.assertEqual(report["error"], {"code": code, "field": field})
        self.assertIsNotNone(rerr)
        self.assert_rust_agrees(path.name, path.parent)
        return err

    def assert_reads(self, path: Path, kind: str | None = None) -> Any:
        rec = pf.read_any(path) if kind is None else getattr(pf, f"read_{kind}")(path)
        report, err = pf.inspect(path)
        self.assertIsNone(err)
        self.assertTrue(report["valid"])
        self.assert_rust_agrees(path.name, path.parent)
        return rec


class GenericDefectTests(TempDirTest):
    """The defects of the brief, for every kind, through its own reader."""

    def test_samples_are_valid(self) -> None:
        for kind in pf.KINDS:
            with self.subTest(kind=kind):
                rec = self.assert_reads(self.build(kind), kind)
                self.assertEqual(rec.KIND, kind)
                tensors, _ = sample(kind)
                for name, arr in tensors.items():
                    np.testing.assert_array_equal(getattr(rec, name), arr)

    def test_wrong_kind(self) -> None:
        for kind in pf.KINDS:
            other = "mesh" if kind != "mesh" else "cameras"
            with self.subTest(kind=kind):
                path = self.build(kind)
                self.assert_rejects(path, "wrong_kind", "format", other, any_kind=False)
                edit_header(path, lambda h: h["__metadata__"].__setitem__("format", "profuse.nope"))
                self.assert_rejects(path, "wrong_kind", "format")
                edit_header(path, lambda h: h["__metadata__"].pop("format"))
                self.assert_rejects(path, "wrong_kind", "format", kind)

    def test_wrong_version(self) -> None:
        for kind in pf.KINDS:
            for version in ("2.0", "0.9", "1", "1.0.0", "v1.0", "", "1.x", "1.-0", "1.4294967296"):
                with self.subTest(kind=kind, version=version):
                    path = self.build(kind, version=version)
                    self.assert_rejects(path, "wrong_version", "format_version", kind)

    def test_missing_tensor(self) -> None:
        for kind in pf.KINDS:
            tensors, _ = sample(kind)
            for name in tensors:
                if kind == "gaussians" and name == "sh_rest":
                    continue  # required only for sh_degree > 0; covered below
                optional = name in {
                    "distortion", "class_ids", "weight_sum", "confidence", "colors", "faces",
                    "labels", "instances", "object_ids",
                } and not (kind in ("masks", "vertex_labels") and name == "labels")
                if optional:
                    continue
                with self.subTest(kind=kind, tensor=name):
                    path = self.build(kind, lambda t, m: t.pop(name))
                    self.assert_rejects(path, "missing_tensor", name, kind)

    def test_wrong_dtype(self) -> None:
        for kind in pf.KINDS:
            tensors, _ = sample(kind)
            for name in tensors:
                with self.subTest(kind=kind, tensor=name):
                    path = self.build(kind, lambda t, m: t.__setitem__(name, other_dtype(t[name])))
                    self.assert_rejects(path, "dtype", name, kind)

    def test_inconsistent_shape(self) -> None:
        for kind in pf.KINDS:
            first, second = GENERIC[kind][2]
            with self.subTest(kind=kind):
                path = self.build(kind, lambda t, m: t.__setitem__(second, t[second][:-1]))
                self.assert_rejects(path, "shape", second, kind)
            with self.subTest(kind=kind, rank=True):
                path = self.build(kind, lambda t, m: t.__setitem__(first, t[first][..., None]))
                self.assert_rejects(path, "shape", first, kind)

    def test_out_of_range(self) -> None:
        for kind, (mutate, field) in OUT_OF_RANGE.items():
            with self.subTest(kind=kind):
                path = self.build(kind, lambda t, m: mutate(t))
                self.assert_rejects(path, "out_of_range", field, kind)

    def test_non_finite(self) -> None:
        for kind in pf.KINDS:
            name = GENERIC[kind][1]
            if name is None:
                continue
            for value in (np.nan, np.inf, -np.inf):
                with self.subTest(kind=kind, value=value):
                    def poison(t: dict, m: dict) -> None:
                        arr = t[name].copy()
                        arr.reshape(-1)[-1] = value
                        t[name] = arr
                    path = self.build(kind, poison)
                    self.assert_rejects(path, "non_finite", name, kind)

    def test_truncated(self) -> None:
        for kind in pf.KINDS:
            with self.subTest(kind=kind):
                path = self.build(kind)
                data = path.read_bytes()
                path.write_bytes(data[:-1])
                self.assert_rejects(path, "truncated", None, kind)
                path.write_bytes(data[:7])
                self.assert_rejects(path, "truncated", None, kind)
                path.write_bytes(b"")
                self.assert_rejects(path, "truncated", None, kind)

    def test_header_length_past_eof(self) -> None:
        for kind in pf.KINDS:
            with self.subTest(kind=kind):
                path = self.build(kind)
                data = path.read_bytes()
                path.write_bytes(struct.pack("<Q", len(data) - 7) + data[8:])
                self.assert_rejects(path, "truncated", None, kind)
                path.write_bytes(struct.pack("<Q", 100_000_001) + data[8:])
                self.assert_rejects(path, "header", None, kind)

    def test_non_json_header(self) -> None:
        for kind in pf.KINDS:
            with self.subTest(kind=kind):
                path = self.build(kind)
                header, body = split_file(path.read_bytes())
                text = json.dumps(header)
                for bad in ("#" + text[1:], text[:-1], text + "x", "[" + text + "]", '"x"'):
                    path.write_bytes(join_file(bad, body))
                    self.assert_rejects(path, "header", None, kind)
                raw = json.dumps(header).encode()
                path.write_bytes(struct.pack("<Q", len(raw) + 1) + raw + b"\xff" + body)
                self.assert_rejects(path, "header", None, kind)

    def test_lying_header(self) -> None:
        for kind in pf.KINDS:
            target = GENERIC[kind][0]
            with self.subTest(kind=kind, lie="shape"):
                path = edit_header(self.build(kind), lambda h: h[target]["shape"].insert(0, 2))
                self.assert_rejects(path, "header", None, kind)
            with self.subTest(kind=kind, lie="overlap"):
                def overlap(h: dict) -> None:
                    last = h[last_tensor(h)]["data_offsets"]
                    last[0] -= 1
                    last[1] -= 1
                path = edit_header(self.build(kind), overlap)
                self.assert_rejects(path, "header", None, kind)
            with self.subTest(kind=kind, lie="gap"):
                def gap(h: dict) -> None:
                    last = h[last_tensor(h)]["data_offsets"]
                    last[0] += 1
                    last[1] += 1
                path = edit_header(self.build(kind), gap)
                self.assert_rejects(path, "header", None, kind)
            with self.subTest(kind=kind, lie="trailing"):
                path = self.build(kind)
                path.write_bytes(path.read_bytes() + b"\0")
                self.assert_rejects(path, "header", None, kind)
            with self.subTest(kind=kind, lie="dtype"):
                path = edit_header(self.build(kind), lambda h: h[target].__setitem__("dtype", "F8_E4M3"))
                self.assert_rejects(path, "header", None, kind)


class ContainerTests(TempDirTest):
    """SPEC.md section 2 corner cases, and JSON parsed as strictly as serde_json."""

    def with_header(self, header: Any, body: bytes = b"", pad: bool = True) -> Path:
        path = self.fresh("c")
        path.write_bytes(join_file(header, body, pad))
        return path

    def mesh_parts(self) -> tuple[dict, bytes]:
        return split_file(self.build("mesh").read_bytes())

    def test_foreign_formats_are_named(self) -> None:
        """Issue 20 item 12: a PLY, .npy or .npz given as a container is named, with the
        tool that reads it, instead of "header length ... exceeds the limit"."""
        cases = [
            (b"ply\nformat binary_little_endian 1.0\nend_header\n", "not a safetensors file: it is a PLY file; convert an INRIA 3DGS PLY with `scene-io ply-import FILE --out gaussians.safetensors`"),
            (b"\x93NUMPY\x01\x00v\x00{'descr': '<f4'}", "it is a NumPy .npy array"),
            (b"PK\x03\x04\x14\x00\x00\x00\x08\x00", "it is a zip archive"),
        ]
        for raw, expected in cases:
            path = self.fresh("foreign")
            path.write_bytes(raw)
            err = self.assert_rejects(path, "header", None)
            self.assertIn(expected, err.message)

    def test_io(self) -> None:
        missing = self.dir / "missing.safetensors"
        err = self.assert_rejects(missing, "io", None)
        self.assertIn("cannot open", err.message)
        report, _ = pf.inspect(missing)
        self.assertIsNone(report["size_bytes"])
        self.assertEqual((report["metadata"], report["tensors"]), ({}, {}))
        with self.assertRaises(pf.FormatError) as ctx:
            pf.read_any(self.dir)
        self.assertEqual(ctx.exception.code, "io")

    def test_unreadable_container_has_null_size(self) -> None:
        path = self.with_header("not json")
        report, err = pf.inspect(path)
        self.assertEqual(err.code, "header")
        self.assertIsNone(report["size_bytes"])
        self.assertIsNone(report["kind"])

    def test_header_entry_rules(self) -> None:
        h, body = self.mesh_parts()
        bad_entries = [
            [],
            {"shape": [4, 3], "data_offsets": [0, 48]},
            {"dtype": 5, "shape": [4, 3], "data_offsets": [0, 48]},
            {"dtype": "f32", "shape": [4, 3], "data_offsets": [0, 48]},
            {"dtype": "F32", "data_offsets": [0, 48]},
            {"dtype": "F32", "shape": [4, -3], "data_offsets": [0, 48]},
            {"dtype": "F32", "shape": [4, 3.0], "data_offsets": [0, 48]},
            {"dtype": "F32", "shape": [4, True], "data_offsets": [0, 48]},
            {"dtype": "F32", "shape": "4,3", "data_offsets": [0, 48]},
            {"dtype": "F32", "shape": [4, 3]},
            {"dtype": "F32", "shape": [4, 3], "data_offsets": [0]},
            {"dtype": "F32", "shape": [4, 3], "data_offsets": [0, 48, 48]},
            {"dtype": "F32", "shape": [4, 3], "data_offsets": [48, 0]},
            {"dtype": "F32", "shape": [4, 3], "data_offsets": [0, 44]},
            {"dtype": "F32", "shape": [2**40, 2**40, 0], "data_offsets": [0, 0]},
            {"dtype": "F64", "shape": [2**62], "data_offsets": [0, 0]},
        ]
        for entry in bad_entries:
            with self.subTest(entry=entry):
                header = dict(h)
                vertices = header["vertices"]
                if isinstance(entry, dict) and "data_offsets" in entry and entry["data_offsets"] == [0, 48]:
                    entry = {**entry, "data_offsets": vertices["data_offsets"]}
                header["vertices"] = entry
                self.assert_rejects(self.with_header(header, body), "header", None)

    def test_metadata_must_be_string_map(self) -> None:
        h, body = self.mesh_parts()
        for meta in (None, [], "x", {"format": "profuse.mesh", "format_version": "1.0", "n": 3}):
            with self.subTest(meta=meta):
                self.assert_rejects(self.with_header({**h, "__metadata__": meta}, body), "header", None)

    def test_strict_json(self) -> None:
        h, body = self.mesh_parts()
        text = json.dumps(h)
        entry = '"vertices": {'
        cases = {
            "nan": text.replace(entry, entry + '"x": NaN, '),
            "infinity": text.replace(entry, entry + '"x": -Infinity, '),
            "float_overflow": text.replace(entry, entry + '"x": 1e400, '),
            "int_overflow": text.replace(entry, entry + '"x": ' + "9" * 400 + ", "),
            "lone_surrogate": text.replace('"nyu40"', '"\\ud800"'),
            "trailing_surrogate": text.replace('"nyu40"', '"\\udc00x"'),
            # serde_json's limit: 128 nested arrays/objects (header + entry + 126 here)
            "deep_128": text.replace(entry, entry + '"x": ' + "[" * 126 + "]" * 126 + ", "),
            "very_deep": text.replace(entry, entry + '"x": ' + "[" * 100000 + "]" * 100000 + ", "),
            "neg_zero_shape": text.replace('"shape": [4, 3]', '"shape": [-0, 3]', 1),
            "exp_shape": text.replace('"shape": [4, 3]', '"shape": [4e0, 3]', 1),
            "bom": "\ufeff" + text,
            "comment": text + " // x",
            "single_quotes": text.replace('"nyu40"', "'nyu40'"),
            "control_char": text.replace('"nyu40"', '"ny\tu40"'),
        }
        for name, bad in cases.items():
            with self.subTest(case=name):
                self.assert_rejects(self.with_header(bad, body), "header", None)

    def test_lenient_json_that_serde_accepts(self) -> None:
        h, body = self.mesh_parts()
        text = json.dumps(h)
        entry = '"vertices": {'
        cases = {
            "extra_entry_key": text.replace(entry, entry + '"x": [1, -2, 3.5e300, null], '),
            "deep_127": text.replace(entry, entry + '"x": ' + "[" * 125 + "]" * 125 + ", "),
            "whitespace": " \n\t\r" + text + " \n",
            "surrogate_pair": text.replace('"nyu40"', '"\\ud83d\\ude00 \\u00e9"'),
            "escaped_key": text.replace('"label_space"', '"label\\u005fspace"'),
            "big_ints_elsewhere": text.replace(entry, entry + '"x": 18446744073709551616, '),
            "duplicate_metadata": text[:-1] + ', "__metadata__": ' + json.dumps(h["__metadata__"]) + "}",
            "unpadded": text,
        }
        for name, good in cases.items():
            with self.subTest(case=name):
                path = self.with_header(good, body, pad=(name != "unpadded"))
                rec = self.assert_reads(path)
                np.testing.assert_array_equal(rec.vertices, sample("mesh")[0]["vertices"])

    def test_extra_tensors_and_metadata_are_ignored_but_reported(self) -> None:
        def extra(t: dict, m: dict) -> None:
            t["zz_extra"] = np.zeros((2, 0), np.int16)
            t["a_flag"] = np.array(True)
            m["unknown_key"] = "ünïcødé \u2028 \x01 \x7f \"q\" \\"
        path = self.build("selection", extra)
        self.assert_reads(path)
        report, _ = pf.inspect(path)
        self.assertEqual(report["tensors"]["zz_extra"], {"dtype": "I16", "shape": [2, 0]})
        self.assertEqual(report["tensors"]["a_flag"], {"dtype": "BOOL", "shape": []})
        self.assertIn("unknown_key", report["metadata"])
        text = pf.report_json(report)
        self.assertIn("ünïcødé", text)
        self.assertIn('"shape": []', text)
        self.assertIn("\\u0001", text)

    def test_bf16_extra_tensor(self) -> None:
        h, body = self.mesh_parts()
        h = dict(h)
        end = max(v["data_offsets"][1] for k, v in h.items() if k != "__metadata__")
        h["z_bf16"] = {"dtype": "BF16", "shape": [2], "data_offsets": [end, end + 4]}
        self.assert_reads(self.with_header(h, body + b"\0\0\0\0"))

    def test_empty_container(self) -> None:
        path = self.with_header({})
        self.assert_rejects(path, "wrong_kind", "format")
        report, _ = pf.inspect(path)
        self.assertEqual(report["size_bytes"], path.stat().st_size)

    def test_version_forms(self) -> None:
        for version in ("1.0", "1.7", "1.00", "01.0", "1.4294967295"):
            with self.subTest(version=version):
                self.assert_reads(self.build("mesh", version=version))
        for version in ("1. 0", " 1.0", "1.0 ", "+1.0", "1.+0", "\uff11.0", "1.0.", ".0"):
            with self.subTest(version=version):
                self.assert_rejects(self.build("mesh", version=version), "wrong_version", "format_version")

    def test_usize_metadata(self) -> None:
        for value in ("10", "+10", "010", "18446744073709551615"):
            with self.subTest(value=value):
                rec = self.assert_reads(self.build("selection", lambda t, m: m.__setitem__("num_gaussians", value)))
                self.assertEqual(rec.num_gaussians, int(value))
        for value in ("", " 10", "10 ", "-0", "1e1", "10.0", "0x10", "1_0", "\u0661\u0660", "18446744073709551616", "+"):
            with self.subTest(value=value):
                path = self.build("selection", lambda t, m: m.__setitem__("num_gaussians", value))
                self.assert_rejects(path, "metadata", "num_gaussians")


class KindRuleTests(TempDirTest):
    """Each kind's metadata and value rules, in the Rust order."""

    def check(self, kind: str, edit: Callable[[dict, dict], None], code: str, field: str | None) -> None:
        self.assert_rejects(self.build(kind, edit), code, field, kind)

    def ok(self, kind: str, edit: Callable[[dict, dict], None]) -> Any:
        return self.assert_reads(self.build(kind, edit), kind)

    def test_cameras(self) -> None:
        def setv(name: str, idx: Any, value: Any) -> Callable:
            return lambda t, m: t[name].__setitem__(idx, value)
        self.check("cameras", lambda t, m: m.pop("image_names"), "metadata", "image_names")
        self.check("cameras", lambda t, m: m.__setitem__("image_names", '["a", 1]'), "metadata", "image_names")
        self.check("cameras", lambda t, m: m.__setitem__("image_names", "a.png"), "metadata", "image_names")
        self.check("cameras", lambda t, m: m.__setitem__("image_names", '["a", ""]'), "metadata", "image_names")
        self.check("cameras", lambda t, m: m.__setitem__("image_names", '["a"]'), "shape", "image_size")
        self.check("cameras", setv("image_size", (0, 1), 0), "out_of_range", "image_size")
        self.check("cameras", setv("intrinsics", (1, 1), 0.0), "out_of_range", "intrinsics")
        self.check("cameras", setv("intrinsics", (1, 0), -3.0), "out_of_range", "intrinsics")
        self.check("cameras", setv("world_to_camera", (1, 0, 3), np.inf), "non_finite", "world_to_camera")
        self.check("cameras", setv("world_to_camera", (1, 0, 0), 0.01), "invalid", "world_to_camera")
        self.check("cameras", setv("world_to_camera", (0, 2, 2), -1.0), "invalid", "world_to_camera")
        self.check("cameras", setv("distortion", (0, 0), np.nan), "non_finite", "distortion")
        # within tolerance, and a missing optional tensor
        self.ok("cameras", setv("world_to_camera", (0, 0, 1), 5e-5))
        rec = self.ok("cameras", lambda t, m: t.pop("distortion"))
        self.assertEqual(rec.counts(), {"views": 2, "distorted": 0})
        # the lanes check: a shape whose element count is not a multiple of the row length
        self.check("cameras", lambda t, m: t.__setitem__("image_size", np.ones((2, 3), np.uint32)), "shape", "image_size")
        # Rust order: the empty-name rule runs after the tensor checks
        def both(t: dict, m: dict) -> None:
            m["image_names"] = '["a", ""]'
            t.pop("intrinsics")
        self.check("cameras", both, "missing_tensor", "intrinsics")

    def test_gaussians(self) -> None:
        self.check("gaussians", lambda t, m: m.__setitem__("sh_degree", "4"), "metadata", "sh_degree")
        self.check("gaussians", lambda t, m: m.pop("sh_degree"), "metadata", "sh_degree")
        self.check("gaussians", lambda t, m: m.__setitem__("sh_degree", "0"), "metadata", "sh_degree")
        self.check("gaussians", lambda t, m: m.__setitem__("sh_degree", "2"), "shape", "sh_rest")
        self.check("gaussians", lambda t, m: t.pop("sh_rest"), "missing_tensor", "sh_rest")
        self.check("gaussians", lambda t, m: t["rotations"].__setitem__(1, 0.0), "invalid", "rotations")
        self.check("gaussians", lambda t, m: t["opacity_logits"].__setitem__(0, np.inf), "non_finite", "opacity_logits")
        self.check("gaussians", lambda t, m: t["sh_rest"].__setitem__((2, 2, 2), np.nan), "non_finite", "sh_rest")
        # sh_rest is checked before means (SPEC: sh_rest finite first)
        def two(t: dict, m: dict) -> None:
            t["sh_rest"][0, 0, 0] = np.nan
            t["means"][0, 0] = np.nan
        self.check("gaussians", two, "non_finite", "sh_rest")

        def degree0(t: dict, m: dict) -> None:
            m["sh_degree"] = "0"
            t.pop("sh_rest")
        rec = self.ok("gaussians", degree0)
        self.assertEqual(rec.counts(), {"gaussians": 3, "sh_degree": 0})
        self.assertIsNone(rec.sh_rest)
        self.ok("gaussians", lambda t, m: t["rotations"].__setitem__(1, [-0.0, 0.0, 0.0, 1e-30]))

    def test_masks(self) -> None:
        def setv(name: str, idx: Any, value: Any) -> Callable:
            return lambda t, m: t[name].__setitem__(idx, value)
        self.check("masks", setv("mask_offsets", 0, 1), "out_of_range", "mask_offsets")
        self.check("masks", setv("mask_offsets", 1, 6), "out_of_range", "mask_offsets")
        self.check("masks", setv("mask_offsets", 2, 4), "out_of_range", "mask_offsets")
        self.check("masks", setv("labels", (0, 1, 0), 3), "out_of_range", "labels")
        self.check("masks", setv("features", (0, 0), 0.9), "invalid", "features")
        self.check("masks", lambda t, m: t.__setitem__("labels", t["labels"].astype(np.int32)), "dtype", "labels")
        self.check("masks", lambda t, m: m.__setitem__("view_names", '["a"]'), "shape", "labels")
        self.check("masks", lambda t, m: t.__setitem__("features", np.zeros((5, 0), np.float32)), "shape", "features")
        self.check("masks", lambda t, m: t.__setitem__("features", t["features"][:4]), "out_of_range", "mask_offsets")
        # U32 labels with the U32 reserved value; F16 features with the F16 tolerance
        def wide(t: dict, m: dict) -> None:
            lab = t["labels"].astype(np.uint32)
            lab[lab == U16_NONE] = U32_NONE
            t["labels"] = lab
        self.ok("masks", wide)
        self.check("masks", lambda t, m: t.__setitem__("labels", t["labels"].astype(np.uint32)), "out_of_range", "labels")

        def half(scale: float) -> Callable:
            def edit(t: dict, m: dict) -> None:
                t["features"] = (t["features"] * scale).astype(np.float16)
            return edit
        self.ok("masks", half(1.005))
        self.check("masks", half(1.02), "invalid", "features")
        self.check("masks", lambda t, m: t.__setitem__("features", t["features"] * np.float32(1.001)), "invalid", "features")
        rec = self.ok("masks", lambda t, m: None)
        self.assertEqual(rec.counts(), {"views": 2, "masks": 5, "height": 2, "width": 3, "feature_dim": 4})

    def test_masks_u16_view_capacity(self) -> None:
        m_count = 65536

        def crowded(t: dict, m: dict) -> None:
            m["view_names"] = '["a"]'
            t["labels"] = np.zeros((1, 1, 1), np.uint16)
            t["mask_offsets"] = np.array([0, m_count], np.uint32)
            t["features"] = np.ones((m_count, 1), np.float16)
        self.check("masks", crowded, "out_of_range", "mask_offsets")

    def test_matches(self) -> None:
        self.check("matches", lambda t, m: m.__setitem__("coords", "pixel"), "metadata", "coords")
        self.check("matches", lambda t, m: m.pop("coords"), "metadata", "coords")
        self.check("matches", lambda t, m: m.__setitem__("num_views", "two"), "metadata", "num_views")
        self.check("matches", lambda t, m: t["pairs"].__setitem__(1, [1, 1]), "invalid", "pairs")
        self.check("matches", lambda t, m: t["pairs"].__setitem__(1, [0, 1]), "invalid", "pairs")
        self.check("matches", lambda t, m: t["certainty"].__setitem__((1, 1, 2), 1.5), "out_of_range", "certainty")
        self.check("matches", lambda t, m: t["certainty"].__setitem__((0, 0, 0), -0.25), "out_of_range", "certainty")
        self.check("matches", lambda t, m: t["certainty"].__setitem__((0, 0, 0), np.nan), "non_finite", "certainty")
        self.check("matches", lambda t, m: t.__setitem__("certainty", t["certainty"][:, :1]), "shape", "certainty")
        # range beats self-pair in the same row; an earlier duplicate beats a later range error
        self.check("matches", lambda t, m: t["pairs"].__setitem__(1, [5, 5]), "out_of_range", "pairs")

        def mixed(t: dict, m: dict) -> None:
            t["warp"] = t["warp"].astype(np.float16)
            t["certainty"][0, 0, 0] = -0.0
        rec = self.ok("matches", mixed)
        self.assertEqual(rec.counts(), {"views": 2, "pairs": 2, "height": 2, "width": 3})
        self.ok("matches", lambda t, m: t.__setitem__("certainty", t["certainty"].astype(np.float16)))

    def test_sparse_matches(self) -> None:
        self.check("sparse_matches", lambda t, m: t["pair_offsets"].__setitem__(2, 4), "out_of_range", "pair_offsets")
        self.check("sparse_matches", lambda t, m: t["pair_offsets"].__setitem__(1, 6), "out_of_range", "pair_offsets")
        self.check("sparse_matches", lambda t, m: t.__setitem__("pair_offsets", t["pair_offsets"][:2]), "shape", "pair_offsets")
        self.check("sparse_matches", lambda t, m: t["points_j"].__setitem__((4, 1), np.inf), "non_finite", "points_j")
        self.check("sparse_matches", lambda t, m: t["certainty"].__setitem__(0, 1.0000001), "out_of_range", "certainty")
        self.check("sparse_matches", lambda t, m: t["pairs"].__setitem__(1, [0, 1]), "invalid", "pairs")
        self.check("sparse_matches", lambda t, m: m.__setitem__("num_views", "2"), "out_of_range", "pairs")

    def test_proposals(self) -> None:
        self.check("proposals", lambda t, m: t["proposal_size"].__setitem__(1, 3), "invalid", "proposal_size")

        def empty(t: dict, m: dict) -> None:
            t["proposal_size"] = np.array([2, 2, 0], np.uint32)
            t["proposal_views"] = np.array([2, 1, 1], np.uint32)
        self.check("proposals", empty, "invalid", "proposal_size")
        self.check("proposals", lambda t, m: t["proposal_views"].__setitem__(0, 0), "out_of_range", "proposal_views")
        self.check("proposals", lambda t, m: t["proposal_views"].__setitem__(0, 3), "out_of_range", "proposal_views")
        rec = self.ok("proposals", lambda t, m: None)
        self.assertEqual(rec.counts(), {"masks": 5, "proposals": 2, "assigned_masks": 4})

    def test_features(self) -> None:
        self.check("features", lambda t, m: t["features"].__setitem__((2, 0), 1e-9), "invalid", "features")
        self.check("features", lambda t, m: t["features"].__setitem__((0, 0), 0.5), "invalid", "features")
        self.check("features", lambda t, m: t["weight_sum"].__setitem__(1, -1.0), "out_of_range", "weight_sum")
        self.check("features", lambda t, m: t["weight_sum"].__setitem__(2, 1.0), "invalid", "weight_sum")
        self.check("features", lambda t, m: t["weight_sum"].__setitem__(0, 0.0), "invalid", "weight_sum")
        self.check("features", lambda t, m: t["weight_sum"].__setitem__(0, np.nan), "non_finite", "weight_sum")
        self.check("features", lambda t, m: t.__setitem__("features", np.zeros((4, 0), np.float32)), "shape", "features")
        self.check("features", lambda t, m: t.__setitem__("valid", t["valid"][:3]), "shape", "valid")
        rec = self.ok("features", lambda t, m: t.__setitem__("features", t["features"].astype(np.float16)))
        self.assertEqual(rec.counts(), {"gaussians": 4, "feature_dim": 4, "valid": 3})
        self.ok("features", lambda t, m: t.pop("weight_sum"))

    def test_pq(self) -> None:
        self.check("pq", lambda t, m: m.__setitem__("metric", "l2"), "metadata", "metric")
        self.check("pq", lambda t, m: m.pop("metric"), "metadata", "metric")
        self.check("pq", lambda t, m: m.__setitem__("nbits", "4"), "metadata", "nbits")
        self.check("pq", lambda t, m: t.__setitem__("centroids", t["centroids"][:, :255]), "shape", "centroids")
        self.check("pq", lambda t, m: t.__setitem__("codes", t["codes"][:, :1]), "shape", "codes")
        self.check("pq", lambda t, m: t["norms"].__setitem__(0, -0.5), "out_of_range", "norms")
        self.check("pq", lambda t, m: t["norms"].__setitem__(2, 0.5), "invalid", "norms")
        self.check("pq", lambda t, m: t["centroids"].__setitem__((1, 200, 1), np.nan), "non_finite", "centroids")

        def no_subquantisers(t: dict, m: dict) -> None:
            t["centroids"] = np.zeros((0, 256, 2), np.float32)
            t["codes"] = np.zeros((3, 0), np.uint8)
        self.check("pq", no_subquantisers, "shape", "centroids")
        self.ok("pq", lambda t, m: m.__setitem__("nbits", "+8"))
        rec = self.ok("pq", lambda t, m: t["norms"].__setitem__(2, -0.0))
        self.assertEqual(rec.counts(), {"vectors": 3, "dim": 4, "m": 2, "ksub": 256, "valid": 2})

    def test_prompts(self) -> None:
        self.check("prompts", lambda t, m: m.__setitem__("names", '["a", "b", "a"]'), "metadata", "names")
        self.check("prompts", lambda t, m: m.__setitem__("names", '["a", "", "c"]'), "metadata", "names")
        self.check("prompts", lambda t, m: m.__setitem__("names", '["a", "b"]'), "shape", "embeddings")
        self.check("prompts", lambda t, m: t["embeddings"].__setitem__(1, 0.0), "invalid", "embeddings")
        self.check("prompts", lambda t, m: t.__setitem__("embeddings", np.zeros((3, 0), np.float32)), "shape", "embeddings")
        rec = self.ok("prompts", lambda t, m: t["embeddings"].__setitem__(1, 5.0))  # not unit: allowed
        self.assertEqual(rec.counts(), {"prompts": 3, "dim": 4})
        self.assertEqual(rec.names, ["chair", "red mug", "object"])

    def test_selection(self) -> None:
        self.check("selection", lambda t, m: t["gaussian_ids"].__setitem__(1, 1), "out_of_range", "gaussian_ids")
        self.check("selection", lambda t, m: m.__setitem__("prompt", ""), "metadata", "prompt")
        self.check("selection", lambda t, m: m.pop("prompt"), "metadata", "prompt")
        self.check("selection", lambda t, m: m.__setitem__("num_gaussians", "9"), "out_of_range", "gaussian_ids")
        rec = self.ok("selection", lambda t, m: None)
        self.assertEqual(rec.counts(), {"selected": 3, "gaussians": 10})

    def test_vertex_labels(self) -> None:
        self.check("vertex_labels", lambda t, m: t["confidence"].__setitem__(1, 1.5), "out_of_range", "confidence")
        self.check("vertex_labels", lambda t, m: t["confidence"].__setitem__(1, -0.1), "out_of_range", "confidence")
        rec = self.ok("vertex_labels", lambda t, m: t.pop("confidence"))
        self.assertEqual(rec.counts(), {"vertices": 5, "labelled": 4})

    def test_mesh(self) -> None:
        self.check("mesh", lambda t, m: t.__setitem__("labels", t["labels"][:3]), "shape", "labels")
        self.check("mesh", lambda t, m: t.__setitem__("faces", t["faces"][:, :2]), "shape", "faces")
        rec = self.ok("mesh", lambda t, m: [t.pop(k) for k in ("colors", "faces", "labels", "instances")])
        self.assertEqual(rec.counts(), {"vertices": 4, "faces": 0, "labelled": 0})
        rec = self.ok("mesh", lambda t, m: None)
        self.assertEqual(rec.counts(), {"vertices": 4, "faces": 2, "labelled": 3})

    def test_view_maps(self) -> None:
        self.check("view_maps", lambda t, m: m.__setitem__("view_names", '["a", ""]'), "metadata", "view_names")
        self.check("view_maps", lambda t, m: m.pop("num_objects"), "metadata", "num_objects")
        self.check("view_maps", lambda t, m: t["depth"].__setitem__((1, 1, 1), -1.0), "out_of_range", "depth")
        self.check("view_maps", lambda t, m: m.__setitem__("num_objects", "2"), "out_of_range", "object_ids")
        rec = self.ok("view_maps", lambda t, m: t.pop("object_ids"))
        self.assertEqual(rec.counts(), {"views": 2, "height": 2, "width": 3, "objects": 3})

    def test_topk(self) -> None:
        self.check("topk", lambda t, m: m.pop("num_gaussians"), "metadata", "num_gaussians")
        self.check("topk", lambda t, m: t["weights"].__setitem__((0, 0, 0), 1.5), "out_of_range", "weights")
        self.check("topk", lambda t, m: t["weights"].__setitem__((0, 1, 1), 0.05), "invalid", "weights")
        self.check("topk", lambda t, m: t["weights"].__setitem__((0, 0, 1), 0.6), "invalid", "weights")
        self.check("topk", lambda t, m: t["transmittance"].__setitem__((0, 0), 0.5), "invalid", "weights")
        self.check("topk", lambda t, m: t["transmittance"].__setitem__((0, 2), -0.5), "out_of_range", "transmittance")
        self.check(
            "topk",
            lambda t, m: [t.__setitem__(k, t[k][:, :, :0]) for k in ("ids", "weights")],
            "shape",
            "ids",
        )
        rec = self.ok("topk", lambda t, m: None)
        self.assertEqual(rec.counts(), {"height": 2, "width": 3, "k": 3, "hits": 10})


class CliTests(TempDirTest):
    def test_usage(self) -> None:
        out = subprocess.run([sys.executable, str(MODULE)], capture_output=True, timeout=60)
        self.assertEqual(out.returncode, 2)
        self.assertIn(b"usage", out.stderr)

    def test_valid_and_invalid(self) -> None:
        good = self.build("prompts")
        ok = run_python_cli(good.name, self.dir)
        self.assertEqual(ok.returncode, 0)
        report = json.loads(ok.stdout)
        self.assertEqual(report["file"], good.name)
        self.assertEqual(report["size_bytes"], good.stat().st_size)
        self.assertEqual(list(report), sorted(report))
        bad = self.build("prompts", lambda t, m: t["embeddings"].__setitem__(0, np.nan))
        out = run_python_cli(bad.name, self.dir)
        self.assertEqual(out.returncode, 1)
        self.assertEqual(json.loads(out.stdout)["error"], {"code": "non_finite", "field": "embeddings"})
        self.assertIn(b"error: " + bad.name.encode(), out.stderr)
        missing = run_python_cli("missing.safetensors", self.dir)
        self.assertEqual(missing.returncode, 1)
        self.assertIsNone(json.loads(missing.stdout)["size_bytes"])
        self.assert_rust_agrees("missing.safetensors", self.dir)


if __name__ == "__main__":
    unittest.main(verbosity=1)
