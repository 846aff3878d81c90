#!/usr/bin/env bash
# Throughput of parallel.sh on this machine with 1 and 2 local job slots (docs/cluster.md):
# IMAGES synthetic clevr567 views (64², seed 11, each with its camera) are encoded and an orbit
# of FRAMES frames (64²) rendered for each (one render job an image), into a fresh output folder
# per run, timed from start to end of parallel.sh (wall time, and the CPU time of all its
# processes). For each encoding of ENCODINGS (default: "default --fast", the model's default
# encoding and one encoder pass) and threads a colf process (all cores; 1), runs with 1 and 2
# job slots alternate, REPEATS times each, so that other work on the machine weighs on both
# alike. A Markdown table row per run goes to stdout, with the load average before it.
#
#   examples/cluster/throughput.sh [IMAGES [FRAMES [REPEATS]]]     (defaults 8, 36, 1)
#
# COLF: folder of the colf binaries (default: target/release of this checkout: cargo build
# --release first).
set -euo pipefail

here=$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)
COLF=${COLF:-$here/../../target/release}
images=${1:-8} frames=${2:-36} repeats=${3:-1}
for n in "$images" "$frames" "$repeats"; do
  [[ $n =~ ^[1-9][0-9]*$ ]] || {
    echo "usage: throughput.sh [IMAGES [FRAMES [REPEATS]]]" >&2
    exit 2
  }
done
[ -x "$COLF/colf-render" ] || {
  echo "throughput.sh: error: $COLF/colf-render: not found (cargo build --release, or set COLF)" >&2
  exit 1
}

work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
"$COLF/colf-synth" --scenes "$images" --seed 11 -q --out "$work/data"
mkdir "$work/in"
for scene in "$work"/data/scene_*; do
  name=$(basename "$scene")
  cp "$scene/view_000.png" "$work/in/$name.png"
  cp "$scene/transforms.json" "$work/in/$name.json"
done

echo "| encoding | threads a process | job slots | wall time | CPU time | images a minute | frames a second | load before |"
echo "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"
TIMEFORMAT='%R %U %S'
for encoding in ${ENCODINGS:-default --fast}; do
  flags=
  [ "$encoding" = default ] || flags=$encoding
  for threads in all 1; do
    t=
    [ "$threads" = all ] || t=$threads
    for ((r = 0; r < repeats; r++)); do
      for slots in 1 2; do
        rm -rf "$work/out"
        load=$(cut -d' ' -f1 /proc/loadavg)
        times=$({ time COLF=$COLF FRAMES=$frames SIZE=64 CHUNK=$frames ENCODE_FLAGS=$flags \
          THREADS=$t "$here/parallel.sh" -j "$slots" "$work/in" "$work/out" >"$work/log" 2>&1; } 2>&1) || {
          echo "throughput.sh: error: parallel.sh failed: $(tail -n 1 "$work/log")" >&2
          exit 1
        }
        read -r wall user sys <<<"$times"
        awk -v e="$encoding" -v t="$threads" -v j="$slots" -v w="$wall" -v u="$user" -v s="$sys" \
          -v n="$images" -v fr="$frames" -v l="$load" 'BEGIN {
            printf "| %s | %s | %d | %.1f s | %.1f s | %.1f | %.1f | %s |\n", e, t, j, w, u + s,
              60 * n / w, n * fr / w, l
          }'
      done
    done
  done
done
