#!/bin/bash
# The hostile-input harness over five small files of one synthetic scene: HAC, Predict-GS,
# Predict-GS with the compact codec, HAC++ and Predict-GS+HAC++ (120 demo iterations each).
#   tools/checks/hostile_files.sh OUT [SEED ...]      (default seeds 1 2; PGS, PY: the commands)
# Prints the harness's summary line per seed; OUT/hostile-sSEED.txt holds each run's findings.
set -e
out=${1:?usage: tools/checks/hostile_files.sh OUT [SEED ...]}; shift
seeds=${*:-1 2}
PGS=${PGS:-pgs}; PY=${PY:-python}
[ -d "$out/scene" ] || $PGS make-scene "$out/scene" --views 10 --width 48 --height 36 --seed 5
train() {
  [ -f "$out/$1/checkpoint.pt" ] || $PGS train "$out/scene" --patch demo "${@:2}" \
    --set train.iterations=120 --out "$out/$1" --no-progress > "$out/$1.log" 2>&1
}
train H; train P --patch predict-gs; train C --patch hacpp; train Q --patch predict-gs --patch hacpp
mkdir -p "$out/files"
f="$out/files"
[ -f "$f/hac.pgs" ] || $PGS encode "$out/H" -o "$f/hac.pgs" > /dev/null
[ -f "$f/pgs.pgs" ] || $PGS encode "$out/P" -o "$f/pgs.pgs" > /dev/null
[ -f "$f/compact.pgs" ] || $PGS encode "$out/P" -o "$f/compact.pgs" --positions sorted \
  --masks patterns --grids used > /dev/null
[ -f "$f/hacpp.pgs" ] || $PGS encode "$out/C" -o "$f/hacpp.pgs" > /dev/null
[ -f "$f/pgs-hacpp.pgs" ] || $PGS encode "$out/Q" -o "$f/pgs-hacpp.pgs" > /dev/null
rc=0
for s in $seeds; do
  $PY -m baseline.testing.hostile "$f/hac.pgs" "$f/pgs.pgs" "$f/compact.pgs" "$f/hacpp.pgs" \
    "$f/pgs-hacpp.pgs" --random 400 --seed "$s" > "$out/hostile-s$s.txt" 2>&1 || rc=1
  echo "seed $s: $(tail -n 1 "$out/hostile-s$s.txt")"
done
exit $rc
