#!/bin/bash
# Every refusal of the guard, tried on a small synthetic scene: prints each command, the last
# lines it prints and its exit status (PGS=path/to/pgs to choose the executable).
set -u
P="${PGS:-pgs}"
W=$(mktemp -d /tmp/guard-retest.XXXX)
cd "$W"
run() { echo "\$ $*"; out=$("$@" 2>&1); rc=$?; echo "$out" | tail -n 2 | sed 's/^/  | /'; echo "  exit $rc"; }
T="--set train.iterations=30 --set train.threads=1 --set train.log_every=1000 --no-progress"
$P make-scene scene --views 10 --width 48 --height 36 >/dev/null 2>&1
$P make-scene other --views 10 --width 48 --height 36 --seed 3 >/dev/null 2>&1
$P train scene --out run --patch demo $T >/dev/null 2>&1
$P encode run -o f.pgs >/dev/null 2>&1
echo "## 1. work lost"
run $P encode run -o run/checkpoint.pt
run $P export-ply run -o run/checkpoint.pt
run $P train scene --out run --patch demo $T
( $P train scene --out run2 --patch demo --set train.iterations=400 --set train.threads=1 --no-progress >/dev/null 2>&1 & ); sleep 12
run $P train scene --out run2 --patch demo --set train.iterations=400 --set train.threads=1 --no-progress --overwrite
run $P decode f.pgs -o run
run $P train scene --out scene/images/x --patch demo $T
run $P train scene --out scene --patch demo $T
echo "## 2. resume"
run $P train other --out run --patch demo $T --resume
run $P train scene --out run --patch demo $T --resume --set model.voxel_size=0.1
run $P train scene --out nothing-here --patch demo $T --resume
echo "## 4. crashes"
$P make-scene one --views 1 --width 48 --height 36 >/dev/null 2>&1
run $P train one --out r1 --patch demo $T
mkdir -p deep && python3 -c "
import json; d={'frames':[]}
s='['*100000+']'*100000
open('deep/transforms_train.json','w').write('{\"camera_angle_x\":0.5,\"frames\":'+s+'}')"
run $P train deep --out r2 --patch demo $T
run $P make-scene s5 --width -5
run $P make-scene s0 --views 0
mkdir -p bomb/sparse/0 && cp -r scene/images bomb/ && cp scene/sparse/0/cameras.* scene/sparse/0/images.* bomb/sparse/0/ && python3 -c "
import struct; open('bomb/sparse/0/points3D.bin','wb').write(struct.pack('<Q', 2**62))"
run $P train bomb --out r3 --patch demo $T
run timeout 60 $P decode /dev/zero -o z
run env PGS_DECODE_MEMORY_MB=inf $P decode f.pgs -o d1
run env PGS_DECODE_MEMORY_MB=-5 $P decode f.pgs -o d2
run $P train scene --out r4 --patch demo $T --set model.voxel_size=-0.1
run $P train scene --out r5 --patch demo $T --set model.voxel_size=1e-12
mkdir -p broot && cp -r scene broot/good && mkdir -p broot/broken/sparse/0 && echo junk > broot/broken/sparse/0/cameras.txt
run $P benchmark broot --scenes broken --out bench --iterations 30 --no-progress --no-plots
echo "work dir: $W"
