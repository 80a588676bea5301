#!/usr/bin/env python3
"""Builds the seed corpus of every fuzz target into fuzz/corpus/<target>/ (not committed).

Seeds come from the golden vectors (formats/vectors) and from small cuts of the shared
real data (../shared/data, when present: the fox transforms.json and XFeat matches, the
guitar splat PLY, the ScanNet arrays), plus small files made here for the formats that
have no sample in either (COLMAP text and binary, LangSplat, PLY variants). Every seed is
kept small (< 64 KiB): large seeds only slow the fuzzer down.

    python3 fuzz/build_corpus.py [--shared PATH]     (needs numpy)
"""

from __future__ import annotations

import argparse
import io
import json
import struct
import zipfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
VECTORS = ROOT / "formats" / "vectors"
OUT = ROOT / "fuzz" / "corpus"
KINDS = [
    "cameras", "gaussians", "masks", "matches", "sparse_matches", "proposals", "features", "pq",
    "prompts", "selection", "vertex_labels", "mesh", "view_maps", "topk", "fuse_partial",
    "semantic_index", "warp_partial",
]


def npy_bytes(arr: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, arr, allow_pickle=False)
    return buf.getvalue()


def npz_bytes(arrays: dict[str, np.ndarray], compressed: bool) -> bytes:
    buf = io.BytesIO()
    (np.savez_compressed if compressed else np.savez)(buf, **arrays)
    return buf.getvalue()


def seeds_formats(out: dict[str, dict[str, bytes]]) -> None:
    for p in sorted(VECTORS.glob("*/*.safetensors")):
        out["formats_container"][f"{p.parent.name}_{p.stem}"] = p.read_bytes()
    for p in sorted((VECTORS / "valid").glob("*.safetensors")):
        kind = next(k for k in sorted(KINDS, key=len, reverse=True) if p.stem.startswith(k))
        out["formats_kinds"][p.stem] = bytes([KINDS.index(kind)]) + p.read_bytes()
    for p in sorted((VECTORS / "gt").glob("*/*.json")):
        out["formats_gt"][f"{p.parent.name}_{p.stem}"] = p.read_bytes()


def seeds_npy(out: dict[str, dict[str, bytes]], shared: Path) -> None:
    rng = np.random.default_rng(0)
    arrays = {
        "f32_2d": rng.normal(size=(4, 3)).astype("<f4"),
        "f64_1d": np.arange(5, dtype="<f8"),
        "f16_3d": np.ones((2, 2, 2), "<f2"),
        "u8": np.arange(6, dtype=np.uint8).reshape(2, 3),
        "i32_fortran": np.asfortranarray(np.arange(6, dtype="<i4").reshape(2, 3)),
        "u32_be": np.arange(4, dtype=">u4"),
        "bool": np.array([True, False]),
        "empty": np.zeros((0, 3), "<f4"),
        "scalar": np.array(3.5, "<f4"),
    }
    for name, arr in arrays.items():
        out["npy"][name] = npy_bytes(arr)
    scannet = shared / "scannet" / "scene0000_00"
    for p in sorted(scannet.glob("*.npy")):
        out["npy"][f"scannet_{p.stem}"] = npy_bytes(np.load(p)[:16])
    out["npz"]["stored"] = npz_bytes({"a": arrays["f32_2d"], "b": arrays["u8"]}, False)
    out["npz"]["deflated"] = npz_bytes({"kpts_i": arrays["f32_2d"][:, :2]}, True)
    for p in sorted((shared / "fox" / "matches_xfeat").glob("*.npz"))[:3]:
        with np.load(p) as z:
            out["npz"][f"fox_{p.stem}"] = npz_bytes({k: z[k][:24] for k in z.files}, p.stem.endswith("2"))
    garden = shared / "garden" / "test_garden.npz"
    if garden.exists():
        with np.load(garden) as z:
            out["npz"]["garden"] = npz_bytes({k: z[k][:8] if z[k].ndim else z[k] for k in z.files}, False)


def ply_binary(names: list[str], rows: np.ndarray, extra_header: str = "") -> bytes:
    head = "ply\nformat binary_little_endian 1.0\n" + extra_header
    head += f"element vertex {rows.shape[0]}\n" + "".join(f"property float {n}\n" for n in names)
    return (head + "end_header\n").encode() + rows.astype("<f4").tobytes()


def seeds_ply(out: dict[str, dict[str, bytes]], shared: Path) -> None:
    inria = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2"] + [f"f_rest_{i}" for i in range(9)]
    inria += ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    rows = np.random.default_rng(1).normal(size=(3, len(inria)))
    out["ply"]["inria_degree1"] = ply_binary(inria, rows, "comment made by build_corpus\n")
    out["ply"]["ascii_mesh"] = (
        b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
        b"property float z\nproperty uchar red\nproperty uchar green\nproperty uchar blue\n"
        b"property ushort label\nelement face 1\nproperty list uchar int vertex_indices\n"
        b"end_header\n0 0 0 255 0 0 1\n1 0 0 0 255 0 2\n0 1 0 0 0 255 0\n3 0 1 2\n"
    )
    guitar = shared / "splats" / "guitar.ply"
    if guitar.exists():
        data = guitar.read_bytes()
        end = data.index(b"end_header\n") + len(b"end_header\n")
        header = data[:end].replace(b"element vertex 90854", b"element vertex 12")
        out["ply"]["guitar_12"] = header + data[end : end + 12 * 14 * 4]


def colmap_seed(cameras: bytes, images: bytes, points: bytes) -> bytes:
    return struct.pack("<HH", len(cameras), len(images)) + cameras + images + points


def seeds_colmap(out: dict[str, dict[str, bytes]]) -> None:
    cams = b"# Camera list\n1 PINHOLE 64 48 50 50 32 24\n2 OPENCV 64 48 50 50 32 24 -0.01 0.001 0 0\n"
    imgs = (
        b"# Image list\n1 1 0 0 0 0 0 4 1 a.png\n10 20 -1\n"
        b"2 0.7071 0 0.7071 0 1 0 4 2 b.png\n\n"
    )
    pts = b"# 3D points\n1 0 0 0 255 0 0 0.5 1 0\n2 1 1 1 0 255 0 0.1 2 0\n"
    out["colmap_text"]["two_views"] = colmap_seed(cams, imgs, pts)
    out["colmap_text"]["simple_radial"] = colmap_seed(
        b"1 SIMPLE_RADIAL 64 48 50 32 24 0.01\n", b"1 1 0 0 0 0 0 0 1 x.jpg\n\n", b""
    )
    # Binary: cameras (count, then id, model id, width, height, params as f64).
    bcams = struct.pack("<Q", 2)
    bcams += struct.pack("<iiQQ", 1, 1, 64, 48) + struct.pack("<4d", 50, 50, 32, 24)
    bcams += struct.pack("<iiQQ", 2, 4, 64, 48) + struct.pack("<8d", 50, 50, 32, 24, -0.01, 0.001, 0, 0)
    bimgs = struct.pack("<Q", 2)
    for image_id, cam, name in [(1, 1, b"a.png"), (2, 2, b"b.png")]:
        bimgs += struct.pack("<i4d3di", image_id, 1, 0, 0, 0, 0, 0, 4, cam) + name + b"\0"
        bimgs += struct.pack("<Q", 1) + struct.pack("<ddq", 10.0, 20.0, -1)
    bpts = struct.pack("<Q", 1)
    bpts += struct.pack("<Q3d3Bd", 1, 0.0, 0.0, 0.0, 255, 0, 0, 0.5)
    bpts += struct.pack("<Q", 2) + struct.pack("<ii", 1, 0) + struct.pack("<ii", 2, 0)
    out["colmap_binary"]["two_views"] = colmap_seed(bcams, bimgs, bpts)


def seeds_json(out: dict[str, dict[str, bytes]], shared: Path) -> None:
    fox = shared / "fox" / "transforms.json"
    if fox.exists():
        j = json.loads(fox.read_text())
        j["frames"] = j["frames"][:3]
        out["transforms"]["fox_3"] = json.dumps(j).encode()
    out["transforms"]["per_frame"] = json.dumps(
        {
            "frames": [
                {
                    "file_path": "images/a.png", "w": 64, "h": 48, "fl_x": 50, "fl_y": 50,
                    "cx": 32, "cy": 24, "k1": 0.01,
                    "transform_matrix": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 4], [0, 0, 0, 1]],
                }
            ]
        }
    ).encode()
    out["transforms"]["camera_angle"] = json.dumps(
        {
            "camera_angle_x": 0.69, "w": 64, "h": 48,
            "frames": [{"file_path": "./a", "transform_matrix": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 4], [0, 0, 0, 1]]}],
        }
    ).encode()


def seeds_importers(out: dict[str, dict[str, bytes]], shared: Path) -> None:
    rng = np.random.default_rng(2)
    k = (rng.random(size=(6, 2)) * [63, 47]).astype("<f4")
    out["keypoints"]["six"] = npz_bytes({"kpts_i": k, "kpts_j": k[::-1].copy()}, False)
    out["keypoints"]["deflated"] = npz_bytes({"kpts_i": k, "kpts_j": k}, True)
    for p in sorted((shared / "fox" / "matches_xfeat").glob("*.npz"))[:2]:
        with np.load(p) as z:
            out["keypoints"][f"fox_{p.stem}"] = npz_bytes({n: z[n][:32] for n in z.files}, False)
    seg = np.full((4, 6, 8), -1, "<i4")
    seg[0, :3] = 0
    seg[0, 3:] = 1
    seg[1, :, :4] = 2
    seg[2] = 3
    feats = rng.normal(size=(4, 8)).astype("<f2")
    for level in range(4):
        s, f = npy_bytes(seg), npy_bytes(feats)
        out["langsplat"][f"level{level}"] = bytes([level]) + struct.pack("<H", len(s)) + s + f
    s, f = npy_bytes(seg.astype("<i8")), npy_bytes(feats.astype("<f4"))
    out["langsplat"]["i64_f32"] = bytes([0]) + struct.pack("<H", len(s)) + s + f


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--shared", type=Path, default=ROOT.parent / "shared" / "data")
    args = parser.parse_args()
    targets = [
        "formats_container", "formats_kinds", "formats_gt", "npy", "npz", "ply", "colmap_text",
        "colmap_binary", "transforms", "keypoints", "langsplat",
    ]
    out: dict[str, dict[str, bytes]] = {t: {} for t in targets}
    seeds_formats(out)
    seeds_npy(out, args.shared)
    seeds_ply(out, args.shared)
    seeds_colmap(out)
    seeds_json(out, args.shared)
    seeds_importers(out, args.shared)
    for target, seeds in out.items():
        # Seeds are (re)written by name; inputs the fuzzer added to the directory stay.
        d = OUT / target
        d.mkdir(parents=True, exist_ok=True)
        for name, data in seeds.items():
            assert len(data) < 64 * 1024, (target, name, len(data))
            (d / name).write_bytes(data)
        print(f"{target}: {len(seeds)} seeds")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
