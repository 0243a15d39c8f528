#!/usr/bin/env bash
# Builds issue 36's held-out localization scenes into target/scenes/ (models/sfp-v3.md, "Held
# out"): real images no model here was trained or tuned on, each turned into a map/query scene
# by the shared make_scene.py (SIFT SfM pseudo ground truth, every 5th registered image a query;
# british-museum-3: every 3rd, so that its other photos are queries too).
#
# | scene          | images                      | source                                                       |
# |----------------|-----------------------------|--------------------------------------------------------------|
# | visp-castel    | 30 video frames, 640x480    | Debian visp-images-data 3.5.0-1, mbt-depth/castel/castel     |
# | british-museum | 10 internet photos          | facebookresearch/vggsfm @ e1d9d2e, examples/british_museum   |
# | british-museum-3 | the same 10 photos, every 3rd a query                                                    |
# | kitchen        | 25 photos, 1558x1039        | facebookresearch/vggsfm @ e1d9d2e, examples/kitchen          |
# | lund-street    | 29 phone photos, 1024x768   | mapillary/OpenSfM @ 238744c, data/lund                       |
#
# The Debian package is downloaded here (apt-get download); the two repositories are checkouts
# the caller gives (git clone https://github.com/facebookresearch/vggsfm and
# https://github.com/mapillary/OpenSfM; the scenes of a checkout not given are skipped). Every
# source image is checked against benches/heldout_scenes.sha256 before anything is built. A
# scene already built (its verify.txt, make_scene.py's last step) is kept. The prepared images
# are the same bytes on every run, the SfM is not (COLMAP on 2 threads): a rebuilt scene's
# ground truth differs a little (visp-castel: 3,396 or 3,318 points), so compare models on one
# build.
#
# python3 must have pillow and pycolmap (the tests' venv: PATH="$(bash .ci/tools | tail -1)/bin:$PATH").
#
# Usage: bash benches/heldout_scenes.sh [VGGSFM_CHECKOUT] [OPENSFM_CHECKOUT]
set -euo pipefail
vggsfm=${1:+$(realpath "$1")}
opensfm=${2:+$(realpath "$2")}
cd "$(dirname "$0")/.."
source benches/scenes.sh
manifest=$PWD/benches/heldout_scenes.sha256
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
mkdir -p "$work/src"

stage() { # NAME FOLDER: the scene's source images, as the manifest names them
  mkdir -p "$work/src/$1"
  cp "$2"/* "$work/src/$1/"
}
if [ ! -f "$CACHE/visp-castel/verify.txt" ]; then
  (cd "$work" && apt-get download visp-images-data=3.5.0-1 >/dev/null)
  dpkg-deb -x "$work"/visp-images-data_3.5.0-1_all.deb "$work/deb"
  mkdir -p "$work/src/visp-castel"
  cp "$work"/deb/usr/share/visp-images-data/ViSP-images/mbt-depth/castel/castel/image_*.pgm "$work/src/visp-castel/"
fi
[ -z "$vggsfm" ] || { stage british-museum "$vggsfm/examples/british_museum/images"; stage kitchen "$vggsfm/examples/kitchen/images"; }
[ -z "$opensfm" ] || stage lund-street "$opensfm/data/lund/images"

build() { # NAME SOURCE CAMERA_MODE EVERY: SOURCE's images, every EVERY-th registered one a query
  local name=$1 source=$2 src=$work/src/$2
  [ -d "$src" ] && [ ! -f "$CACHE/$name/verify.txt" ] || return 0
  # Every file the manifest lists for this source, and nothing else.
  (cd "$work/src" && grep " $source/" "$manifest" | sha256sum --quiet -c -)
  [ "$(ls "$src" | wc -l)" -eq "$(grep -c " $source/" "$manifest")" ] || { echo "$source: files beyond the manifest in $src" >&2; exit 1; }
  if [ "$source" = visp-castel ]; then # make_scene.py reads JPEG and PNG, not PGM
    python3 -c "import sys; from PIL import Image; [Image.open(p).save(p[:-4] + '.png') for p in sys.argv[1:]]" "$src"/*.pgm
    rm "$src"/*.pgm
  fi
  # COLMAP's mapper is randomised: on lund-street one run in a few registers no model.
  local try
  for try in 1 2 3; do
    rm -rf "$CACHE/$name" "$work/$name"
    python3 "$DATA/tools/make_scene.py" "$src" "$CACHE/$name" "$work/$name" --camera-mode "$3" --every "$4" \
      >"$CACHE/$name.log" 2>&1 && break
    echo "$name: make_scene.py failed (try $try of 3; $CACHE/$name.log)" >&2
    [ "$try" -lt 3 ] || exit 1
  done
  echo "$name: $(jget "$CACHE/$name/stats.json" "f\"{d['split']['num_queries']} queries, {d['split']['num_db_images']} map images\"")"
}
build visp-castel visp-castel SINGLE 5
build british-museum british-museum PER_IMAGE 5 # internet photos: a camera each, as Sacre-Coeur
build british-museum-3 british-museum PER_IMAGE 3 # the same photos, 3 other queries (names[1::3])
build kitchen kitchen SINGLE 5
build lund-street lund-street SINGLE 5
