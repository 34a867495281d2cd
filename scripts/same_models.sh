#!/usr/bin/env bash
# Whether two builds train the same models: one short training of each
# route kind (CMU_KO8 single-pose and views with HOG cells, LM-O box-only
# photographs with learned cells, a mesh alone, mesh + photographs, and a
# join), run with the same command and seed by each build's
# `sdhop-train`, then compared by scripts/compare_models.py (tensors byte
# for byte, metadata apart from times).
#
#   scripts/same_models.sh OLD_BIN NEW_BIN OUT
#   e.g. git worktree add /tmp/old REV && (cd /tmp/old && cargo build --release --bins)
#        scripts/same_models.sh /tmp/old/target/release/sdhop-train target/release/sdhop-train out/same
#
# Environment: KO8 (default ../shared/data/cmu_ko8), LMO (default
# ../shared/data/lmo_dev), ROUTES (default "single views coco mesh photos
# join"), SIDES (default "old new"; "new" retrains with NEW_BIN only and
# compares with the old side already in OUT).
set -euo pipefail
old=${1:?usage: scripts/same_models.sh OLD_BIN NEW_BIN OUT}
new=${2:?usage: scripts/same_models.sh OLD_BIN NEW_BIN OUT}
out=${3:?usage: scripts/same_models.sh OLD_BIN NEW_BIN OUT}
ko8=${KO8:-../shared/data/cmu_ko8}
lmo=${LMO:-../shared/data/lmo_dev}
routes=${ROUTES:-single views coco mesh photos join}
sides=${SIDES:-old new}
mkdir -p "$out"
python3 ../shared/tools/lmo_boxes_coco.py "$lmo" --first 12 --out "$out/boxes.json" >/dev/null
short=(--max-passes 2 --seed 3)
train() { # NAME ARGS...: trains NAME with both builds
    local name=$1
    shift
    local file=""
    [ "$1" = mesh ] && file=/duck.safetensors
    for side in $sides; do
        local bin=$old
        [ "$side" = new ] && bin=$new
        mkdir -p "$out/$side/$name"
        echo "== $name ($side): $(basename "$bin") $*" >&2
        local work=()
        [ "$1" = mesh ] && work=(--work "$out/$side/$name-work")
        "$bin" "$@" "${work[@]}" --out "$out/$side/$name$file" >"$out/$side/$name.log" 2>&1 ||
            { echo "$name ($side) failed: see $out/$side/$name.log" >&2; exit 1; }
    done
}
for r in $routes; do
    case $r in
    single) train single train --ko8 "$ko8" --objects cup --sources single \
        --negative-scenes 10 --other-negatives 2 "${short[@]}" ;;
    views) train views train --ko8 "$ko8" --objects saucepan --sources views \
        --per-view 1 --latent-rounds 1 --negative-scenes 10 --other-negatives 2 "${short[@]}" ;;
    coco) train coco train --coco "$out/boxes.json" --images "$out" --category duck \
        --box-folds 0 "${short[@]}" ;;
    mesh) train mesh mesh --mesh "$lmo/models/obj_000009.ply" --name duck \
        --backgrounds "$ko8/negative" --renders 24 --negatives 10 "${short[@]}" ;;
    photos) train photos mesh --mesh "$lmo/models/obj_000009.ply" --name duck \
        --photos "$out/boxes.json" --renders 12 --negatives 10 --fold-passes 1 "${short[@]}" ;;
    join)
        for side in $sides; do
            bin=$old
            [ "$side" = new ] && bin=$new
            "$bin" join --base "$out/$side/single" --add "$out/$side/views" --objects cup \
                --offset 0.5 --out "$out/$side/join" >"$out/$side/join.log" 2>&1 ||
                { echo "join ($side) failed: see $out/$side/join.log" >&2; exit 1; }
        done ;;
    *) echo "unknown route $r" >&2; exit 2 ;;
    esac
done
status=0
for r in $routes; do
    echo "-- $r"
    python3 "$(dirname "$0")/compare_models.py" "$out/old/$r" "$out/new/$r" || status=1
done
exit $status
