"""Benchmarks of the Python package against its targets; prints medians and ratios.

    python bench.py [--shared ../../../shared/data] [--big-mb 1024] [--repeat 5]

- open: `sfpmap.Map(path)` on a synthetic map of --big-mb MB (target < 1 ms), and on a small one;
- view: one section view on the big map and on the small map (target O(1): ratio ~1);
- localize overhead: wall time of `Localizer.localize` from Python against the Rust call's own
  total (`Localization.times["total"]`), South Building SFP map, every query (target < 5 %);
- localize_many: 2 threads against 1 thread on the same queries (target >= 1.8x).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

# The installed package, not the source folder beside this script (it lacks the compiled part).
sys.path = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).resolve().parent]
import sfpmap  # noqa: E402


def median_time(f, n: int) -> float:
    ts = []
    for _ in range(n):
        t = time.perf_counter()
        f()
        ts.append(time.perf_counter() - t)
    return statistics.median(ts)


def _spin(n: int) -> int:
    x = 0
    for i in range(n):
        x += i
    return x


def machine_parallelism() -> float:
    """What this machine gives two workers now: 2 processes / 1 process speed-up of pure
    Python spinning (no GIL shared). On an idle 2-core machine it is ~2."""
    import multiprocessing

    work = [5_000_000] * 4
    with multiprocessing.Pool(1) as p:
        one = median_time(lambda: p.map(_spin, work), 3)
    with multiprocessing.Pool(2) as p:
        two = median_time(lambda: p.map(_spin, work), 3)
    return one / two


def main() -> None:
    here = Path(__file__).resolve()
    ap = argparse.ArgumentParser()
    ap.add_argument("--shared", type=Path, default=here.parents[3] / "shared/data")
    ap.add_argument("--big-mb", type=int, default=1024)
    ap.add_argument("--repeat", type=int, default=5)
    args = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="sfpmap-bench-"))

    big = tmp / "big.sfpm"
    small = tmp / "small.sfpm"
    points = args.big_mb * 1024 * 1024 // (240 * 2 + 12)
    big_bytes = sfpmap._sfpmap._write_synthetic_map(str(big), points, 240, 64)
    small_bytes = sfpmap._sfpmap._write_synthetic_map(str(small), 1000, 240, 64)

    def open_close(p):
        sfpmap.Map(p).close()

    o_big, o_small = median_time(lambda: open_close(big), 200), median_time(lambda: open_close(small), 200)
    print(f"open   {big_bytes / 1e9:.2f} GB map: median {o_big * 1e3:.3f} ms; {small_bytes / 1e3:.0f} kB map: "
          f"{o_small * 1e3:.3f} ms; ratio {o_big / o_small:.2f} (target < 1 ms)")
    with sfpmap.Map(big) as mb, sfpmap.Map(small) as ms:
        lb, ls = mb.levels[0], ms.levels[0]
        v_big = median_time(lambda: lb.short, 2000)
        v_small = median_time(lambda: ls.short, 2000)
    print(f"view   level short block, big: median {v_big * 1e6:.1f} us; small: {v_small * 1e6:.1f} us; "
          f"ratio {v_big / v_small:.2f} (target O(1))")

    scene = args.shared / "scenes/south-building"
    m = sfpmap.Map(tmp / "south.sfpm") if (tmp / "south.sfpm").exists() else None
    if m is None:
        sfpmap.convert(scene / "sparse-map", images=scene / "images", out=tmp / "south.sfpm")
        m = sfpmap.Map(tmp / "south.sfpm")
    queries = sfpmap.read_queries(scene / "queries.txt")
    ex = sfpmap.Extractor()
    feats = {n: ex.extract(scene / "images" / n) for n, _ in queries}
    loc = sfpmap.Localizer(m)
    overheads, walls, rust = [], [], []
    for _ in range(args.repeat):
        for n, c in queries:
            t = time.perf_counter()
            r = loc.localize(feats[n], c)
            wall = (time.perf_counter() - t) * 1e3
            walls.append(wall)
            rust.append(r.times["total"])
            overheads.append(wall / r.times["total"] - 1)
    print(f"localize  median wall {statistics.median(walls):.2f} ms vs Rust call {statistics.median(rust):.2f} ms: "
          f"overhead median {100 * statistics.median(overheads):.2f} % (target < 5 %)")

    batch = [(feats[n], c, n) for n, c in queries] * 4
    ratios = []
    for _ in range(args.repeat):
        t1 = median_time(lambda: loc.localize_many(batch, threads=1), 1)
        t2 = median_time(lambda: loc.localize_many(batch, threads=2), 1)
        ratios.append(t1 / t2)
    print(f"localize_many {len(batch)} queries: 2 threads / 1 thread speed-up median {statistics.median(ratios):.2f}x "
          f"(min {min(ratios):.2f}, max {max(ratios):.2f}; target >= 1.8x); the machine's own 2-process "
          f"speed-up in the same run: {machine_parallelism():.2f}x")
    m.close()


if __name__ == "__main__":
    main()
