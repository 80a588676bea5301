"""Tests of the writers of profuse_formats (stdlib unittest; pytest runs them too):
``python3 test_writers.py`` or ``python3 -m pytest formats/python``.

* Golden vectors: writing the content of every valid vector of ``formats/vectors`` (as
  listed in ``expected.json``) with the kind's ``write_<kind>`` function gives exactly the
  bytes the Rust writer produced, and read -> ``write_record`` -> read is the identity.
* Rust reads what Python writes: with ``PROFUSE_RUST_INSPECT=/path/to/profuse``, a file of
  every kind written here is valid for ``profuse inspect`` with the counts Python reports.
* Bad inputs: every writer validates with the reader's rules, raises ``FormatError`` with
  the code and field, and leaves neither the file nor a temporary behind.
"""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import tempfile
import unittest
from pathlib import Path
from typing import Any

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

import profuse_formats as pf  # noqa: E402

VECTORS = HERE.parent / "vectors"
EXPECTED = json.loads((VECTORS / "expected.json").read_text())
RUST = os.environ.get("PROFUSE_RUST_INSPECT")

# Metadata keys that the per-kind writers take as arguments, and how to parse them.
_NAME_LISTS = {"image_names", "view_names", "names"}
_INTEGERS = {"num_views", "num_gaussians", "num_objects", "sh_degree", "k", "num_groups", "pixels", "hits", "min_share"}
_INTEGERS |= {"num_masks", "num_view_pairs", "first_pair", *pf.WARP_COUNTERS}
_TEXTS = {"coords", "prompt", "grouping", "orphans", *pf.WARP_INPUTS}
# Keys a writer sets itself (the Rust writer does too).
_FIXED = {"convention", "metric", "nbits"}

WRITERS = {kind: getattr(pf, f"write_{kind}") for kind in pf.KINDS}


def vector_content(entry: dict[str, Any]) -> tuple[dict[str, np.ndarray], dict[str, str]]:
    """The tensors and metadata of a valid vector, from ``expected.json``."""
    tensors = {}
    for name, t in entry["tensors"].items():
        dtype = np.dtype(pf._NUMPY_DTYPES[t["dtype"]])
        tensors[name] = np.array(t["values"], dtype=dtype).reshape(t["shape"])
    return tensors, dict(entry["metadata"])


def writer_arguments(
    tensors: dict[str, np.ndarray], metadata: dict[str, str]
) -> dict[str, Any]:
    """Keyword arguments of ``write_<kind>`` for a file's tensors and metadata."""
    kwargs: dict[str, Any] = dict(tensors)
    rest = {}
    for key, value in metadata.items():
        if key in ("format", "format_version") or key in _FIXED:
            continue
        if key in _NAME_LISTS:
            kwargs[key] = json.loads(value)
        elif key in _INTEGERS:
            kwargs[key] = int(value)
        elif key in _TEXTS:
            kwargs[key] = value
        else:
            rest[key] = value
    kwargs["metadata"] = rest
    return kwargs


def rust_inspect(path: Path) -> subprocess.CompletedProcess:
    assert RUST is not None
    return subprocess.run(
        [os.path.abspath(RUST), "inspect", str(path)], capture_output=True, timeout=120
    )


class TempDir(unittest.TestCase):
    def setUp(self) -> None:
        self._tmp = tempfile.TemporaryDirectory()
        self.dir = Path(self._tmp.name)

    def tearDown(self) -> None:
        self._tmp.cleanup()

    def leftovers(self) -> list[str]:
        return sorted(p.name for p in self.dir.iterdir() if p.name.startswith(".profuse-tmp-"))


class GoldenVectorTests(TempDir):
    def test_every_kind_has_a_writer_and_a_golden_vector(self) -> None:
        kinds = {entry["kind"] for entry in EXPECTED["valid"].values()}
        self.assertEqual(kinds, set(pf.KINDS))
        for kind, writer in WRITERS.items():
            self.assertTrue(callable(writer), kind)

    def test_writers_reproduce_the_rust_bytes(self) -> None:
        for name, entry in EXPECTED["valid"].items():
            with self.subTest(vector=name):
                tensors, metadata = vector_content(entry)
                out = self.dir / Path(name).name
                WRITERS[entry["kind"]](out, **writer_arguments(tensors, metadata), generator=None)
                self.assertEqual(out.read_bytes(), (VECTORS / name).read_bytes())

    def test_generic_writer_reproduces_the_rust_bytes(self) -> None:
        for name, entry in EXPECTED["valid"].items():
            with self.subTest(vector=name):
                tensors, metadata = vector_content(entry)
                data = pf.encode_file(entry["kind"], tensors, metadata)
                self.assertEqual(data, (VECTORS / name).read_bytes())

    def test_read_write_read_is_the_identity(self) -> None:
        for name, entry in EXPECTED["valid"].items():
            with self.subTest(vector=name):
                first = pf.read_any(VECTORS / name)
                out = self.dir / Path(name).name
                pf.write_record(out, first)
                self.assertEqual(out.read_bytes(), (VECTORS / name).read_bytes())
                again = pf.read_any(out)
                self.assertEqual(type(again), type(first))
                self.assertEqual(again.metadata, first.metadata)
                self.assertEqual(again.counts(), first.counts())
                self.assertEqual(again.arrays().keys(), first.arrays().keys())
                for key, arr in first.arrays().items():
                    self.assertEqual(again.arrays()[key].dtype, arr.dtype, key)
                    np.testing.assert_array_equal(again.arrays()[key], arr, err_msg=key)


def own_samples() -> dict[str, dict[str, Any]]:
    """Writer arguments for one file of every kind, built here (not from the vectors)."""
    rng = np.random.default_rng(7)

    def unit(rows: int, dim: int, dtype: Any = np.float32) -> np.ndarray:
        x = rng.normal(size=(rows, dim))
        return (x / np.linalg.norm(x, axis=1, keepdims=True)).astype(dtype)

    c, s = np.cos(0.3), np.sin(0.3)
    w2c = np.array([[[1, 0, 0, 0.5], [0, 1, 0, 0], [0, 0, 1, 3]], [[c, 0, s, 0], [0, 1, 0, 0], [-s, 0, c, 4]]])
    none = pf.NO_GROUP
    return {
        "cameras": dict(
            image_names=["images/0.png", "images/1.png"],
            image_size=[[64, 48], [64, 48]],
            intrinsics=[[50.0, 50.0, 32.0, 24.0], [55.0, 54.0, 31.5, 24.5]],
            world_to_camera=w2c,
        ),
        "gaussians": dict(
            means=rng.normal(size=(5, 3)),
            log_scales=np.full((5, 3), -3.0),
            rotations=[[1, 0, 0, 0]] * 5,
            opacity_logits=np.zeros(5),
            sh_dc=np.full((5, 3), 0.1),
            sh_rest=np.zeros((5, 8, 3), np.float32),
            class_ids=np.array([0, 1, -1, 2, 2]),
        ),
        "masks": dict(
            view_names=["images/0.png", "images/1.png"],
            labels=np.array([[[0, 1], [1, 65535]], [[0, 0], [65535, 65535]]], np.uint16),
            mask_offsets=[0, 2, 3],
            features=unit(3, 8, np.float16),
        ),
        "matches": dict(
            num_views=2,
            coords="pixels",
            pairs=[[0, 1]],
            warp=rng.uniform(0, 40, size=(1, 3, 4, 2)).astype(np.float32),
            certainty=rng.uniform(0, 1, size=(1, 3, 4)).astype(np.float32),
        ),
        "sparse_matches": dict(
            num_views=2,
            pairs=[[0, 1], [1, 0]],
            pair_offsets=[0, 2, 3],
            points_i=rng.uniform(0, 40, size=(3, 2)),
            points_j=rng.uniform(0, 40, size=(3, 2)),
            certainty=[1.0, 0.5, 0.25],
        ),
        "proposals": dict(
            mask_proposal=[0, none, 0], proposal_size=[2], proposal_views=[2], metadata={"tau_iou": "0.5"}
        ),
        "features": dict(
            features=np.vstack([unit(2, 4), np.zeros((1, 4), np.float32)]),
            valid=np.array([True, True, False]),
            weight_sum=[0.5, 1.5, 0.0],
        ),
        "pq": dict(
            centroids=rng.normal(size=(2, 256, 2)),
            codes=[[1, 255], [0, 0]],
            norms=[0.9, 0.0],
            valid=[1, 0],
        ),
        "prompts": dict(names=["chair", "table", "object"], embeddings=unit(3, 8), class_ids=[5, 7, -1]),
        "selection": dict(prompt="chair", num_gaussians=5, gaussian_ids=[0, 3], scores=[0.9, 0.7]),
        "vertex_labels": dict(labels=[3, -1, 5], confidence=[0.5, 0.0, 1.0]),
        "mesh": dict(
            vertices=rng.normal(size=(4, 3)),
            faces=[[0, 1, 2], [0, 2, 3]],
            colors=np.full((4, 3), 200, np.uint8),
            labels=[1, 0, 2, 2],
            metadata={"label_space": "nyu40"},
        ),
        "view_maps": dict(
            view_names=["images/0.png"],
            num_objects=2,
            depth=np.array([[[1.0, 0.0], [2.5, 3.0]]]),
            object_ids=np.array([[[0, none], [1, 1]]], np.uint32),
        ),
        "topk": dict(
            num_gaussians=5,
            ids=np.array([[[4, none], [none, none]]], np.uint32),
            weights=np.array([[[0.5, 0.0], [0.0, 0.0]]]),
            transmittance=[[0.5, 1.0]],
            metadata={"view": "0"},
        ),
        "fuse_partial": dict(
            num_gaussians=3,
            num_views=2,
            k=4,
            grouping="proposals",
            orphans="singleton",
            num_groups=2,
            pixels=7,
            hits=9,
            views=[1],
            mask_group=[0, 1, 0],
            mask_features=unit(3, 4),
            mask_mass=pf.fixed_point_words([2**62, 3 * 2**61, 2**70]),
            w_offsets=[0, 1, 1, 3],
            w_groups=[1, 0, 1],
            w_sums=pf.fixed_point_words([5, 2**64 + 1, 2**62]),
            metadata={"weight_scale": "2^-62"},
        ),
        "warp_partial": dict(
            num_views=4,
            num_masks=5,
            num_view_pairs=3,
            first_pair=0,
            pairs=np.array([[0, 1], [1, 3]], np.uint32),
            edge_offsets=np.array([0, 0, 1], np.uint64),
            edge_masks=np.array([[1, 4]], np.uint32),
            edge_scores=np.array([[0.1 + 0.2, 1.0]]),
            **{key: i for i, key in enumerate(pf.WARP_COUNTERS)},
            **{key: f"{key}-id" for key in pf.WARP_INPUTS},
        ),
        "semantic_index": dict(
            descriptors=unit(3, 4),
            index=[2, 0, 65535, 1],
            share=[255, 100, 0, 128],
            min_share=128,
        ),
    }


class WriteThenReadTests(TempDir):
    def test_every_kind_round_trips_through_python_and_rust(self) -> None:
        samples = own_samples()
        self.assertEqual(set(samples), set(pf.KINDS))
        for kind, kwargs in samples.items():
            with self.subTest(kind=kind):
                path = self.dir / f"{kind}.safetensors"
                WRITERS[kind](path, **kwargs)
                rec = pf.read_any(path)
                self.assertEqual(rec.KIND, kind)
                self.assertEqual(rec.metadata["generator"], pf.GENERATOR)
                self.assertEqual(rec.metadata["format"], f"profuse.{kind}")
                self.assertEqual(rec.metadata["format_version"], "1.0")
                for name, value in kwargs.items():
                    if name in rec.TENSORS:
                        got = getattr(rec, name)
                        want = np.asarray(value)
                        if want.dtype.kind == "f":
                            want = want.astype(got.dtype)
                        np.testing.assert_array_equal(got, want, err_msg=name)
                data = path.read_bytes()
                header_len = int.from_bytes(data[:8], "little")
                self.assertEqual((8 + header_len) % 8, 0)
                self.assertEqual(self.leftovers(), [])
                if RUST:
                    out = rust_inspect(path)
                    self.assertEqual(out.returncode, 0, out.stderr.decode())
                    report = json.loads(out.stdout)
                    self.assertTrue(report["valid"])
                    self.assertEqual(report["kind"], kind)
                    self.assertEqual(report["counts"], rec.counts())
                    self.assertEqual(report["metadata"], rec.metadata)

    def test_semantic_index_past_65535_proposals_is_u32(self) -> None:
        # SPEC.md 4.17: U32 iff P > 65535; proposal 65535 is then real, u32 max is none.
        p = 65537
        table = np.where(np.arange(p) % 2 == 0, 1.0, -1.0).astype(np.float16)[:, None]
        path = self.dir / "si.safetensors"
        index = np.array([65535, 0, 2**32 - 1, 65536, 7], np.uint32)
        pf.write_semantic_index(
            path, descriptors=table, index=index, share=[255, 128, 0, 200, 1], min_share=128
        )
        rec = pf.read_semantic_index(path)
        self.assertEqual(rec.index.dtype, np.uint32)
        np.testing.assert_array_equal(rec.index, index)
        if RUST:
            out = rust_inspect(path)
            self.assertEqual(out.returncode, 0, out.stderr.decode())
            self.assertEqual(json.loads(out.stdout)["counts"], rec.counts())

    def test_semantic_index_without_share_needs_min_share_0(self) -> None:
        path = self.dir / "si.safetensors"
        kwargs = dict(descriptors=np.eye(3, 4), index=[2, 0, 65535, 1], share=None)
        pf.write_semantic_index(path, min_share=0, **kwargs)
        rec = pf.read_semantic_index(path)
        self.assertIsNone(rec.share)
        np.testing.assert_array_equal(rec.dominant(), [True, True, False, True])
        np.testing.assert_array_equal(rec.shares(), [255, 255, 0, 255])
        self.assertEqual(rec.counts()["gaussians"], 4)
        if RUST:
            out = rust_inspect(path)
            self.assertEqual(out.returncode, 0, out.stderr.decode())
            self.assertEqual(json.loads(out.stdout)["counts"], rec.counts())
        with self.assertRaises(pf.FormatError) as ctx:
            pf.write_semantic_index(path, min_share=1, **kwargs)
        self.assertEqual((ctx.exception.code, ctx.exception.field), ("missing_tensor", "share"))

    def test_fixed_point_words_round_trip(self) -> None:
        values = [0, 1, 2**62, 2**64 - 1, 2**64, 2**128 - 1]
        words = pf.fixed_point_words(values)
        self.assertEqual(words.dtype, np.dtype("<u8"))
        self.assertEqual(words.tolist()[4], [0, 1])
        self.assertEqual(pf.fixed_point(words), values)
        with self.assertRaises(ValueError):
            pf.fixed_point_words([2**128])

    def test_dtype_conversions(self) -> None:
        path = self.dir / "f.safetensors"
        pf.write_features(path, features=np.eye(2), valid=[True, True])
        rec = pf.read_features(path)
        self.assertEqual((rec.features.dtype, rec.valid.dtype), (np.float32, np.uint8))
        pf.write_masks(
            path,
            view_names=["a"],
            labels=np.array([[[0, 4294967295]]], np.int64),
            mask_offsets=[0, 1],
            features=np.eye(1),
        )
        self.assertEqual(pf.read_masks(path).labels.dtype, np.uint32)
        big_endian = np.array([[1.0, 0.0]], ">f4")
        pf.write_features(path, features=big_endian, valid=[1])
        np.testing.assert_array_equal(pf.read_features(path).features, [[1.0, 0.0]])


class BadInputTests(TempDir):
    def assert_refused(self, code: str, field: str | None, write: Any) -> None:
        target = self.dir / "out.safetensors"
        target.write_bytes(b"previous")
        with self.assertRaises(pf.FormatError) as ctx:
            write(target)
        e = ctx.exception
        self.assertEqual((e.code, e.field), (code, field), str(e))
        self.assertEqual(e.path, str(target))
        self.assertIn(str(target), str(e))
        self.assertEqual(target.read_bytes(), b"previous")
        self.assertEqual(self.leftovers(), [])

    def test_value_rules_of_the_reader_apply(self) -> None:
        base = own_samples()

        def with_(kind: str, **changes: Any) -> Any:
            kwargs = {**base[kind], **changes}
            return lambda p: WRITERS[kind](p, **kwargs)

        self.assert_refused("invalid", "features", with_("masks", features=np.ones((3, 8), np.float16)))
        self.assert_refused("out_of_range", "labels", with_("masks", labels=np.full((2, 2, 2), 7, np.uint16)))
        self.assert_refused("shape", "mask_offsets", with_("masks", mask_offsets=[0, 3]))
        self.assert_refused("metadata", "image_names", with_("cameras", image_names="images/0.png"))
        self.assert_refused("invalid", "world_to_camera", with_("cameras", world_to_camera=np.ones((2, 3, 4))))
        self.assert_refused("non_finite", "means", with_("gaussians", means=np.full((5, 3), np.nan)))
        self.assert_refused("metadata", "sh_degree", with_("gaussians", sh_degree=4))
        self.assert_refused("metadata", "coords", with_("matches", coords="meters"))
        self.assert_refused("invalid", "pairs", with_("sparse_matches", pairs=[[0, 1], [0, 1]]))
        self.assert_refused("metadata", "names", with_("prompts", names=["a", "a", "b"]))
        self.assert_refused("out_of_range", "gaussian_ids", with_("selection", gaussian_ids=[3, 0]))
        self.assert_refused("invalid", "weights", with_("topk", weights=np.array([[[0.0, 0.0], [0.0, 0.0]]])))
        self.assert_refused("metadata", "grouping", with_("fuse_partial", grouping="kmeans"))
        self.assert_refused("out_of_range", "w_sums", with_("fuse_partial", w_sums=np.zeros((3, 2), np.uint64)))
        self.assert_refused(
            "missing_tensor", "mask_proposal", with_("fuse_partial", grouping="blend", num_groups=3)
        )

    def test_inputs_are_checked_before_writing(self) -> None:
        base = own_samples()
        masks = base["masks"]
        self.assert_refused(
            "dtype", "labels", lambda p: pf.write_masks(p, **{**masks, "labels": np.zeros((2, 2, 2))})
        )
        self.assert_refused(
            "out_of_range", "mask_offsets", lambda p: pf.write_masks(p, **{**masks, "mask_offsets": [0, -1, 3]})
        )
        self.assert_refused(
            "dtype", "features", lambda p: pf.write_masks(p, **{**masks, "features": [["a", "b"]]})
        )
        self.assert_refused(
            "metadata", "num_views", lambda p: pf.write_matches(p, **{**base["matches"], "num_views": -1})
        )
        self.assert_refused(
            "metadata", "num_views", lambda p: pf.write_matches(p, **{**base["matches"], "num_views": True})
        )

    def test_unknown_kind_and_missing_directory(self) -> None:
        with self.assertRaises(ValueError):
            pf.write_file(self.dir / "x", "splats", {})
        with self.assertRaises(pf.FormatError) as ctx:
            pf.write_prompts(self.dir / "no" / "such.safetensors", **own_samples()["prompts"])
        self.assertEqual(ctx.exception.code, "io")

    def test_only_regular_files_are_replaced(self) -> None:
        """Issue 20 item 5 for the Python writers: a device, FIFO or directory at the output
        path is an ``io`` error naming what is there, and is left as it was (the Rust rule)."""
        # Only special files made here: a regression must not clobber a real device.
        prompts = own_samples()["prompts"]
        fifo = self.dir / "fifo"
        os.mkfifo(fifo)
        folder = self.dir / "folder"
        folder.mkdir()
        sock_path = self.dir / "socket"
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self.addCleanup(sock.close)
        sock.bind(str(sock_path))
        for target, found in ((fifo, "FIFO"), (folder, "directory"), (sock_path, "socket")):
            before = os.stat(target)
            with self.assertRaises(pf.FormatError) as ctx:
                pf.write_prompts(target, **prompts)
            self.assertEqual(ctx.exception.code, "io")
            self.assertIn(f"is a {found}", str(ctx.exception))
            after = os.stat(target)
            self.assertEqual((after.st_mode, after.st_ino), (before.st_mode, before.st_ino))
        self.assertEqual(self.leftovers(), [])
        regular = self.dir / "regular.safetensors"
        regular.write_bytes(b"previous")
        pf.write_prompts(regular, **prompts)
        self.assertEqual(pf.read_prompts(regular).names, prompts["names"])


if __name__ == "__main__":
    unittest.main()
