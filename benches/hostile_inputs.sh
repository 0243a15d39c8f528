#!/usr/bin/env bash
# Issue 12's targets on the crafted maps, this build beside a reference build: median wall time
# of 3 runs and peak RSS of each. Maps: SFPMAP_HOSTILE_OUT=DIR cargo test --all-features
#   --release --test cli hostile_format::write_crafted_maps -- --ignored
# Usage: benches/hostile_inputs.sh NEW_BINARY REFERENCE_BINARY DIR
set -u
new=$1 ref=$2 dir=$3
row() { # binary, args...
  local b=$1; shift; local t=() m=0
  for _ in 1 2 3; do
    /usr/bin/time -o /tmp/hostile-time -f "%e %M" timeout 120 "$b" "$@" >/dev/null 2>&1
    out=$(tail -1 /tmp/hostile-time)
    t+=("${out% *}"); m=${out#* }
  done
  printf '%s s, %d MB' "$(printf '%s\n' "${t[@]}" | sort -n | sed -n 2p)" $((m / 1024))
}
printf '| command | this build | reference |\n|---|---|---|\n'
for cmd in "verify levels-65535.sfpm" "info levels-65535.sfpm" "export levels-65535.sfpm --ply /tmp/hostile-out.ply --force" \
           "verify zstd-160.sfpm" "info zstd-160.sfpm" "slice zstd-160.sfpm --level 0 -o /tmp/hostile-out.sfpm --force"; do
  set -- $cmd; c=$1; shift; f=$1; shift
  printf '| `%s %s %s` | %s | %s |\n' "$c" "$f" "$*" "$(row "$new" "$c" "$dir/$f" "$@")" "$(row "$ref" "$c" "$dir/$f" "$@")"
done
rm -f /tmp/hostile-out.ply /tmp/hostile-out.sfpm
