# Shared by the scene scripts (scenes_compare.sh, size_accuracy.sh, models_compare.sh,
# budget.sh, catalog.sh, heldout_scenes.sh): where the shared scenes are, the KITTI 06 scene
# built once, and copies of their databases. Source it.
DATA=../shared/data
CACHE=target/scenes
mkdir -p "$CACHE"

jget() { python3 -c "import json,sys;d=json.load(open(sys.argv[1]));print(eval(sys.argv[2],{'d':d}))" "$@"; }

scene_dir() { # the scene's folder (KITTI 06 built once: map every frame but each 4th, queries those)
  if [ "$1" = kitti06 ]; then
    if [ ! -f "$CACHE/kitti06/stats.json" ]; then
      local K=$DATA/sequences/kitti06
      python3 "$DATA/tools/make_posed_scene.py" "$K/images" "$K/poses.txt" "$K/calib.txt" \
        "$CACHE/kitti06" --every 4 >"$CACHE/kitti06.log" 2>&1
    fi
    echo "$CACHE/kitti06"
  elif [ -f "$CACHE/$1/verify.txt" ]; then
    # A held-out scene built here (benches/heldout_scenes.sh): verify.txt is make_scene.py's
    # last step, so a build that failed or was stopped is not taken for one.
    echo "$CACHE/$1"
  elif [ -f "$DATA/scenes/$1/queries.txt" ]; then
    echo "$DATA/scenes/$1"
  else
    echo "scene_dir: no scene $1 (a held-out one is built by benches/heldout_scenes.sh)" >&2
    return 1
  fi
}

scene_databases() { # SCENE_DIR WORK_DIR: copies of database.db and queries.db (never the originals); South Building's are rebuilt once
  local S=$1 C=$2
  if [ -f "$S/database.db" ]; then cp "$S/database.db" "$C/database.db"; cp "$S/queries.db" "$C/queries.db"
  elif [ ! -f "$C/database.db" ]; then
    python3 "$DATA/tools/make_scene.py" IGNORED "$S" "$(mktemp -d)" --camera-mode SINGLE --every 5 \
      --steps regen-db --regen-out "$C/database.db" --regen-queries-out "$C/queries.db" >"$C/regen.log" 2>&1
  fi
}

scene_maps() { # BIN SCENE_DIR WORK_DIR: the scene's SIFT map (from the database copy) and SFP map (from its images), built once into WORK_DIR
  local bin=$1 S=$2 C=$3
  [ -f "$C/sift.sfpm" ] || "$bin" convert --colmap "$S/sparse-map" --database "$C/database.db" -o "$C/sift.sfpm" --force -q
  [ -f "$C/sfp.sfpm" ] || "$bin" convert --colmap "$S/sparse-map" --images "$S/images" -o "$C/sfp.sfpm" --force -q
}
