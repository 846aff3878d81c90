#!/bin/sh
# mix_scenes.sh DEST PREFIX:SRC:N ... — one training folder made of the first N scenes of each
# colf-synth folder SRC, as symbolic links named PREFIX_scene_NNNNN, mask files left out (so a
# run on DEST cannot read a label). Written to DEST.tmp, then renamed: a stopped run leaves no
# half-made DEST.
set -eu
[ $# -ge 2 ] || { echo "usage: mix_scenes.sh DEST PREFIX:SRC:N ..." >&2; exit 2; }
dest=$1; shift
rm -rf "$dest.tmp"
trap 'rm -rf "$dest.tmp"' EXIT
mkdir -p "$dest.tmp"
for spec in "$@"; do
  prefix=${spec%%:*}; rest=${spec#*:}; src=${rest%:*}; n=${rest##*:}
  count=0
  for scene in "$src"/scene_*; do
    [ "$count" -lt "$n" ] || break
    [ -d "$scene" ] || { echo "mix_scenes.sh: $src: no scene folders" >&2; exit 1; }
    out="$dest.tmp/${prefix}_$(basename "$scene")"
    mkdir "$out"
    abs=$(cd "$scene" && pwd)   # links must not depend on where DEST is
    for f in "$scene"/*; do
      case $f in *.mask.png) ;; *) ln -s "$abs/$(basename "$f")" "$out/" ;; esac
    done
    count=$((count + 1))
  done
  [ "$count" -eq "$n" ] || { echo "mix_scenes.sh: $src: $count scenes, $n asked for" >&2; exit 1; }
done
mv "$dest.tmp" "$dest"
trap - EXIT
