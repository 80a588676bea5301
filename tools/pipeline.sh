#!/usr/bin/env bash
# The ProFuse pipeline composed from the per-crate plumbing tools, stage by stage, with
# the same default parameters as `profuse run` (a test checks that the outputs are equal
# byte for byte).
#
#   tools/pipeline.sh SCENE_DIR [OUT_DIR]       (OUT_DIR defaults to SCENE_DIR/out)
#
# Environment: PROFUSE_BIN_DIR = directory of built tools (default: build target/release);
# PQ_M = sub-quantisers (default 128; must divide the descriptor dimension).
set -euo pipefail

if [[ $# -lt 1 || $# -gt 2 ]]; then
    echo "usage: $0 SCENE_DIR [OUT_DIR]" >&2
    exit 2
fi
S=$1
O=${2:-$S/out}
here=$(cd "$(dirname "$0")/.." && pwd)
if [[ -n ${PROFUSE_BIN_DIR:-} ]]; then
    bin=$PROFUSE_BIN_DIR
else
    cargo build --quiet --release --manifest-path "$here/Cargo.toml" -p profuse-tools >&2
    bin=$here/target/release
fi
mkdir -p "$O"

# 1. geometry: triangulated initial Gaussians
"$bin/gs-init" --quiet run --cameras "$S/cameras.safetensors" --images "$S" \
    --matches "$S/matches.safetensors" --out "$O/gaussians.safetensors" >/dev/null
# 2. semantics: 3D Context Proposals, then registration
"$bin/warp-graph" --quiet run --masks "$S/masks.safetensors" --matches "$S/matches.safetensors" \
    --cameras "$S/cameras.safetensors" --gaussians "$O/gaussians.safetensors" \
    --out "$O/proposals.safetensors" >/dev/null
"$bin/fuse" --quiet run --gaussians "$O/gaussians.safetensors" --cameras "$S/cameras.safetensors" \
    --masks "$S/masks.safetensors" --proposals "$O/proposals.safetensors" \
    --out "$O/features.safetensors" >/dev/null
# 3. indexing
"$bin/pq" --quiet train --features "$O/features.safetensors" --m "${PQ_M:-128}" \
    --out "$O/pq.safetensors" >/dev/null
# 4. selection: the label files' categories over the labelled frames (LERF layout)
if [[ -d $S/gt/label ]]; then
    mapfile -t prompts < <(python3 - "$S/gt/label" "$S/prompts.safetensors" <<'PY'
import json, pathlib, struct, sys
with open(sys.argv[2], "rb") as f:
    n = struct.unpack("<Q", f.read(8))[0]
    names = set(json.loads(json.loads(f.read(n))["__metadata__"]["names"]))
cats = {o["category"] for p in pathlib.Path(sys.argv[1]).glob("*.json")
        for o in json.loads(p.read_text())["objects"]}
print("\n".join(sorted(cats & names)))
PY
    )
    args=()
    for p in "${prompts[@]}"; do args+=(--prompt "$p"); done
    rm -rf "$O/query"
    "$bin/query" --quiet run --gaussians "$O/gaussians.safetensors" --cameras "$S/cameras.safetensors" \
        --pq "$O/pq.safetensors" --prompts "$S/prompts.safetensors" "${args[@]}" \
        --score relevancy --threshold 0.5 --views-from-labels "$S/gt/label" --layout lerf \
        --out "$O/query" >/dev/null
fi
# 5. point-cloud labels on the labelled mesh
if [[ -f $S/gt/mesh.safetensors ]]; then
    # one labelling per ScanNet class set, each with that set's vocabulary only
    for set in 19 15 10; do
        "$bin/vertex-transfer" --quiet run --gaussians "$O/gaussians.safetensors" --pq "$O/pq.safetensors" \
            --prompts "$S/prompts.safetensors" --mesh "$S/gt/mesh.safetensors" --class-set "nyu$set" \
            --out "$O/vertex_labels_nyu$set.safetensors" >/dev/null
    done
fi
echo "{\"out\": \"$O\"}"
