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
