#!/usr/bin/env bash
# CMU_KO8 from any side (issue 44): each object's single-pose model joined
# with a view component trained apart from its 25 views and the box-only
# photographs of the multi-view part, where two-fold cross-validation over
# those photographs says it helps, at the offset (added to the view
# component's scores) the folds chose; held-out single-pose photographs
# guard the choice (sdhop-train join --check-folds --guard-folds: each
# fold of a single-pose cross-validation scored with that fold's models,
# so no photograph that trained what it judges is scored). The choice is
# the set's (join --guard-scope set, the default): the settings that find
# the objects best from any side together, the set's single-pose means no
# worse than the unjoined set's and its time (each candidate timed alone
# on one thread; join --max-time-ratio, default 1.4) at most 1.4 times
# the unjoined set's.
#
#   scripts/ko8_any_side.sh OUT [train flags...]
#   BASE=models scripts/ko8_any_side.sh out/any-side     # -> out/any-side/models
#
# Steps: the views+boxes models of each fold (train --box-fold K/2: fold K's
# photographs held out) into OUT/fold0, OUT/fold1; on all photographs into
# OUT/views; the single-pose models of a GUARD_FOLDS-fold cross-validation
# (sdhop-train cv --save-models: `train --ko8 DATA --sources single`'s
# defaults, each fold's photographs held out) into OUT/guard, its figures in
# OUT/cv (skipped when OUT/guard holds them already); then join into
# OUT/models, with the check's table in OUT/join.txt. Environment: DATA
# (default ../shared/data/cmu_ko8), BASE (the single-pose models, `train --sources single`; default models/, the
# shipped ones: a model that is already joined is refused), OBJECTS
# (comma-separated, default all eight), OFFSETS (default 0,0.25,0.5),
# GUARD_FOLDS (default 5; all eight objects, as the guard scores every
# base model: about 25 minutes on two cores),
# BIN (default target/release/sdhop-train).
set -euo pipefail
out=${1:?usage: scripts/ko8_any_side.sh OUT [train flags...]}
shift
data=${DATA:-../shared/data/cmu_ko8}
base=${BASE:-models}
bin=${BIN:-target/release/sdhop-train}
offsets=${OFFSETS:-0,0.25,0.5}
guard_folds=${GUARD_FOLDS:-5}
objects=()
if [ -n "${OBJECTS:-}" ]; then objects=(--objects "$OBJECTS"); fi
mkdir -p "$out"
for k in 0 1; do
    "$bin" train --ko8 "$data" --sources views,boxes --box-fold "$k/2" \
        "${objects[@]}" --out "$out/fold$k" "$@"
done
"$bin" train --ko8 "$data" --sources views,boxes "${objects[@]}" --out "$out/views" "$@"
if [ ! -f "$out/guard/fold-0/fold.json" ]; then
    "$bin" cv --ko8 "$data" --folds "$guard_folds" \
        --save-models "$out/guard" --out "$out/cv"
fi
"$bin" join --base "$base" --add "$out/views" --ko8 "$data" \
    --check-folds "$out/fold0,$out/fold1" --guard-folds "$out/guard" \
    --offsets "$offsets" --out "$out/models" \
    | tee "$out/join.txt"
