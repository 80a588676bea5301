#!/usr/bin/env bash
# The geometry of the real fox capture, checked on photos that took no part in it:
# `profuse prepare --geometry-only` (poses, undistortion and cut, correspondences, gs-init,
# gs-refine), then `gs-refine eval` of the held-out photos at half resolution.
#
#   examples/fox.sh SHARED_FOX_DIR OUT_DIR [--photos-only]
#
# SHARED_FOX_DIR holds transforms.json and images/ (../shared/data/fox).
#   default        poses from transforms.json, correspondences from XFeat run by prepare
#   --photos-only  images/ alone: COLMAP gives the poses, its tracks + XFeat the matches
# FOX_KEYPOINTS=DIR uses keypoint pairs made elsewhere instead of XFeat (e.g. the shared
# SHARED_FOX_DIR/matches_xfeat).
# Held-out photos 0018, 0044, 0089 (views 10, 25, 40) are left out of the matches and of
# the refinement. FOX_REFINE_ITERS=N sets the refinement's iterations (default 1,000 at
# half resolution with densification over 300-700; 0 keeps the triangulated Gaussians);
# FOX_PREPARE_ARGS adds options to `profuse prepare` (e.g. "--set gs_init.budget=5000").
# Writes OUT/scene (the scene directory; OUT/scene/prepare.json has every stage's report
# and seconds) and OUT/heldout/view_<v>.png (render | photo); prints the held-out
# evaluation as one JSON object: psnr and coverage (means) and per view.
set -euo pipefail

usage() {
    echo "usage: $0 SHARED_FOX_DIR OUT_DIR [--photos-only]" >&2
    exit 2
}
[[ $# -eq 2 || $# -eq 3 ]] || usage
FOX=$1
OUT=$2
source_args=()
if [[ $# -eq 3 ]]; then
    [[ $3 == --photos-only ]] || usage
    source_args=(--photos-only)
fi
if [[ -n ${FOX_KEYPOINTS:-} ]]; then
    source_args+=(--keypoints "$FOX_KEYPOINTS")
fi
here=$(cd "$(dirname "$0")/.." && pwd)
if [[ -n ${PROFUSE_BIN_DIR:-} ]]; then
    bin=$PROFUSE_BIN_DIR
else
    cargo build --quiet --release --manifest-path "$here/Cargo.toml" -p profuse-tools \
        --bin profuse --bin gs-refine >&2
    bin=$here/target/release
fi
refine=()
[[ -n ${FOX_REFINE_ITERS:-} ]] && refine=(--set "gs_refine.iterations=$FOX_REFINE_ITERS")

mkdir -p "$OUT"
# shellcheck disable=SC2086 # FOX_PREPARE_ARGS is a list of options
"$bin/profuse" prepare "$FOX" --out "$OUT/scene" --geometry-only --held-out 0018,0044,0089 \
    "${source_args[@]}" "${refine[@]}" ${FOX_PREPARE_ARGS:-} >"$OUT/prepare.json"
"$bin/gs-refine" --quiet eval --gaussians "$OUT/scene/gaussians.safetensors" \
    --cameras "$OUT/scene/cameras.safetensors" --images "$OUT/scene" --views 10,25,40 \
    --scale 0.5 --out-dir "$OUT/heldout"
