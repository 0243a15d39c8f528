"""Fixtures: the shared scenes, the CLI binary and maps made by it once per session.

Environment: SFPMAP_CLI (the `sfpmap` binary, default target/release/sfpmap of the repository)
and SFPMAP_SHARED_DATA (default ../shared/data beside the repository). Tests that need either
fail when it is missing, unless SFPMAP_SKIP_SHARED_DATA=1 (then they skip, saying so).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[3]


def _need(path: Path, what: str) -> Path:
    if not path.exists():
        if os.environ.get("SFPMAP_SKIP_SHARED_DATA") == "1":
            pytest.skip(f"{what} absent ({path}); SFPMAP_SKIP_SHARED_DATA=1")
        pytest.fail(f"{what} absent: {path}")
    return path


def need_module(name: str):
    """The module `name`, imported; missing, it fails the test as missing data does (skips
    under SFPMAP_SKIP_SHARED_DATA=1): the test extra installs it (pyproject, `test`)."""
    import importlib

    try:
        return importlib.import_module(name)
    except ImportError as e:
        if os.environ.get("SFPMAP_SKIP_SHARED_DATA") == "1":
            pytest.skip(f"{name} absent ({e}); SFPMAP_SKIP_SHARED_DATA=1")
        pytest.fail(f"{name} absent ({e}): pip install {name} (the test extra)")


def rss_kb() -> int:
    """This process's resident memory (Linux), for tests of what a call keeps in memory."""
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    raise RuntimeError("no VmRSS")


def gil_stall(call) -> tuple:
    """Runs `call` on a thread and spins here meanwhile: (the call's duration, the longest this
    thread went without running while it ran). A call that holds the GIL stalls this thread
    for about all of its duration; one that releases it, for a switch interval or two."""
    import threading
    import time

    started, done = threading.Event(), threading.Event()
    span = []

    def work():
        started.set()  # the last thing before the call
        t0 = time.perf_counter()
        try:
            call()
        finally:
            span.extend((t0, time.perf_counter()))
            done.set()

    worker = threading.Thread(target=work)
    worker.start()
    started.wait()
    first = last = time.perf_counter()
    longest = 0.0
    while not done.is_set():
        now = time.perf_counter()
        longest = max(longest, now - last)
        last = now
    worker.join()
    t0, t1 = span
    # A stall from the call's start to this thread's first turn, or from its last turn to
    # the call's end, counts too.
    return t1 - t0, max(longest, first - t0, t1 - last)


def assert_releases_the_gil(call, min_seconds: float = 0.2) -> None:
    """`call(i)` lets other Python threads run while it works: this thread, spinning meanwhile,
    never stalls for half of one call. On a fast machine one call can be too short to tell, so
    the calls are repeated (i = 0, 1, 2, … across all of them: a caller writing files names each
    differently) until
    they take `min_seconds`. A control call that holds the GIL (a backtracking regular
    expression) shows that the measurement sees a held GIL."""
    import itertools
    import re
    import sys

    calls = itertools.count()
    repeats = 1
    # Short calls are measured against half of one call: Python's thread switches must then
    # be far shorter than a call (default 5 ms), or a released GIL would look held.
    interval = sys.getswitchinterval()
    sys.setswitchinterval(1e-4)
    try:
        while True:
            seconds, longest = gil_stall(lambda: [call(next(calls)) for _ in range(repeats)])
            if seconds >= min_seconds or repeats >= 64:
                break
            repeats *= 2
        enough = seconds >= min_seconds
        # A held GIL stalls every measurement; one stall of a busy 2-core machine (the OS
        # running something else for 24 ms of a 46 ms call, seen once in CI) does not repeat.
        # So a stall is measured once more (the same calls), and the run whose stall is the
        # smaller share of its calls counts.
        if enough and longest >= seconds / repeats / 2:
            again, longest_again = gil_stall(lambda: [call(next(calls)) for _ in range(repeats)])
            if longest_again / again < longest / seconds:
                seconds, longest = again, longest_again
    finally:
        sys.setswitchinterval(interval)
    assert enough, f"{repeats} calls took {seconds:.3f} s: too short to tell"
    per_call = seconds / repeats
    assert longest < per_call / 2, f"stalled {longest:.3f} s of a {per_call:.3f} s call: the GIL was held"
    for n in range(16, 40):
        held, stalled = gil_stall(lambda: re.match(r"(a+)+$", "a" * n + "b"))
        if held >= min_seconds:
            break
    assert stalled > held / 2, f"control: stalled {stalled:.3f} s of {held:.3f} s holding the GIL"


@pytest.fixture(scope="session")
def cli() -> Path:
    return _need(Path(os.environ.get("SFPMAP_CLI", REPO / "target/release/sfpmap")), "the sfpmap CLI")


@pytest.fixture(scope="session")
def shared() -> Path:
    return _need(Path(os.environ.get("SFPMAP_SHARED_DATA", REPO.parent / "shared/data")), "shared data")


def run_cli(cli: Path, *args: object) -> str:
    r = subprocess.run([str(cli), "--quiet", *map(str, args)], capture_output=True, text=True)
    if r.returncode != 0:
        raise AssertionError(f"sfpmap {' '.join(map(str, args))}: {r.stderr}")
    return r.stdout


@pytest.fixture(scope="session")
def work(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("sfpmap")


@pytest.fixture(scope="session")
def sacre_sift(cli, shared, work) -> Path:
    """Sacre Coeur as a SIFT map (database.db), made by the CLI."""
    scene = shared / "scenes/sacre-coeur"
    out = work / "sacre-sift.sfpm"
    run_cli(cli, "convert", "--colmap", scene / "sparse-map", "--database", scene / "database.db", "-o", out)
    return out


@pytest.fixture(scope="session")
def south_sfp(cli, shared, work) -> Path:
    """South Building as an SFP map (the images through the embedded model), by the CLI."""
    scene = shared / "scenes/south-building"
    out = work / "south-sfp.sfpm"
    run_cli(cli, "convert", "--colmap", scene / "sparse-map", "--images", scene / "images", "-o", out)
    return out


@pytest.fixture(scope="session")
def south_zstd(cli, south_sfp, work) -> Path:
    """The South Building SFP map sliced to level 2 and re-encoded with zstd."""
    out = work / "south-l2-zstd.sfpm"
    run_cli(cli, "slice", south_sfp, "--level", "2", "--codec", "zstd", "-o", out)
    return out


def cli_poses(cli: Path, *args: object, out: Path) -> dict:
    """`sfpmap localize ... --format json`: {name: pose or None}."""
    run_cli(cli, "localize", *args, "--format", "json", "-o", out, "--force")
    return {q["name"]: q["cam_from_world"] for q in json.loads(out.read_text())}


def copy_db(src: Path, dst_dir: Path) -> Path:
    """Databases are opened from copies (shared/ stays byte-identical)."""
    dst = dst_dir / src.name
    if not dst.exists():
        shutil.copyfile(src, dst)
    return dst
