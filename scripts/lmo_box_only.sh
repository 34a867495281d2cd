#!/usr/bin/env bash
# LM-O, box-only training (issue 43's protocol): one model per object from
# the boxes of the first 50 development photographs (lmo_boxes_coco.py),
# each scored alone on the other 150 (bop-eval --train-photos 50), then the
# rows joined into one table, report and plot (recall against FPPI).
#
#   scripts/lmo_box_only.sh OUT [train flags...]
#   scripts/lmo_box_only.sh out/lmo-cnn --features cnn
#   scripts/lmo_box_only.sh out/lmo-hog --features hog
#
# Environment: DATA (default ../shared/data/lmo_dev), OBJECTS (default
# "ape cat duck glue"), FIRST (default 50), BIN (default
# target/release/sdhop-train). Training time and peak memory of each object
# are written to OUT/OBJECT.time (GNU time, where installed).
set -euo pipefail
out=${1:?usage: scripts/lmo_box_only.sh OUT [train flags...]}
shift
data=${DATA:-../shared/data/lmo_dev}
objects=${OBJECTS:-ape cat duck glue}
first=${FIRST:-50}
bin=${BIN:-target/release/sdhop-train}
mkdir -p "$out"
python3 ../shared/tools/lmo_boxes_coco.py "$data" --first "$first" --out "$out/boxes.json"
merge=()
for o in $objects; do
    mkdir -p "$out/models-$o"
    timer=()
    if [ -x /usr/bin/time ]; then timer=(/usr/bin/time -v -o "$out/$o.time"); fi
    "${timer[@]}" "$bin" train --coco "$out/boxes.json" --images "$out" --category "$o" \
        --out "$out/models-$o" "$@" 2>&1 | grep -v '^skipped' || true
    [ -f "$out/models-$o/$o.safetensors" ] || { echo "training $o failed" >&2; exit 1; }
    "$bin" bop-eval --data "$data" --models-dir "$out/models-$o" --train-photos "$first" \
        --out "$out/eval-$o"
    merge+=(--merge "sdhop=$out/eval-$o/report.json")
done
"$bin" bop-eval "${merge[@]}" --out "$out/eval"
