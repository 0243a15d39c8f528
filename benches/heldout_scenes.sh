#!/usr/bin/env bash
# Builds issue 36's held-out localization scenes into target/scenes/ (models/sfp-v3.md, "Held
# out"): real images no model here was trained or tuned on, each turned into a map/query scene
# by the shared make_scene.py (SIFT SfM pseudo ground truth, every 5th registered image a query;
# british-museum-3: every 3rd, so that its other photos are queries too).
#
# | scene            | images                          | source                                                     |
# |------------------|---------------------------------|------------------------------------------------------------|
# | visp-castel      | 30 video frames, 640x480        | Debian visp-images-data 3.5.0-1, mbt-depth/castel/castel   |
# | british-museum   | 10 internet photos              | facebookresearch/vggsfm @ e1d9d2e, examples/british_museum |
# | british-museum-3 | the same, every 3rd one a query | the same                                                   |
# | kitchen          | 25 photos, 1558x1039            | facebookresearch/vggsfm @ e1d9d2e, examples/kitchen        |
# | lund-street      | 29 phone photos, 1024x768       | mapillary/OpenSfM @ 238744c, data/lund                     |
#
# The Debian package is downloaded here (apt-get download); the two repositories are checkouts
# the caller gives (git clone https://github.com/facebookresearch/vggsfm and
# https://github.com/mapillary/OpenSfM; the scenes of a checkout not given are skipped). Every
# source image is checked against benches/heldout_scenes.sha256 before anything is built. A
# scene already built (its verify.txt, make_scene.py's last step) is kept. The prepared images
# are the same bytes on every run, the SfM is not (COLMAP on 2 threads): a rebuilt scene's
# ground truth differs a little (visp-castel's sparse-full: 3,396 or 3,318 points; lund-street:
# 21, 27 or 28 images registered), so compare models on one build.
#
# python3 must have pillow and pycolmap (the tests' venv: PATH="$(bash .ci/tools | tail -1)/bin:$PATH").
#
# Usage: bash benches/heldout_scenes.sh [VGGSFM_CHECKOUT] [OPENSFM_CHECKOUT]
#   ("" for a checkout not given: bash benches/heldout_scenes.sh "" OpenSfM)
set -euo pipefail
checkout() { # the given checkout's absolute path, or nothing
  [ -z "$1" ] && return 0
  [ -d "$1" ] || { echo "heldout_scenes.sh: $1 is not a folder (a checkout of $2)" >&2; exit 1; }
  realpath -- "$1"
}
vggsfm=$(checkout "${1:-}" facebookresearch/vggsfm)
opensfm=$(checkout "${2:-}" mapillary/OpenSfM)
cd "$(dirname "$0")/.."
source benches/scenes.sh
manifest=$PWD/benches/heldout_scenes.sha256
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
mkdir -p "$work/src"

stage() { # SET FOLDER: a set of source images, named as the manifest names them
  mkdir -p "$work/src/$1"
  cp -- "$2"/* "$work/src/$1/"
}
if [ ! -f "$CACHE/visp-castel/verify.txt" ]; then
  castel=./usr/share/visp-images-data/ViSP-images/mbt-depth/castel/castel
  if (cd "$work" && apt-get download visp-images-data=3.5.0-1 >/dev/null 2>&1); then
    mkdir -p "$work/deb" "$work/src/visp-castel"
    # The package unpacks to about 220 MB: only the 30 frames are taken out.
    dpkg-deb --fsys-tarfile "$work"/visp-images-data_3.5.0-1_all.deb |
      tar -x -C "$work/deb" --wildcards "$castel/image_*.pgm"
    cp "$work/deb/$castel"/image_*.pgm "$work/src/visp-castel/"
  else
    echo "visp-castel: apt-get download visp-images-data=3.5.0-1 failed; skipped" >&2
  fi
fi
[ -z "$vggsfm" ] || { stage british-museum "$vggsfm/examples/british_museum/images"; stage kitchen "$vggsfm/examples/kitchen/images"; }
[ -z "$opensfm" ] || stage lund-street "$opensfm/data/lund/images"

listed() { # SET: the manifest's lines of that set, matched on the name's prefix exactly
  awk -v p="$1/" 'index($2, p) == 1' "$manifest"
}

build() { # NAME SET CAMERA_MODE EVERY: SET's images, every EVERY-th registered one a query
  local name=$1 set_dir=$work/src/$2 images
  [ -d "$set_dir" ] && [ ! -f "$CACHE/$name/verify.txt" ] || return 0
  # Every file the manifest lists for this set, and nothing else (--strict: a malformed line
  # fails the check instead of being skipped).
  (cd "$work/src" && listed "$2" | sha256sum --quiet --strict -c -)
  [ "$(ls "$set_dir" | wc -l)" -eq "$(listed "$2" | wc -l)" ] ||
    { echo "$2: files beyond the manifest in $set_dir" >&2; exit 1; }
  images=$set_dir
  if [ "$2" = visp-castel ]; then # make_scene.py reads JPEG and PNG, not PGM
    images=$work/png/$2
    mkdir -p "$images"
    python3 -c "import os, sys; from PIL import Image
for p in sys.argv[2:]: Image.open(p).save(os.path.join(sys.argv[1], os.path.basename(p)[:-4] + '.png'))" \
      "$images" "$set_dir"/*.pgm
  fi
  # COLMAP's mapper is randomised: a run may register no model (lund-street, one in a few) or
  # a part of the images (visp-castel: 17 of 30 once, 30 of 30 twice), so a scene is built
  # again, up to 3 times, until 90 % of its images are registered; the last build stands. A
  # scene counts as built once make_scene.py's last step wrote verify.txt (benches/scenes.sh).
  local try registered
  for try in 1 2 3; do
    # The maps other scripts built once from the old build (scene_maps) go with it.
    rm -rf "$CACHE/$name" "$CACHE/$name"-size "$CACHE/$name"-compare "$work/$name"
    if python3 "$DATA/tools/make_scene.py" "$images" "$CACHE/$name" "$work/$name" --camera-mode "$3" \
      --every "$4" >"$CACHE/$name.log" 2>&1; then
      registered=$(jget "$CACHE/$name/stats.json" "f\"{d['split']['sparse_full']['reg_images']} of {d['prep']['num_images']}\"")
      jget "$CACHE/$name/stats.json" "d['split']['sparse_full']['reg_images'] >= 0.9 * d['prep']['num_images']" |
        grep -q True && break
      echo "$name: $registered images registered (try $try of 3)" >&2
    else
      echo "$name: make_scene.py failed (try $try of 3; $CACHE/$name.log)" >&2
      [ "$try" -lt 3 ] || { rm -rf "$CACHE/$name"; exit 1; }
    fi
  done
  echo "$name: $registered images registered, $(jget "$CACHE/$name/stats.json" "f\"{d['split']['num_queries']} queries, {d['split']['num_db_images']} map images\"")"
}
build visp-castel visp-castel SINGLE 5
build british-museum british-museum PER_IMAGE 5 # internet photos: a camera each, as Sacre-Coeur
build british-museum-3 british-museum PER_IMAGE 3 # the same photos, 3 other queries (names[1::3])
build kitchen kitchen SINGLE 5
build lund-street lund-street SINGLE 5
