"""Hostile inputs for the Python reader (issue 20 items 2 and 3).

* Regression tests of item 2: zero-element tensors whose shapes numpy cannot represent
  (a dimension >= 2^63, or non-zero dimensions spanning >= 2^63 bytes) are valid files
  (SPEC.md 2: a dimension may be 0; step 7 multiplies left to right in u64), read without
  ``ValueError``; a topk file with no pixels and K = 2^31 reads at once (a loop per slot
  hung for minutes).
* A property test with seeded mutators (item 3): the golden vectors mutated by byte flips,
  truncation, appended bytes, header-length edits, shape / dtype / offset edits (also
  consistent ones, re-tiled so that they reach the kind checks, and "zero rows, huge D"),
  metadata edits, dropped tensors and deeply nested JSON. Every case must end, within a
  time limit, in a record or a :class:`profuse_formats.FormatError`: nothing else may
  escape. With ``PROFUSE_RUST_INSPECT=/path/to/profuse`` a sample of the cases is also
  inspected by Rust (under a 2 GiB address-space limit), which must print the same bytes
  and exit with the same code.

The mutators are a seeded ``random.Random`` (hypothesis is not among the package's
dependencies), so every run checks the same cases; ``PROFUSE_MUTATION_CASES`` and
``PROFUSE_MUTATION_SEED`` run more or other cases. Standard-library ``unittest`` only:
``python3 formats/python/test_hostile_inputs.py``.
"""

from __future__ import annotations

import contextlib
import json
import os
import random
import resource
import signal
import struct
import subprocess
import sys
import tempfile
import time
import unittest
from pathlib import Path
from typing import Any, Iterator

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

import profuse_formats as pf  # noqa: E402

VECTORS = HERE.parent / "vectors"
RUST = os.environ.get("PROFUSE_RUST_INSPECT")
CASES = int(os.environ.get("PROFUSE_MUTATION_CASES", "2000"))
SEED = int(os.environ.get("PROFUSE_MUTATION_SEED", "20"))
#: One in this many mutated cases is also inspected by Rust.
RUST_EVERY = 8
#: Seconds one case may take in Python (small files: real cases take milliseconds).
CASE_SECONDS = 5.0
#: Address-space limit of the Rust inspector: no allocation may approach 2 GiB.
RUST_MEMORY = 2 << 30

HUGE = [2**31, 2**32, 2**40, 2**61, 2**62, 2**63, 2**64 - 1]


# --------------------------------------------------------------------------------------
# Files, limits, and the two inspectors
# --------------------------------------------------------------------------------------


def build(meta: dict[str, str], tensors: list[tuple[str, str, list[int], bytes]]) -> bytes:
    """A container from metadata and (name, dtype, shape, data) entries laid out in order."""
    header: dict[str, Any] = {"__metadata__": meta}
    body = b""
    for name, dtype, shape, data in tensors:
        header[name] = {"dtype": dtype, "shape": shape, "data_offsets": [len(body), len(body) + len(data)]}
        body += data
    return join(header, body)


def split(data: bytes) -> tuple[dict, bytes] | None:
    """Header and body of a well-formed container, None otherwise."""
    if len(data) < 8:
        return None
    (n,) = struct.unpack("<Q", data[:8])
    try:
        header = json.loads(data[8 : 8 + n])
    except (ValueError, RecursionError):
        return None
    return (header, data[8 + n :]) if isinstance(header, dict) else None


def join(header: Any, body: bytes) -> bytes:
    text = json.dumps(header).encode("utf-8")
    text += b" " * ((-(8 + len(text))) % 8)
    return struct.pack("<Q", len(text)) + text + body


@contextlib.contextmanager
def time_limit(seconds: float) -> Iterator[None]:
    """Raises TimeoutError in the block after ``seconds`` (SIGALRM; POSIX)."""

    def expire(signum: int, frame: Any) -> None:
        raise TimeoutError(f"case took more than {seconds} s")

    previous = signal.signal(signal.SIGALRM, expire)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)


def limit_memory() -> None:  # pragma: no cover - runs in the child
    resource.setrlimit(resource.RLIMIT_AS, (RUST_MEMORY, RUST_MEMORY))


def rust_inspect(path: Path) -> tuple[bytes, int]:
    """``profuse inspect`` under a 2 GiB address-space limit."""
    assert RUST is not None
    out = subprocess.run(
        [os.path.abspath(RUST), "inspect", path.name],
        cwd=path.parent,
        capture_output=True,
        timeout=60,
        preexec_fn=limit_memory,
    )
    return out.stdout, out.returncode


class AgreeMixin:
    def assert_agree(self, path: Path) -> tuple[bytes, int]:
        """Python's verdict (and, with PROFUSE_RUST_INSPECT, Rust's identical one)."""
        with contextlib.chdir(path.parent):
            py = python_inspect_relative(path.name)
        if RUST is not None:
            rs = rust_inspect(path)
            self.assertEqual(rs[0].decode("utf-8", "replace"), py[0].decode("utf-8", "replace"), path.name)  # type: ignore[attr-defined]
            self.assertEqual(rs[1], py[1], f"exit code of {path.name}")  # type: ignore[attr-defined]
        return py


def python_inspect_relative(name: str) -> tuple[bytes, int]:
    """The in-process Python ``inspect`` (the CLI's code path) of a file in the current
    directory, named as Rust names it: stdout bytes and exit code. ``inspect`` catches
    only :class:`pf.FormatError`; anything else escapes to the caller."""
    with time_limit(CASE_SECONDS):
        report, err = pf.inspect(name)
        if err is None:
            getattr(pf, f"read_{report['kind']}")(name)
    return (pf.report_json(report) + "\n").encode("utf-8"), 0 if err is None else 1


def meta(kind: str, **extra: str) -> dict[str, str]:
    return {"format": f"profuse.{kind}", "format_version": "1.0", **extra}


# --------------------------------------------------------------------------------------
# Item 2: zero-element tensors with huge dimensions, and K = 2^31
# --------------------------------------------------------------------------------------


class HugeDimensionTests(AgreeMixin, unittest.TestCase):
    def setUp(self) -> None:
        self._tmp = tempfile.TemporaryDirectory()
        self.dir = Path(self._tmp.name)

    def tearDown(self) -> None:
        self._tmp.cleanup()

    def write(self, name: str, data: bytes) -> Path:
        self.assertLess(len(data), 500)
        path = self.dir / name
        path.write_bytes(data)
        return path

    def test_features_with_zero_rows_and_a_huge_dimension_are_valid(self) -> None:
        """Issue 20 item 2: D = 2^62, 2^63, 2^64 - 1 raised ValueError (numpy cannot shape
        them); D = 2^61 F32 (2^63 bytes per row) too. Valid, D reported, empty arrays."""
        for d in HUGE:
            for dtype in ("F16", "F32"):
                with self.subTest(d=d, dtype=dtype):
                    path = self.write(
                        "f.safetensors",
                        build(meta("features"), [("features", dtype, [0, d], b""), ("valid", "U8", [0], b"")]),
                    )
                    rec = pf.read_features(path)
                    self.assertEqual((rec.dim, len(rec.valid), rec.features.size), (d, 0, 0))
                    self.assertEqual(rec.counts(), {"feature_dim": d, "gaussians": 0, "valid": 0})
                    out, rc = self.assert_agree(path)
                    self.assertEqual(rc, 0)
                    self.assertEqual(json.loads(out)["tensors"]["features"]["shape"], [0, d])

    def test_masks_with_no_masks_or_views_and_huge_dimensions_are_valid(self) -> None:
        """Issue 20 item 2: masks with zero masks and a huge D, and with zero views and an
        H x W plane of 2^80 pixels (its reshape raised ValueError)."""
        cases = [
            ([0, 4, 4], [0, d]) for d in HUGE
        ] + [([0, 2**40, 2**40], [0, 512]), ([0, 2**63, 1], [0, 2**63])]
        for labels, features in cases:
            with self.subTest(labels=labels, features=features):
                path = self.write(
                    "m.safetensors",
                    build(
                        meta("masks", view_names="[]"),
                        [
                            ("mask_offsets", "U32", [1], b"\0\0\0\0"),
                            ("labels", "U32", labels, b""),
                            ("features", "F16", features, b""),
                        ],
                    ),
                )
                rec = pf.read_masks(path)
                self.assertEqual((rec.height, rec.width, rec.dim), (labels[1], labels[2], features[1]))
                self.assertEqual(self.assert_agree(path)[1], 0)

    def test_topk_with_no_pixels_and_a_huge_k_is_valid_and_immediate(self) -> None:
        """Issue 20 item 2: a 300-byte topk file with K = 2^31 hung (> 300 s) in a Python
        loop per slot; K = 2^62 cannot even be shaped by numpy. Valid, read at once."""
        for h, w, k in [(0, 0, 2**31), (1, 0, 2**31), (0, 3, 2**62), (0, 0, 2**64 - 1)]:
            with self.subTest(shape=(h, w, k)):
                path = self.write(
                    "t.safetensors",
                    build(
                        meta("topk", num_gaussians="0"),
                        [
                            ("ids", "U32", [h, w, k], b""),
                            ("weights", "F32", [h, w, k], b""),
                            ("transmittance", "F32", [h, w], b""),
                        ],
                    ),
                )
                start = time.monotonic()
                with time_limit(CASE_SECONDS):
                    rec = pf.read_topk(path)
                self.assertLess(time.monotonic() - start, 1.0)
                self.assertEqual((rec.height, rec.width, rec.k), (h, w, k))
                self.assertEqual(self.assert_agree(path)[1], 0)

    def test_other_kinds_with_empty_tensors_of_huge_shape(self) -> None:
        """Issue 20 item 2 on every kind with a free dimension: prompts, matches, view maps
        valid; pq (M = 0) and fuse_partial (D = 0) the same typed error as in Rust."""
        big = 2**40
        files = {
            "prompts": build(meta("prompts", names="[]"), [("embeddings", "F32", [0, 2**62], b"")]),
            "matches": build(
                meta("matches", num_views="2", coords="pixels"),
                [("pairs", "U32", [0, 2], b""), ("warp", "F32", [0, big, big, 2], b""),
                 ("certainty", "F32", [0, big, big], b"")],
            ),
            "view_maps": build(
                meta("view_maps", view_names="[]", num_objects="0"),
                [("depth", "F32", [0, 2**63, 2**63], b""), ("object_ids", "U32", [0, 2**63, 2**63], b"")],
            ),
            "pq": build(
                meta("pq", metric="inner_product", nbits="8"),
                [("centroids", "F32", [0, 256, 2**62], b""), ("codes", "U8", [0, 0], b""),
                 ("norms", "F32", [0], b""), ("valid", "U8", [0], b"")],
            ),
        }
        expected = {"prompts": None, "matches": None, "view_maps": None, "pq": ("shape", "centroids")}
        for kind, data in files.items():
            with self.subTest(kind=kind):
                path = self.write(f"{kind}.safetensors", data)
                out, rc = self.assert_agree(path)
                err = json.loads(out)["error"]
                want = expected[kind]
                self.assertEqual(None if err is None else (err["code"], err["field"]), want)

    def test_a_shape_whose_u64_product_overflows_is_a_header_error(self) -> None:
        """Left to right, [2^32, 2^32, 0] overflows u64 before the 0: a header error in both
        readers (SPEC.md 2 step 7), while [0, 2^32, 2^32] is a valid empty tensor."""
        for shape, code in [([2**32, 2**32, 0], "header"), ([0, 2**32, 2**32], None)]:
            with self.subTest(shape=shape):
                path = self.write(
                    "v.safetensors",
                    build(meta("view_maps", view_names="[]", num_objects="0"), [("depth", "F32", shape, b"")]),
                )
                out, rc = self.assert_agree(path)
                err = json.loads(out)["error"]
                self.assertEqual(None if err is None else err["code"], code)


# --------------------------------------------------------------------------------------
# Item 3: a property test with mutators
# --------------------------------------------------------------------------------------

INTERESTING = [0, 1, 2, 3, 255, 256, 2**16, 2**31, 2**32, 2**40, 2**61, 2**62, 2**63, 2**64 - 1]
DTYPES = ["BOOL", "U8", "I8", "U16", "I16", "U32", "I32", "U64", "I64", "F16", "BF16", "F32", "F64"]
META_VALUES = [
    "", "0", "1", "2", "+2", "-1", "007", "8", "[]", '["a"]', '["a",""]', '["a","a"]', '["x","y","z"]',
    "normalized", "pixels", "inner_product", "1.0", "1.9", "2.0", "blend", "masks", "proposals",
    "ignore", "singleton", "none", "profuse.mesh", "18446744073709551615", "18446744073709551616",
    "9223372036854775808", "4294967296", '["' + "v" * 300 + '"]',
]
#: Largest tensor a consistent re-shape may create.
MAX_TENSOR_BYTES = 1 << 16


def tensors_of(header: dict) -> list[str]:
    return sorted(
        (n for n, e in header.items() if n != "__metadata__" and isinstance(e, dict)),
        key=lambda n: (str(header[n].get("data_offsets")), n),
    )


def retile(header: dict, body: bytes, data: dict[str, bytes]) -> bytes:
    """Re-lays the tensors out in their current order with ``data`` replacing some tensors'
    bytes (others keep theirs), so that the container is valid again."""
    out = b""
    for name in tensors_of(header):
        entry = header[name]
        chunk = data[name] if name in data else old_bytes(entry, body)
        entry["data_offsets"] = [len(out), len(out) + len(chunk)]
        out += chunk
    return join(header, out)


def old_bytes(entry: dict, body: bytes) -> bytes:
    """The bytes a (possibly mutated) entry's ``data_offsets`` point at, or none."""
    offsets = entry.get("data_offsets")
    if isinstance(offsets, list) and len(offsets) == 2 and all(type(o) is int for o in offsets):
        return body[max(offsets[0], 0) : max(offsets[1], 0)]
    return b""


def nbytes(dtype: str, shape: list[int]) -> int | None:
    size = pf.DTYPE_SIZES.get(dtype) if isinstance(dtype, str) else None
    if size is None or not all(type(d) is int and d >= 0 for d in shape):
        return None
    n = 1
    for d in shape:
        n *= d
        if n > 2**64 - 1:
            return None
    return n * size


def resized(rng: random.Random, old: bytes, n: int) -> bytes:
    """``n`` bytes: the old data repeated or cut, sometimes random."""
    if rng.random() < 0.2:
        return rng.randbytes(n)
    if not old:
        return bytes(n)
    return (old * (n // len(old) + 1))[:n]


def substitute_dims(rng: random.Random, header: dict, body: bytes) -> bytes | None:
    """A consistent edit of named dimensions: every occurrence of one dimension value in
    every shape becomes another (often 0), and sometimes a second value becomes huge, with
    every tensor re-sized and re-tiled ("zero rows, huge D" in files whose other tensors
    agree). None when the result would not be small."""
    names = tensors_of(header)
    values = sorted({d for n in names for d in header[n].get("shape") or [] if isinstance(d, int)})
    if not values:
        return None
    swap = {rng.choice(values): rng.choice([0, 0, 1, 2, 3, 2**32])}
    if rng.random() < 0.7 and len(values) > 1:
        other = rng.choice([v for v in values if v not in swap])
        swap[other] = rng.choice(HUGE + [0])
    data: dict[str, bytes] = {}
    for name in names:
        entry = header[name]
        shape = [swap.get(d, d) if isinstance(d, int) else d for d in entry.get("shape") or []]
        n = nbytes(entry.get("dtype", ""), shape) if all(isinstance(d, int) for d in shape) else None
        if n is None or n > MAX_TENSOR_BYTES:
            return None
        entry["shape"] = shape
        data[name] = resized(rng, old_bytes(entry, body), n)
    m = header.get("__metadata__")
    if isinstance(m, dict) and rng.random() < 0.5:
        # Keep metadata-bound counts (V, Q) in step when they were swapped to 0.
        for key in ("view_names", "image_names", "names"):
            if key in m and 0 in swap.values():
                m[key] = "[]"
    return retile(header, body, data)


def mutate_parsed(rng: random.Random, header: dict, body: bytes) -> bytes:
    """One structured edit of a parsed container."""
    names = tensors_of(header)
    r = rng.random()
    if names and r < 0.15:
        edited = substitute_dims(rng, json.loads(json.dumps(header)), body)
        if edited is not None:
            return edited
    if names and r < 0.35:
        # Consistent re-shape (often "zero rows, huge D"), re-tiled to reach the kind checks.
        name = rng.choice(names)
        entry = header[name]
        shape = list(entry.get("shape") or [])
        if shape and rng.random() < 0.5:
            i = rng.randrange(len(shape))
            shape[i] = 0
            if len(shape) > 1:
                j = rng.choice([k for k in range(len(shape)) if k != i])
                shape[j] = rng.choice(HUGE)
        elif shape:
            i = rng.randrange(len(shape))
            d = shape[i] if isinstance(shape[i], int) else 0
            shape[i] = rng.choice(INTERESTING + [max(0, d + rng.choice([-1, 1]))])
        if rng.random() < 0.2:
            entry["dtype"] = rng.choice(DTYPES)
        n = nbytes(entry.get("dtype", ""), shape)
        if n is None or n > MAX_TENSOR_BYTES:
            entry["shape"] = shape  # an inconsistent entry: a header error
            return join(header, body)
        entry["shape"] = shape
        return retile(header, body, {name: resized(rng, old_bytes(entry, body), n)})
    if names and r < 0.42:
        entry = header[rng.choice(names)]
        which = rng.random()
        if which < 0.4:
            entry["dtype"] = rng.choice(DTYPES + ["f32", "Q8", 3])
        elif which < 0.7 and entry.get("shape"):
            entry["shape"][rng.randrange(len(entry["shape"]))] = rng.choice(
                INTERESTING + [2**64, -1, 1.5, "3", None]
            )
        else:
            offsets = entry.get("data_offsets") or [0, 0]
            k = rng.randrange(2)
            offsets[k] = rng.choice([0, offsets[k] + 1, max(0, offsets[k] - 1), 2**63, 2**64 - 1, 2**64, -1])
            if rng.random() < 0.2:
                offsets = offsets[::-1] if rng.random() < 0.5 else offsets + [0]
            entry["data_offsets"] = offsets
        return join(header, body)
    if r < 0.62:
        m = header.setdefault("__metadata__", {})
        if not isinstance(m, dict):
            return join(header, body)
        key = rng.choice(sorted(m) + ["format", "format_version", "num_views", "names"])
        if rng.random() < 0.15:
            m.pop(key, None)
        elif rng.random() < 0.1:
            m[key] = rng.choice([1, None, ["a"], {"x": "y"}])
        else:
            m[key] = rng.choice(META_VALUES + [str(m.get(key, "")) + "0"])
        return join(header, body)
    if names and r < 0.72:
        drop = rng.choice(names)
        del header[drop]
        return retile(header, body, {})
    if r < 0.78:
        # Deep nesting: both JSON parsers must refuse it as a header error, not crash.
        depth = rng.choice([64, 127, 128, 129, 200, 3000, 100000])
        header["__deep__"] = json.loads("[" * min(depth, 500) + "]" * min(depth, 500)) if depth <= 500 else None
        text = json.dumps(header)
        if depth > 500:
            text = text.replace('"__deep__": null', '"__deep__": ' + "[" * depth + "]" * depth)
        raw = text.encode()
        raw += b" " * ((-(8 + len(raw))) % 8)
        return struct.pack("<Q", len(raw)) + raw + body
    if names and r < 0.86:
        # A tensor added at the end (an extra tensor, possibly of a known name or odd dtype).
        name = rng.choice(["extra", "valid", "weight_sum", "class_ids", "mask_proposal", "confidence"])
        dtype = rng.choice(DTYPES)
        shape = rng.choice([[0], [1], [2, 3], [0, 2**62], [5]])
        n = nbytes(dtype, shape) or 0
        end = max((header[k]["data_offsets"][1] for k in names if isinstance(header[k].get("data_offsets"), list)), default=0)
        header[name] = {"dtype": dtype, "shape": shape, "data_offsets": [end, end + n]}
        return retile(header, body, {name: resized(rng, b"", n)})
    text = json.dumps(header)
    pos = rng.randrange(len(text) + 1)
    text = text[:pos] + rng.choice(['"', ",", "}", "{", "]", "\\", "\u00e9", "\ud800", "1e999", "-0", " "]) + text[pos:]
    raw = text.encode("utf-8", "surrogatepass")
    return struct.pack("<Q", len(raw)) + raw + body


def mutate_raw(rng: random.Random, data: bytes) -> bytes:
    """One byte-level edit: flips, truncation, appended bytes, a new header length."""
    r = rng.random()
    b = bytearray(data)
    if r < 0.4 and b:
        for _ in range(rng.randint(1, 4)):
            i = rng.randrange(len(b))
            b[i] = b[i] ^ (1 << rng.randrange(8)) if rng.random() < 0.5 else rng.randrange(256)
        return bytes(b)
    if r < 0.65:
        return bytes(b[: rng.randrange(len(b) + 1)])
    if r < 0.8:
        return bytes(b) + rng.randbytes(rng.choice([1, 7, 8, 64]))
    n = rng.choice([0, 1, 7, max(0, len(b) - 8), len(b) - 7, 100_000_000, 100_000_001, 2**63, 2**64 - 1])
    return struct.pack("<Q", n % 2**64) + bytes(b[8:])


def mutate(rng: random.Random, data: bytes) -> bytes:
    """One to three edits, structured when the file still parses."""
    for _ in range(rng.choice([1, 1, 2, 3])):
        parsed = split(data)
        if parsed is not None and rng.random() < 0.7:
            data = mutate_parsed(rng, *parsed)
        else:
            data = mutate_raw(rng, data)
    return data


class MutationPropertyTests(AgreeMixin, unittest.TestCase):
    def test_mutated_vectors_give_a_record_or_a_format_error_in_time(self) -> None:
        """Issue 20 item 3: every mutated golden vector gives a verdict within
        CASE_SECONDS, only ever a FormatError (never another exception or a hang), and on a
        sample (one in RUST_EVERY) the same report and exit code as Rust."""
        rng = random.Random(SEED)
        sources = sorted((VECTORS / "valid").glob("*.safetensors")) + sorted(
            (VECTORS / "invalid").glob("*.safetensors")
        )[::6]
        corpus = [p.read_bytes() for p in sources]
        outcomes = {"valid": 0, "invalid": 0, "rust_checked": 0}
        with tempfile.TemporaryDirectory() as tmp:
            for i in range(CASES):
                data = mutate(rng, rng.choice(corpus))
                path = Path(tmp) / f"case{i}.safetensors"
                path.write_bytes(data)
                try:
                    if RUST is not None and i % RUST_EVERY == 0:
                        _, rc = self.assert_agree(path)
                        outcomes["rust_checked"] += 1
                    else:
                        with contextlib.chdir(tmp):
                            _, rc = python_inspect_relative(path.name)
                except pf.FormatError:  # pragma: no cover - inspect catches these
                    raise
                except AssertionError:
                    self._keep(path, data)
                    raise
                except BaseException as e:  # noqa: BLE001 - anything else is the bug
                    self._keep(path, data)
                    self.fail(f"case {i}: {type(e).__name__}: {e}")
                outcomes["valid" if rc == 0 else "invalid"] += 1
        # The mutators reach both verdicts (a test that only saw header errors would be weak).
        self.assertGreater(outcomes["valid"], CASES // 50, outcomes)
        self.assertGreater(outcomes["invalid"], CASES // 2, outcomes)
        print(f"mutation outcomes: {outcomes}", file=sys.stderr)

    @staticmethod
    def _keep(path: Path, data: bytes) -> None:
        keep = Path(tempfile.gettempdir()) / f"profuse-mutation-{SEED}-{path.name}"
        keep.write_bytes(data)
        print(f"reproducer kept at {keep}", file=sys.stderr)


class SpecialFileTests(unittest.TestCase):
    def test_a_fifo_or_folder_is_refused_instead_of_blocking(self) -> None:
        """A FIFO would block open() forever: refused at once, like a folder (the Rust
        reader's rule and wording)."""
        with tempfile.TemporaryDirectory() as d:
            fifo = Path(d) / "g.safetensors"
            os.mkfifo(fifo)
            for path in (fifo, Path(d)):
                with self.assertRaises(pf.FormatError) as e:
                    pf.read_gaussians(path)
                self.assertEqual(e.exception.code, "io")
                self.assertIn("not a regular file", str(e.exception))


if __name__ == "__main__":
    unittest.main()

