#!/usr/bin/env bash
# Byte-identity check for restructuring commits: simulates seven captures from a folder of
# photographs (handheld, static, Bayer, fast shake with the photon trajectory, HDR, moving object,
# pan), reconstructs them with every method and denoiser, --scale 2, --video, align, display,
# eval and cfa compare, and writes the sha256 of every output to OUT/sums.txt.
#
#   tools/byte_identity/run.sh OLD_BIN /tmp/old SCENES_DIR
#   tools/byte_identity/run.sh target/release/quantacolor /tmp/new SCENES_DIR
#   diff /tmp/old/sums.txt /tmp/new/sums.txt && echo byte-identical
#
# SCENES_DIR holds kodim02/04/07/12/15/22.png and MultiResolution_Bonita.exr (the photographs
# `bench quality` uses). Add QUANTACOLOR_ISA=generic in front to compare the portable paths.
set -euo pipefail
if [ $# -ne 3 ]; then
    echo "usage: $0 QUANTACOLOR_BINARY OUT_DIR SCENES_DIR" >&2
    exit 2
fi
BIN=$(realpath "$1"); OUT=$2; S=$(realpath "$3")
rm -rf "$OUT"; mkdir -p "$OUT"; cd "$OUT"
sim() { "$BIN" simulate --out "cap-$1" "${@:2}" >/dev/null; }
sim hand   --scene "$S/kodim04.png" --motion handheld --frames 1000 --seed 301
sim static --scene "$S/kodim07.png" --motion static --frames 512 --seed 302
sim bayer  --scene "$S/kodim22.png" --motion handheld --frames 512 --cfa bayer --seed 303
sim fast   --scene "$S/kodim15.png" --motion fast-handheld --frames 512 --seed 304
sim hdr    --scene "$S/MultiResolution_Bonita.exr" --motion handheld --frames 1000 \
    --peak-percentile 50 --peak 0.1 --seed 305
sim obj    --scene "$S/kodim12.png" --motion object --frames 512 --seed 306
sim pan    --scene "$S/kodim02.png" --motion pan --frames 2000 --seed 307
for c in hand static bayer fast hdr obj pan; do
    "$BIN" reconstruct "cap-$c" --out "rec-$c" >/dev/null
done
"$BIN" reconstruct cap-hand --out rec-hand-none --denoise none >/dev/null
"$BIN" reconstruct cap-hand --out rec-hand-bm3d --denoise bm3d >/dev/null
"$BIN" reconstruct cap-hand --out rec-hand-naive --method naive >/dev/null
"$BIN" reconstruct cap-static --out rec-static-s2 --scale 2 --denoise none >/dev/null
"$BIN" reconstruct cap-hand --out rec-hand-video --video --stride 400 >/dev/null
"$BIN" align cap-fast --out align-fast >/dev/null
"$BIN" display rec-hdr/linear.npy --out hdr.tif --tonemap mantiuk06 >/dev/null
"$BIN" display rec-hand/linear.npy --out dark.png --mesopic 0 >/dev/null
"$BIN" eval rec-hand/linear.npy cap-hand/ground_truth.npy --border 16 > eval.txt
"$BIN" cfa compare --out cfa-sheet >/dev/null
# Every output but report.toml (it records timings); captures last.
find . -type f \( -name '*.npy' -o -name '*.png' -o -name '*.tif' -o -name '*.exr' \
    -o -name 'eval.txt' -o -name '*.csv' \) ! -path './cap-*' | sort | xargs sha256sum > sums.txt
find . -path './cap-*' -type f | sort | xargs sha256sum >> sums.txt
echo "$(wc -l < sums.txt) outputs hashed in $OUT/sums.txt"
