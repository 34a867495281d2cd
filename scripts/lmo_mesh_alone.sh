#!/usr/bin/env bash
# LM-O, a detector from the object's mesh alone (no photograph of it): one
# model per object by `sdhop-train mesh` over the CMU_KO8 negative scenes,
# each scored alone on all the development photographs (bop-eval: AUC, COCO
# AP of boxes and masks), then the rows joined into one table and plot.
#
#   scripts/lmo_mesh_alone.sh OUT [mesh flags...]
#   scripts/lmo_mesh_alone.sh out/lmo-mesh-hog
#   scripts/lmo_mesh_alone.sh out/lmo-mesh-cnn --features cnn
#
# Environment: DATA (default ../shared/data/lmo_dev), OBJECTS (default
# "ape:1 cat:6 duck:9 glue:11", name:BOP id), BACKGROUNDS (default
# ../shared/data/cmu_ko8/negative), BIN (default target/release/sdhop-train).
# Training time and peak memory of each object go to OUT/NAME.time (GNU
# time, where installed).
set -euo pipefail
out=${1:?usage: scripts/lmo_mesh_alone.sh OUT [mesh flags...]}
shift
data=${DATA:-../shared/data/lmo_dev}
objects=${OBJECTS:-ape:1 cat:6 duck:9 glue:11}
backgrounds=${BACKGROUNDS:-../shared/data/cmu_ko8/negative}
bin=${BIN:-target/release/sdhop-train}
mkdir -p "$out/models"
merge=()
for o in $objects; do
    name=${o%%:*}
    id=$(printf %06d "${o##*:}")
    mkdir -p "$out/models-$name"
    timer=()
    if [ -x /usr/bin/time ]; then timer=(/usr/bin/time -v -o "$out/$name.time"); fi
    "${timer[@]}" "$bin" mesh --mesh "$data/models/obj_$id.ply" --name "$name" \
        --backgrounds "$backgrounds" --work "$out/work-$name" \
        --out "$out/models-$name/$name.safetensors" "$@"
    [ -f "$out/models-$name/$name.safetensors" ] || { echo "training $name failed" >&2; exit 1; }
    cp "$out/models-$name/$name.safetensors" "$out/models/"
    "$bin" bop-eval --data "$data" --models-dir "$out/models-$name" --out "$out/eval-$name"
    merge+=(--merge "sdhop=$out/eval-$name/report.json")
done
"$bin" bop-eval "${merge[@]}" --out "$out/eval"
