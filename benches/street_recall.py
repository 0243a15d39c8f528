"""Which of exhaustive ranking's top k an image index missed, and whether they share a point
with the query's best image (issue 35): on the generated street, exhaustive VLAD ranking's
top 10 holds now and then an image kilometres away that shares no point with the query's
surroundings (a score just above the noise floor), which no index short of scoring every
image finds. Prints recall@k of every image's top k (as benches/street.sh does) and recall@k
of those of them that share a point with the top 1, then each missed image.

Usage: python benches/street_recall.py MAP EVERY.json INDEXED.json
  (the two JSONs: `sfpmap localize --format json` with `--retrieval-probe 0` and without;
  needs the sfpmap Python package, `python -m pip install ./python/binding` or maturin)
"""
import json
import sys

import numpy as np
import sfpmap


def main(map_path, every_path, indexed_path):
    m = sfpmap.Map(map_path)
    index_of = {name: i for i, name in enumerate(m.images.names)}
    offsets = np.asarray(m.visibility.offsets).astype(np.int64)
    points = np.asarray(m.visibility.points)

    def seen(i):
        return set(points[offsets[i]:offsets[i + 1]].tolist())

    every = {q["name"]: q["retrieved"] for q in json.load(open(every_path))}
    indexed = {q["name"]: q["retrieved"] for q in json.load(open(indexed_path))}
    raw, sharing, misses = [], [], []
    for name, top in every.items():
        if not top:
            continue
        got = set(indexed.get(name, []))
        best = seen(index_of[top[0]])
        related = [t for t in top if t == top[0] or seen(index_of[t]) & best]
        raw.append(len(got & set(top)) / len(top))
        sharing.append(len(got & set(related)) / len(related))
        for rank, t in enumerate(top):
            if t not in got:
                shared = len(seen(index_of[t]) & best)
                gap = abs(index_of[t] - index_of[top[0]])
                misses.append(f"{name}: missed {t} (rank {rank}), {shared} points shared "
                              f"with the top 1, {gap} images from it")
    print(f"recall@k of every image's top k: {np.mean(raw):.3f} (lowest {min(raw):.2f}, "
          f"{len(raw)} queries)")
    print(f"recall@k of those sharing a point with the top 1: {np.mean(sharing):.3f} "
          f"(lowest {min(sharing):.2f})")
    for line in misses:
        print(line)


if __name__ == "__main__":
    if len(sys.argv) != 4:
        sys.exit(__doc__)
    main(*sys.argv[1:])
