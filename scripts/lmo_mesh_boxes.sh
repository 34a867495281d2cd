#!/usr/bin/env bash
# LM-O, a detector from the object's mesh plus box-labelled photographs
# (issue 44's protocol): one model per object from its mesh and the boxes
# of the first 50 development photographs (lmo_boxes_coco.py), each scored
# alone on the other 150 (bop-eval --train-photos 50), then the rows
# joined into one table, report and plot (recall against FPPI).
#
#   scripts/lmo_mesh_boxes.sh OUT [mesh flags...]
#   scripts/lmo_mesh_boxes.sh out/lmo-mesh-boxes
#   scripts/lmo_mesh_boxes.sh out/lmo-renders-first --photo-route renders-first \
#       --backgrounds ../shared/data/cmu_ko8/negative
#
# Environment: DATA (default ../shared/data/lmo_dev), OBJECTS (default
# "ape:1 cat:6 duck:9 glue:11", name:BOP id), FIRST (default 50), BIN
# (default target/release/sdhop-train), POSE (set to 1: also the pose from
# no start with the four models loaded together, bop-eval --pose, every
# POSE_EVERY-th photograph, default 1). Training time and peak memory of
# each object are written to OUT/NAME.time (GNU time, where installed).
set -euo pipefail
out=${1:?usage: scripts/lmo_mesh_boxes.sh OUT [mesh flags...]}
shift
data=${DATA:-../shared/data/lmo_dev}
objects=${OBJECTS:-ape:1 cat:6 duck:9 glue:11}
first=${FIRST:-50}
bin=${BIN:-target/release/sdhop-train}
mkdir -p "$out/models"
python3 ../shared/tools/lmo_boxes_coco.py "$data" --first "$first" --out "$out/boxes.json"
merge=()
for o in $objects; do
    name=${o%%:*}
    id=$(printf %06d "${o##*:}")
    mkdir -p "$out/models-$name"
    timer=()
    if [ -x /usr/bin/time ]; then timer=(/usr/bin/time -v -o "$out/$name.time"); fi
    "${timer[@]}" "$bin" mesh --mesh "$data/models/obj_$id.ply" --name "$name" \
        --photos "$out/boxes.json" --work "$out/work-$name" \
        --out "$out/models-$name/$name.safetensors" "$@" 2>&1 | grep --line-buffered -v '^--photos: left out' || true
    [ -f "$out/models-$name/$name.safetensors" ] || { echo "training $name failed" >&2; exit 1; }
    cp "$out/models-$name/$name.safetensors" "$out/models/"
    "$bin" bop-eval --data "$data" --models-dir "$out/models-$name" --train-photos "$first" \
        --out "$out/eval-$name"
    merge+=(--merge "sdhop=$out/eval-$name/report.json")
done
"$bin" bop-eval "${merge[@]}" --out "$out/eval"
if [ "${POSE:-0}" = 1 ]; then
    "$bin" bop-eval --data "$data" --models-dir "$out/models" --train-photos "$first" \
        --pose --every "${POSE_EVERY:-1}" --out "$out/eval-pose"
fi
