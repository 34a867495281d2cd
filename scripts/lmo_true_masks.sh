#!/usr/bin/env bash
# LM-O with true visible masks (issue 43's "with true masks" figure): one
# model per object from the first 50 development photographs, each
# instance's full box and visible mask (lmo_masks_coco.py), each model
# scored alone on the other 150 (bop-eval --train-photos 50), then the rows
# joined into one table, report and plot (recall against FPPI). The
# masked counterpart of lmo_box_only.sh.
#
#   scripts/lmo_true_masks.sh OUT [train flags...]
#   scripts/lmo_true_masks.sh out/lmo-masks-cnn --features cnn
#
# Environment: DATA (default ../shared/data/lmo_dev), OBJECTS (default
# "ape cat duck glue"), FIRST (default 50), BIN (default
# target/release/sdhop-train). Training time and peak memory of each object
# are written to OUT/OBJECT.time (GNU time, where installed).
set -euo pipefail
out=${1:?usage: scripts/lmo_true_masks.sh OUT [train flags...]}
shift
data=${DATA:-../shared/data/lmo_dev}
objects=${OBJECTS:-ape cat duck glue}
first=${FIRST:-50}
bin=${BIN:-target/release/sdhop-train}
here=$(dirname "$0")
declare -A ids=([ape]=1 [can]=5 [cat]=6 [driller]=8 [duck]=9 [eggbox]=10 [glue]=11 [holepuncher]=12)
mkdir -p "$out"
merge=()
for o in $objects; do
    id=${ids[$o]:?unknown LM-O object $o}
    python3 "$here/lmo_masks_coco.py" "$data" --first "$first" --object "$id" --name "$o" \
        --out "$out/masks-$o.json" 2>/dev/null
    mkdir -p "$out/models-$o"
    timer=()
    if [ -x /usr/bin/time ]; then timer=(/usr/bin/time -v -o "$out/$o.time"); fi
    "${timer[@]}" "$bin" train --coco "$out/masks-$o.json" --images / --category "$o" \
        --out "$out/models-$o" "$@" 2>&1 | grep -v '^skipped' || true
    [ -f "$out/models-$o/$o.safetensors" ] || { echo "training $o failed" >&2; exit 1; }
    "$bin" bop-eval --data "$data" --models-dir "$out/models-$o" --train-photos "$first" \
        --out "$out/eval-$o"
    merge+=(--merge "sdhop=$out/eval-$o/report.json")
done
"$bin" bop-eval "${merge[@]}" --out "$out/eval"
