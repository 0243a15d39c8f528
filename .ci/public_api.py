#!/usr/bin/env python3
"""The library's public API as a sorted list, committed in docs/public-api.txt.

    python3 .ci/public_api.py            # rewrites docs/public-api.txt
    python3 .ci/public_api.py --check    # fails when the API differs from the committed list

Stable rustdoc has no JSON output (`cargo public-api` needs nightly), so this reads the HTML of
`cargo doc --no-deps -p sfpmap`: `all.html` lists every public item by path; each module's
`index.html` lists its submodules and, under "Re-exports", the `pub use` of an item that stays
public at another path as well (a second path to one item, or another crate's item). One line
per item, `kind path`; a re-export is `use path = target`. An item public only with the
`fuzzing` feature (the fuzz crate's and the tests' hooks) ends in ` [fuzzing]`: the list is
made from two doc builds, every feature, and every feature but `fuzzing`.

The list is at the level of items (modules, types, traits, functions, constants, statics,
macros): a new method or field of a listed type does not change it.

The doc builds go to `$CARGO_TARGET_DIR/doc` (default `target/doc`), as `.ci/run` sets it.
Python 3.8+, standard library only.
"""

import html
import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
LIST = ROOT / "docs" / "public-api.txt"
CRATE = "sfpmap"
REGENERATE = "python3 .ci/public_api.py"
HEADER = f"""\
# The public API of the `{CRATE}` library: one line per public item, `kind path`; a `pub use`
# that leaves an item public at two paths is `use path = target`; ` [fuzzing]`: only with the
# `fuzzing` feature. Generated from rustdoc's HTML by `{REGENERATE}`, checked in CI
# (`{REGENERATE} --check`): a change here is a change of the public API, said in its commit.
"""

# all.html's file names: `struct.Map.html` is a struct.
ITEM_FILE = re.compile(r"^(\w+)\.(\w+)\.html$")
ALL_ITEM = re.compile(r'<li><a href="([^"]+)">([^<]+)</a></li>')
MODULE = re.compile(r'<a class="mod" href="([^"]+)/index\.html" title="mod ([^"]+)"')
REEXPORT = re.compile(r'<dt id="reexport\.[^"]*"><code>(.*?)</code></dt>', re.S)
TAG = re.compile(r"<[^>]+>")


def doc_dir():
    target = os.environ.get("CARGO_TARGET_DIR") or str(ROOT / "target")
    return Path(target) / "doc" / CRATE


def features():
    meta = json.loads(
        subprocess.run(
            ["cargo", "metadata", "--no-deps", "--format-version", "1"],
            cwd=ROOT, check=True, capture_output=True, text=True,
        ).stdout
    )
    package = next(p for p in meta["packages"] if p["name"] == CRATE)
    return sorted(f for f in package["features"] if f != "default")


def build(feature_list):
    """Documents the crate with these features; returns its folder."""
    out = doc_dir()
    # A module made private since the last build would leave its page behind.
    shutil.rmtree(out, ignore_errors=True)
    command = ["cargo", "doc", "--quiet", "--no-deps", "-p", CRATE, "--no-default-features"]
    if feature_list:
        command += ["--features", ",".join(feature_list)]
    # The list is about what is public; the docs' own warnings (broken links) are not its job.
    env = dict(os.environ, RUSTDOCFLAGS=os.environ.get("RUSTDOCFLAGS", "") + " -A warnings")
    result = subprocess.run(command, cwd=ROOT, env=env, capture_output=True, text=True)
    if result.returncode != 0:
        sys.stderr.write(result.stdout + result.stderr)
        sys.exit(f"error: `{' '.join(command)}` failed")
    return out


def items(root):
    """The public API in one doc build: a set of `kind path` lines."""
    lines = set()
    page = (root / "all.html").read_text()
    for href, path in ALL_ITEM.findall(page):
        found = ITEM_FILE.match(href.rsplit("/", 1)[-1])
        if not found:
            sys.exit(f"error: all.html: unexpected link {href}: update .ci/public_api.py")
        lines.add(f"{found.group(1)} {html.unescape(path)}")
    # Modules and re-exports, from the crate's page down through every public module's.
    pending = [(root / "index.html", "")]
    while pending:
        index, module = pending.pop()
        page = index.read_text()
        for code in REEXPORT.findall(page):
            text = html.unescape(TAG.sub("", code)).strip()
            found = re.fullmatch(r"pub use (.+);", text)
            if not found:
                sys.exit(f"error: {index}: unexpected re-export {text!r}: update .ci/public_api.py")
            target = found.group(1)
            name = target.rsplit("::", 1)[-1]
            if " as " in target:
                target, name = target.split(" as ")
            path = f"{module}::{name}" if module else name
            lines.add(f"use {path} = {target}")
        for href, title in MODULE.findall(page):
            path = title.split("::", 1)[1]
            # The module's own children only: a link to a module elsewhere is not one.
            parent = path.rsplit("::", 1)[0] if "::" in path else ""
            if parent == module and f"mod {path}" not in lines:
                lines.add(f"mod {path}")
                pending.append((index.parent / href / "index.html", path))
    return lines


def hidden_items():
    """`#[doc(hidden)]` in the library: rustdoc leaves such an item out of the list, public or not."""
    found = []
    for path in sorted((ROOT / "src").rglob("*.rs")):
        for n, line in enumerate(path.read_text().splitlines(), 1):
            if re.search(r"#\[doc\(hidden\)\]", line):
                found.append(f"{path.relative_to(ROOT)}:{n}")
    return found


def public_api():
    hidden = hidden_items()
    if hidden:
        sys.exit(
            "error: #[doc(hidden)] keeps an item out of the list without making it private:"
            " gate it behind a feature (`fuzzing`) or make it pub(crate)\n  " + "\n  ".join(hidden)
        )
    every = features()
    with_fuzzing = items(build(every))
    without = items(build([f for f in every if f != "fuzzing"]))
    if not without <= with_fuzzing:
        extra = "\n".join(sorted(without - with_fuzzing))
        sys.exit(f"error: public only without `fuzzing`:\n{extra}")
    lines = [line if line in without else f"{line} [fuzzing]" for line in with_fuzzing]
    # Sorted by path, then kind, so a module's items stay together.
    return sorted(lines, key=lambda line: (line.split(" ")[1], line))


def main():
    check = sys.argv[1:] == ["--check"]
    if sys.argv[1:] and not check:
        sys.exit(__doc__)
    lines = public_api()
    text = HEADER + "".join(f"{line}\n" for line in lines)
    kinds = {}
    for line in lines:
        kind = line.split(" ")[0]
        kinds[kind] = kinds.get(kind, 0) + 1
    summary = ", ".join(f"{n} {kind}" for kind, n in sorted(kinds.items()))
    if not check:
        LIST.write_text(text)
        print(f"{LIST.relative_to(ROOT)}: {len(lines)} lines ({summary})")
        return
    committed = LIST.read_text().splitlines() if LIST.exists() else []
    old = {line for line in committed if line and not line.startswith("#")}
    new = set(lines)
    if LIST.exists() and committed == text.splitlines():
        print(f"public API unchanged: {len(lines)} lines ({summary})")
        return
    for line in sorted(old - new):
        print(f"- {line}")
    for line in sorted(new - old):
        print(f"+ {line}")
    sys.stdout.flush()
    sys.exit(
        f"error: public API changed ({len(old)} -> {len(new)} lines; - gone, + new): regenerate"
        f" {LIST.relative_to(ROOT)} with `{REGENERATE}`, and say why in the commit"
    )


if __name__ == "__main__":
    main()
