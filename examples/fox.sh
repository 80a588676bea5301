#!/usr/bin/env bash
# Triangulate the real fox scene from real XFeat keypoint matches and check the Gaussians
# against photos of views that took no part in the triangulation.
#
#   examples/fox.sh SHARED_FOX_DIR OUT_DIR
#
# SHARED_FOX_DIR holds transforms.json, images/ and matches_xfeat/ (see its README).
# Steps, each a plumbing tool of this workspace:
#   1. scene-io transforms   transforms.json -> cameras with OpenCV lens (k1 k2 p1 p2)
#   2. scene-io undistort    photos -> pinhole photos + pinhole cameras, cut (--crop) to the
#                            largest rectangle with no black border, the principal point
#                            moved with the cut
#   3. scene-io keypoints    XFeat .npz pairs -> undistorted sparse matches in the cut
#                            cameras' pixels, leaving out every pair that touches a
#                            held-out view
#   4. gs-init run           triangulate, gate (reprojection in both views, behind camera,
#                            triangulation angle), initialise Gaussians (σ = 3 reference
#                            pixels at the point's depth: k-NN scales let the few far-off
#                            points that survive the gates blow up into screen-filling blobs)
#   5. splat-raster render   the three held-out views, side by side with their photos
#   6. (optional, FOX_REFINE_ITERS=N) gs-refine run: N iterations of photometric refinement
#      on the other views at FOX_REFINE_SCALE (default 0.5) of the photos, then gs-refine
#      eval of the held-out views at half resolution, before and after refinement
#      (PSNR over every pixel, coverage = alpha > 0.5); PNGs in OUT/heldout_refined/;
#      FOX_REFINE_ARGS adds options to gs-refine run (e.g. "--densify-until 1500")
# Prints one JSON object: gaussians, median_reproj_px, rejected_frac, heldout_psnr,
# heldout_coverage, plus the per-view figures and the rejection counts.
set -euo pipefail

if [[ $# -ne 2 ]]; then
    echo "usage: $0 SHARED_FOX_DIR OUT_DIR" >&2
    exit 2
fi
FOX=$1
OUT=$2
# Views held out of triangulation: spread over the capture (0-based indices into the
# imported cameras; their image stems are looked up below).
HELDOUT=(${FOX_HELDOUT:-10 25 40})
here=$(cd "$(dirname "$0")/.." && pwd)
# PROFUSE_BIN_DIR: use already built tools (the test suite passes its own); else build them.
if [[ -n ${PROFUSE_BIN_DIR:-} ]]; then
    bin=$PROFUSE_BIN_DIR
else
    cargo build --quiet --release --manifest-path "$here/Cargo.toml" -p profuse-tools \
        --bin scene-io --bin gs-init --bin splat-raster --bin gs-refine >&2
    bin=$here/target/release
fi

mkdir -p "$OUT"
"$bin/scene-io" --quiet transforms "$FOX/transforms.json" --out "$OUT/cameras_distorted.safetensors" >/dev/null
"$bin/scene-io" --quiet undistort --cameras "$OUT/cameras_distorted.safetensors" \
    --scene-dir "$FOX" --out-dir "$OUT/scene" --crop >"$OUT/undistort.json"

# Image stems of the held-out views, from the imported cameras (read with the project's
# Python reader, formats/python).
stems=$(PYTHONPATH="$here/formats/python${PYTHONPATH:+:$PYTHONPATH}" \
    python3 - "$OUT/scene/cameras.safetensors" "${HELDOUT[@]}" <<'EOF'
import pathlib, sys
import profuse_formats as pf
names = pf.read_cameras(sys.argv[1]).image_names
print(" ".join(pathlib.Path(names[int(v)]).stem for v in sys.argv[2:]))
EOF
)
read -r -a held_stems <<<"$stems"

pairs=()
for f in "$FOX"/matches_xfeat/*.npz; do
    name=$(basename "$f" .npz)
    keep=1
    for s in "${held_stems[@]}"; do
        [[ $name == "${s}_"* || $name == *"_${s}" ]] && keep=0
    done
    [[ $keep == 1 ]] && pairs+=("$f")
done
"$bin/scene-io" --quiet keypoints "${pairs[@]}" --cameras "$OUT/cameras_distorted.safetensors" \
    --pinhole-cameras "$OUT/scene/cameras.safetensors" --out "$OUT/scene/sparse_matches.safetensors" >"$OUT/keypoints.json"

"$bin/gs-init" --quiet run --cameras "$OUT/scene/cameras.safetensors" --images "$OUT/scene" \
    --sparse-matches "$OUT/scene/sparse_matches.safetensors" --scale pixels:3 \
    --out "$OUT/gaussians.safetensors" >"$OUT/gs_init.json"

mkdir -p "$OUT/heldout"
for i in "${!HELDOUT[@]}"; do
    v=${HELDOUT[$i]}
    "$bin/splat-raster" --quiet render "$OUT/gaussians.safetensors" \
        --cameras "$OUT/scene/cameras.safetensors" --view "$v" \
        --photo "$OUT/scene/images/${held_stems[$i]}.png" \
        --out-dir "$OUT/heldout" >"$OUT/heldout/view_$v.json"
done

if [[ -n ${FOX_REFINE_ITERS:-} ]]; then
    excl=$(IFS=,; echo "${HELDOUT[*]}")
    common=(--cameras "$OUT/scene/cameras.safetensors" --images "$OUT/scene")
    "$bin/gs-refine" --quiet eval --gaussians "$OUT/gaussians.safetensors" "${common[@]}" \
        --views "$excl" --scale 0.5 >"$OUT/heldout_init_half.json"
    "$bin/gs-refine" --quiet run --gaussians "$OUT/gaussians.safetensors" "${common[@]}" \
        --exclude "$excl" --iterations "$FOX_REFINE_ITERS" --scale "${FOX_REFINE_SCALE:-0.5}" \
        ${FOX_REFINE_ARGS:-} --out "$OUT/gaussians_refined.safetensors" >"$OUT/gs_refine.json"
    "$bin/gs-refine" --quiet eval --gaussians "$OUT/gaussians_refined.safetensors" "${common[@]}" \
        --views "$excl" --scale 0.5 --out-dir "$OUT/heldout_refined" >"$OUT/heldout_refined.json"
fi

python3 - "$OUT" "${HELDOUT[@]}" <<'EOF'
import json, sys, pathlib
out = pathlib.Path(sys.argv[1])
g = json.loads((out / "gs_init.json").read_text())
k = json.loads((out / "keypoints.json").read_text())
views = []
for v in sys.argv[2:]:
    r = json.loads((out / "heldout" / f"view_{v}.json").read_text())
    views.append({"view": int(v), "psnr_covered": r.get("psnr_covered"),
                  "coverage": r["coverage"], "side_by_side": r["files"].get("side_by_side")})
psnrs = [v["psnr_covered"] for v in views if v["psnr_covered"] is not None]
rej = g["rejected"]
refined = {}
if (out / "gs_refine.json").exists():
    r = json.loads((out / "gs_refine.json").read_text())
    before = json.loads((out / "heldout_init_half.json").read_text())
    after = json.loads((out / "heldout_refined.json").read_text())
    refined = {"refine_iterations": r["iterations"], "refine_scale": r["scale"],
               "refine_seconds": r["seconds"],
               "heldout_half_psnr_before": before["psnr"], "heldout_half_coverage_before": before["coverage"],
               "heldout_half_psnr_refined": after["psnr"], "heldout_half_coverage_refined": after["coverage"],
               "heldout_refined_views": after["views"]}
print(json.dumps({
    **refined,
    "gaussians": g["kept"],
    "median_reproj_px": g["median_reproj_px"],
    "rejected_frac": rej["total"] / max(g["sampled"], 1),
    "rejected": rej,
    "sampled": g["sampled"],
    "matches_imported": k["matches"],
    "pairs_used": k["pairs"],
    "heldout_psnr": sum(psnrs) / len(psnrs) if psnrs else None,
    "heldout_coverage": sum(v["coverage"] for v in views) / len(views),
    "heldout_views": views,
}, indent=2, sort_keys=True))
EOF
