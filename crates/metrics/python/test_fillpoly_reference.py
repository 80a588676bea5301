"""Our LERF ground-truth rasteriser agrees with the reference evaluation pixel for pixel.

LangSplat's ``eval/utils.py::polygon_to_mask`` (used by OpenGaussian and Dr. Splat for
LERF-OVS) does::

    points = np.asarray(points_list, dtype=np.int32)
    mask = np.zeros(img_shape, dtype=np.uint8)
    cv2.fillPoly(mask, [points], 1)

``reference_mask`` below is that function verbatim in behaviour. The test generates
thousands of random polygons (convex, concave, self-intersecting, degenerate, partly and
fully outside the image, tiny, huge, with fractional, negative and x.5 coordinates),
rasterises them with OpenCV and with ``metrics rasterize`` (the Rust implementation,
``profuse_metrics::mask::rasterize_polygon``) and compares every mask pixel for pixel.

OpenCV generations: 4.11 and later (checked: 4.12.0, 5.0.0) are compared with
``metrics rasterize --opencv current`` (the rule ``metrics lerf`` uses), 4.7 and earlier
(checked: 4.7.0) with ``--opencv legacy``; the two differ only for polygons with vertices
outside the image. OpenCV 4.8-4.10 rounded the right end of fill spans (a regression fixed
by OpenCV PR #26187 in 4.11): their random comparison is skipped.

Run: ``PROFUSE_RUST_METRICS=target/debug/metrics python3 test_fillpoly_reference.py``
(the Rust test ``metrics::fillpoly_agrees_with_opencv`` in tests/e2e does this). Without
``PROFUSE_RUST_METRICS`` the comparison is skipped. Needs numpy and
opencv-python-headless (``pip install -r crates/metrics/python/requirements.txt``).
``PROFUSE_FILLPOLY_CASES`` overrides the number of random polygons (default 6000).
"""

from __future__ import annotations

import json
import math
import os
import random
import subprocess
import tempfile
import unittest
from pathlib import Path

import cv2
import numpy as np

RUST = os.environ.get("PROFUSE_RUST_METRICS")
CASES = int(os.environ.get("PROFUSE_FILLPOLY_CASES", "6000"))
CV_VERSION = tuple(int(p) for p in cv2.__version__.split(".")[:2])
# The fill rule of the installed OpenCV: see the module docstring.
VARIANT = "legacy" if CV_VERSION < (4, 8) else "current"
REGRESSED = (4, 8) <= CV_VERSION < (4, 11)


def reference_mask(width: int, height: int, points_list) -> np.ndarray:
    """LangSplat's polygon_to_mask((h, w), points_list), as a boolean array."""
    points = np.asarray(points_list, dtype=np.int32)
    mask = np.zeros((height, width), dtype=np.uint8)
    cv2.fillPoly(mask, [points], 1)
    return mask.astype(bool)


def rust_masks(cases: list[dict]) -> list[np.ndarray]:
    """Runs ``metrics rasterize`` on the cases and rebuilds each mask from its row runs."""
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "polygons.json"
        path.write_text(json.dumps({"cases": cases}))
        out = subprocess.run(
            [str(RUST), "--quiet", "rasterize", "--polygons", str(path), "--opencv", VARIANT],
            capture_output=True,
            text=True,
            check=False,
        )
    if out.returncode != 0:
        raise AssertionError(f"metrics rasterize failed: {out.stderr}")
    report = json.loads(out.stdout)
    masks = []
    for case, m in zip(cases, report["masks"]):
        mask = np.zeros((case["height"], case["width"]), dtype=bool)
        for y, x0, x1 in m["runs"]:
            mask[y, x0:x1] = True
        assert int(mask.sum()) == m["pixels"]
        masks.append(mask)
    assert len(masks) == len(cases)
    return masks


def _coord(rng: random.Random, lo: float, hi: float, style: str) -> float:
    v = rng.uniform(lo, hi)
    if style == "int":
        return float(round(v))
    if style == "half":
        # x.5 values, negative ones included: truncation toward zero, not floor.
        return math.floor(v) + 0.5
    return v


def random_case(rng: random.Random, k: int) -> dict:
    kind = k % 10
    w = rng.choice([1, 2, 3, 5, 8, 13, 17, 32, 40, 64, 97])
    h = rng.choice([1, 2, 3, 5, 8, 13, 17, 32, 40, 64, 71])
    style = rng.choice(["int", "float", "half"])
    c = lambda lo, hi: _coord(rng, lo, hi, style)  # noqa: E731
    if kind == 0:  # convex: a jittered regular polygon
        n = rng.randint(3, 12)
        cx, cy = c(-5, w + 5), c(-5, h + 5)
        r = rng.uniform(0.5, max(w, h))
        a0 = rng.uniform(0, math.tau)
        pts = [
            [cx + r * math.cos(a0 + i * math.tau / n), cy + r * math.sin(a0 + i * math.tau / n)]
            for i in range(n)
        ]
    elif kind == 1:  # concave: a star
        n = rng.randint(3, 9)
        cx, cy = c(0, w), c(0, h)
        r = rng.uniform(1, max(w, h))
        pts = []
        for i in range(2 * n):
            rr = r if i % 2 == 0 else r * rng.uniform(0.1, 0.6)
            a = i * math.pi / n
            pts.append([cx + rr * math.cos(a), cy + rr * math.sin(a)])
    elif kind in (2, 3):  # self-intersecting: random vertices around the image
        n = rng.randint(3, 16)
        pts = [[c(-0.5 * w, 1.5 * w), c(-0.5 * h, 1.5 * h)] for _ in range(n)]
    elif kind == 4:  # degenerate: collinear, repeated vertices, 1 or 2 vertices, zero area
        choice = rng.randint(0, 4)
        if choice == 0:
            x0, y0, dx, dy = c(-3, w + 3), c(-3, h + 3), c(-6, 6), c(-6, 6)
            pts = [[x0 + t * dx, y0 + t * dy] for t in range(rng.randint(2, 6))]
        elif choice == 1:
            p = [c(-2, w + 2), c(-2, h + 2)]
            pts = [list(p) for _ in range(rng.randint(1, 5))]
        elif choice == 2:
            pts = [[c(-2, w + 2), c(-2, h + 2)] for _ in range(rng.randint(1, 2))]
        elif choice == 3:  # a horizontal or vertical sliver
            x0, y0 = c(-2, w + 2), c(-2, h + 2)
            if rng.random() < 0.5:
                pts = [[x0, y0], [x0 + c(0, w), y0], [x0 + c(0, w), y0]]
            else:
                pts = [[x0, y0], [x0, y0 + c(0, h)], [x0, y0 + c(0, h)]]
        else:  # repeated vertices inside a normal polygon
            base = [[c(0, w), c(0, h)] for _ in range(rng.randint(3, 6))]
            pts = []
            for p in base:
                pts.extend([list(p)] * rng.randint(1, 3))
    elif kind == 5:  # partly outside: vertices far around the image
        n = rng.randint(3, 8)
        pts = [[c(-3 * w, 4 * w), c(-3 * h, 4 * h)] for _ in range(n)]
    elif kind == 6:  # fully outside on one side
        n = rng.randint(3, 8)
        side = rng.randint(0, 3)
        pts = []
        for _ in range(n):
            x, y = c(-2 * w, 3 * w), c(-2 * h, 3 * h)
            if side == 0:
                x = -1 - abs(c(0, 2 * w))
            elif side == 1:
                x = w + abs(c(0, 2 * w))
            elif side == 2:
                y = -1 - abs(c(0, 2 * h))
            else:
                y = h + abs(c(0, 2 * h))
            pts.append([x, y])
    elif kind == 7:  # tiny: inside a pixel or two
        x0, y0 = rng.uniform(-1, w + 1), rng.uniform(-1, h + 1)
        pts = [[x0 + rng.uniform(-1.5, 1.5), y0 + rng.uniform(-1.5, 1.5)] for _ in range(rng.randint(3, 6))]
    elif kind == 8:  # huge: coordinates far beyond the image, up to 1e6
        n = rng.randint(3, 8)
        s = rng.choice([1e2, 1e4, 1e6])
        pts = [[c(-s, s), c(-s, s)] for _ in range(n)]
    else:  # a label-like polygon: many vertices on a wobbly closed curve, fractional
        n = rng.randint(10, 60)
        cx, cy = rng.uniform(0, w), rng.uniform(0, h)
        r = rng.uniform(1, max(w, h) / 1.5)
        ph = rng.uniform(0, math.tau)
        pts = []
        for i in range(n):
            a = i * math.tau / n
            rr = r * (1 + 0.35 * math.sin(3 * a + ph))
            pts.append([cx + rr * math.cos(a) + rng.uniform(-0.6, 0.6), cy + rr * math.sin(a) + rng.uniform(-0.6, 0.6)])
    return {"width": w, "height": h, "polygon": pts}


def hand_cases() -> list[dict]:
    """Cases worth pinning by name: the shapes of the Rust unit tests and corner cases."""
    return [
        {"width": 6, "height": 6, "polygon": [[0, 0], [4, 0], [0, 4]]},
        {"width": 6, "height": 5, "polygon": [[1, 1], [4, 1], [4, 3], [1, 3]]},
        {"width": 4, "height": 4, "polygon": [[-5, -5], [-1, -5], [-1, -1]]},
        {"width": 4, "height": 3, "polygon": [[-9, -9], [9, -9], [9, 9], [-9, 9]]},
        {"width": 5, "height": 5, "polygon": [[-0.5, -0.5], [2.5, -1.5], [3.9, 3.9], [-1.9, 2.5]]},
        # OpenCV issue #26130: 4.8-4.10 fill two pixels beyond this quad's outline.
        {"width": 50, "height": 50, "polygon": [[44, 27], [7, 37], [7, 19], [38, 19]]},
        {"width": 9, "height": 9, "polygon": [[4, 4]]},
        {"width": 9, "height": 9, "polygon": [[1, 1], [7, 5]]},
        {"width": 9, "height": 9, "polygon": [[0, 0], [8, 8], [8, 0], [0, 8]]},
    ]


@unittest.skipUnless(RUST, "set PROFUSE_RUST_METRICS to the `metrics` binary to compare")
class FillPolyAgreement(unittest.TestCase):
    def check(self, cases: list[dict]) -> None:
        ours = rust_masks(cases)
        bad = []
        for i, (case, mine) in enumerate(zip(cases, ours)):
            ref = reference_mask(case["width"], case["height"], case["polygon"])
            if not np.array_equal(ref, mine):
                bad.append((i, case, int((ref != mine).sum())))
        if bad:
            i, case, n = bad[0]
            ref = reference_mask(case["width"], case["height"], case["polygon"])
            self.fail(
                f"{len(bad)} of {len(cases)} masks differ; first: case {i} ({n} pixels) "
                f"{json.dumps(case)}\nopencv:\n{ref.astype(int)}\nours:\n{ours[i].astype(int)}"
            )

    def test_hand_cases(self) -> None:
        self.check(hand_cases()[:5] + hand_cases()[6:] if REGRESSED else hand_cases())

    @unittest.skipIf(REGRESSED, f"OpenCV {cv2.__version__} rounds span ends (fixed in 4.11)")
    def test_random_polygons(self) -> None:
        rng = random.Random(20240916)
        cases = [random_case(rng, k) for k in range(CASES)]
        self.check(cases)
        print(f"\n{len(cases)} random polygons agree with cv2.fillPoly {cv2.__version__} ({VARIANT})")


class TruncationToInt32(unittest.TestCase):
    """The reference's float -> int32 conversion truncates toward zero (not floor, not
    round): the rule `reference_vertices` implements."""

    def test_numpy_truncates_toward_zero(self) -> None:
        got = np.asarray([[2.9, -0.5], [-1.5, 3.5], [-2.9999, 0.0]], dtype=np.int32)
        self.assertEqual(got.tolist(), [[2, 0], [-1, 3], [-2, 0]])


if __name__ == "__main__":
    unittest.main(verbosity=1)
