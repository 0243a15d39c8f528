#!/usr/bin/env python3
"""Checks the user guide (docs/src) and README.md: links and anchors, and runnable snippets.

    python3 .ci/doc_snippets.py links
    SFPMAP_BIN=... SFPMAP_PYTHON=... SFPMAP_SHARED_DATA=... python3 .ci/doc_snippets.py run [PAGE ...]

`links`: every relative link and `#anchor` in docs/src/**/*.md and README.md must resolve to a
file, and an anchor to a heading of the target page (as mdBook and GitHub make heading ids).
Pages that `{{#include}}` another file get that file's headings; the included file's own links
are checked as the book renders them, from the including page.

`run`: the fenced blocks ```sh and ```python of every page and of README.md run, per page in
order, in one scratch folder per page (the convention is on docs/src/contributing.md, "Docs and
their snippets"). A failure prints `page:line`, the exit status and the output's tail;
SFPMAP_DOCS_VERBOSE=1 prints every block's. Pages named on the command line (a path suffix,
e.g. `remote.md`) run alone.

Exit status 0 when everything passed, 1 otherwise. Python 3.8+, standard library only.
"""

import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
DOCS_SRC = ROOT / "docs" / "src"
TAIL_LINES = 40
TIMEOUT_S = int(os.environ.get("SFPMAP_DOCS_SNIPPET_TIMEOUT", "600"))

FENCE = re.compile(r"^ {0,3}(`{3,}|~{3,})\s*([^\s`]*)([^`]*)$")
CWD_DIRECTIVE = re.compile(r"^\s*<!--\s*snippet-cwd:\s*(.+?)\s*-->\s*$")
INCLUDE = re.compile(r"\{\{#include\s+([^}\s]+)\s*\}\}")
INLINE_LINK = re.compile(r"!?\[(?:[^\[\]]|\[[^\]]*\])*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
REFERENCE_DEF = re.compile(r"^ {0,3}\[[^\]]+\]:\s*<?(\S+?)>?(?:\s+\"[^\"]*\")?\s*$")
HEADING = re.compile(r"^ {0,3}(#{1,6})\s+(.*?)\s*#*\s*$")
SCHEME = re.compile(r"^[a-zA-Z][a-zA-Z0-9+.-]*:")


def pages():
    """README.md, then the guide's pages in a stable order (paths relative to ROOT)."""
    found = [ROOT / "README.md"]
    found += sorted(DOCS_SRC.rglob("*.md"))
    return found


def rel(path):
    try:
        return str(Path(path).resolve().relative_to(ROOT))
    except ValueError:
        return str(path)


def expand_includes(path, text, depth=0):
    """mdBook's {{#include FILE}} (whole files only), relative to the including page."""
    if depth > 4:
        return text

    def include(m):
        target = (path.parent / m.group(1)).resolve()
        if not target.is_file():
            return m.group(0)
        return expand_includes(target, target.read_text(encoding="utf-8"), depth + 1)

    return INCLUDE.sub(include, text)


def fence_info(line):
    """(marker, language, attributes) of a fence line, or None."""
    m = FENCE.match(line)
    if not m:
        return None
    marker, word, rest = m.group(1), m.group(2), m.group(3).strip()
    parts = [p for p in re.split(r"[,\s]+", (word + " " + rest).strip()) if p]
    lang = parts[0].lower() if parts else ""
    return marker, lang, set(p.lower() for p in parts[1:])


def prose_lines(text, keep_code_spans=False):
    """(line number, line) outside fenced code blocks, with code spans blanked out unless
    `keep_code_spans` (headings: their code spans are part of their id)."""
    fence = None
    for number, line in enumerate(text.split("\n"), 1):
        info = fence_info(line)
        if fence is None:
            if info:
                fence = info[0]
                continue
            yield number, line if keep_code_spans else strip_code_spans(line)
        elif line.strip().startswith(fence[0]) and set(line.strip()) <= {fence[0][0]} \
                and len(line.strip()) >= len(fence):
            fence = None


def strip_code_spans(line):
    out, i = [], 0
    while i < len(line):
        if line[i] == "`":
            j = i
            while j < len(line) and line[j] == "`":
                j += 1
            run = line[i:j]
            end = line.find(run, j)
            # A closing run must be exactly as long as the opening one.
            while end != -1 and end + len(run) < len(line) and line[end + len(run)] == "`":
                end = line.find(run, end + len(run) + 1)
            if end == -1:
                out.append(run)
                i = j
                continue
            out.append(" " * (end + len(run) - i))
            i = end + len(run)
        else:
            out.append(line[i])
            i += 1
    return "".join(out)


def heading_id(text):
    """The id mdBook (and GitHub) give a heading: its text, lower case, spaces to '-',
    everything but letters, digits, '-' and '_' dropped."""
    text = re.sub(r"!?\[([^\]]*)\]\([^)]*\)", r"\1", text)  # links: their text
    text = re.sub(r"<[^>]+>", "", text)  # inline HTML tags
    text = text.replace("`", "")
    text = re.sub(r"(\*\*|__|\*)", "", text)
    out = []
    for ch in text.strip():
        if ch.isalnum() or ch in "-_":
            out.append(ch.lower())
        elif ch.isspace():
            out.append("-")
    return "".join(out)


def anchors_of(path, cache={}):
    path = path.resolve()
    if path not in cache:
        text = expand_includes(path, path.read_text(encoding="utf-8"))
        ids, seen = set(), {}
        for _, line in prose_lines(text, keep_code_spans=True):
            m = HEADING.match(line)
            if not m:
                continue
            base = heading_id(m.group(2))
            n = seen.get(base, 0)
            seen[base] = n + 1
            ids.add(base if n == 0 else f"{base}-{n}")
        # Explicit anchors: <a id="..."> / <a name="...">.
        ids.update(re.findall(r"<a\s+(?:id|name)=\"([^\"]+)\"", text))
        cache[path] = ids
    return cache[path]


def check_links():
    broken = 0
    checked = 0
    for page in pages():
        text = page.read_text(encoding="utf-8")
        sources = [(page, text)]
        # Included files are rendered as part of this page: check their links from here.
        for m in INCLUDE.finditer(text):
            target = (page.parent / m.group(1)).resolve()
            if not target.is_file():
                line = text[: m.start()].count("\n") + 1
                print(f"{rel(page)}:{line}: broken include {m.group(1)}")
                broken += 1
            else:
                sources.append((target, target.read_text(encoding="utf-8")))
        for source, body in sources:
            for number, line in prose_lines(body):
                targets = [m.group(1) for m in INLINE_LINK.finditer(line)]
                m = REFERENCE_DEF.match(line)
                if m:
                    targets.append(m.group(1))
                for target in targets:
                    checked += 1
                    if not link_ok(page, target):
                        print(f"{rel(source)}:{number}: broken link {target}")
                        broken += 1
    print(f"links: {checked} checked, {broken} broken")
    return broken == 0


def link_ok(page, target):
    if SCHEME.match(target) or target.startswith("//"):
        return True  # external: not checked here
    path_part, _, anchor = target.partition("#")
    if path_part:
        resolved = (page.parent / path_part).resolve()
        if not resolved.exists():
            return False
    else:
        resolved = page.resolve()
    if not anchor:
        return True
    if resolved.is_dir() or resolved.suffix != ".md":
        return False  # an anchor into something that is not a page
    return anchor in anchors_of(resolved)


def snippets(page):
    """Runnable blocks of a page: (line of the fence, kind 'sh' | 'python', code, cwd or None)."""
    lines = page.read_text(encoding="utf-8").split("\n")
    out, i = [], 0
    while i < len(lines):
        info = fence_info(lines[i])
        if not info:
            i += 1
            continue
        marker, lang, attrs = info
        start = i
        body = []
        i += 1
        while i < len(lines):
            s = lines[i].strip()
            if s.startswith(marker[0] * len(marker)) and set(s) <= {marker[0]}:
                break
            body.append(lines[i])
            i += 1
        i += 1
        kind = {"sh": "sh", "bash": "sh", "shell": "sh", "python": "python", "py": "python"}.get(lang)
        if kind is None or "ignore" in attrs:
            continue
        cwd = None
        if start > 0:
            m = CWD_DIRECTIVE.match(lines[start - 1])
            if m:
                cwd = m.group(1)
        out.append((start + 1, kind, "\n".join(body) + "\n", cwd))
    return out


def tail(output):
    lines = output.rstrip("\n").split("\n")
    return "\n".join("    " + line for line in lines[-TAIL_LINES:])


def run_snippets(only):
    errors = []
    binary = os.environ.get("SFPMAP_BIN", "")
    shared = os.environ.get("SFPMAP_SHARED_DATA", "")
    python = os.environ.get("SFPMAP_PYTHON", "")
    if not binary or not os.access(binary, os.X_OK) or not os.path.isabs(binary):
        print(f"SFPMAP_BIN must be the absolute path of an sfpmap executable (is {binary!r})")
        return False
    if not shared or not os.path.isdir(shared) or not os.path.isabs(shared):
        print(f"SFPMAP_SHARED_DATA must be the absolute path of the shared data folder (is {shared!r})")
        return False
    if python and not os.access(python, os.X_OK):
        print(f"SFPMAP_PYTHON is not an executable: {python!r}")
        return False

    # sfpmap first on PATH: the binary under test, whatever its file name.
    bindir = tempfile.mkdtemp(prefix="sfpmap-docs-bin-")
    os.symlink(binary, os.path.join(bindir, "sfpmap"))
    scripts = tempfile.mkdtemp(prefix="sfpmap-docs-scripts-")
    started = time.time()
    ran = not_run = 0
    timings = []
    try:
        for page in pages():
            if only and not any(rel(page).endswith(o) for o in only):
                continue
            blocks = snippets(page)
            if not blocks:
                continue
            scratch = tempfile.mkdtemp(prefix="sfpmap-docs-")
            tmp = os.path.join(scratch, ".tmp")
            os.mkdir(tmp)
            env = dict(os.environ)
            env.update(
                PATH=bindir + os.pathsep + env.get("PATH", ""),
                SHARED=shared,
                SFPMAP_SHARED_DATA=shared,
                TMPDIR=tmp,
                PYTHONDONTWRITEBYTECODE="1",
            )
            page_start = time.time()
            failed_here = False
            for number, (line, kind, code, cwd) in enumerate(blocks):
                where = f"{rel(page)}:{line}"
                if failed_here:
                    print(f"{where}: not run (an earlier block of the page failed)")
                    continue
                if kind == "python" and not python:
                    print(f"{where}: python snippet not run: SFPMAP_PYTHON is not set")
                    errors.append(where)
                    not_run += 1
                    continue
                script = os.path.join(scripts, f"{len(timings)}-{number}.{'sh' if kind == 'sh' else 'py'}")
                with open(script, "w", encoding="utf-8") as f:
                    f.write("set -euo pipefail\n" + code if kind == "sh" else code)
                command = ["bash", script] if kind == "sh" else [python, script]
                workdir = os.path.expandvars(cwd.replace("$SHARED", shared)) if cwd else scratch
                block_start = time.time()
                try:
                    done = subprocess.run(command, cwd=workdir, env=env, stdin=subprocess.DEVNULL,
                                          stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                          timeout=TIMEOUT_S)
                    status, output = done.returncode, done.stdout.decode("utf-8", "replace")
                except subprocess.TimeoutExpired as e:
                    status = f"timeout after {TIMEOUT_S} s"
                    output = (e.stdout or b"").decode("utf-8", "replace")
                seconds = time.time() - block_start
                ran += 1
                if status != 0:
                    print(f"{where}: {kind} snippet failed (exit {status}, {seconds:.1f} s); last lines:")
                    print(tail(output))
                    errors.append(where)
                    failed_here = True
                else:
                    print(f"{where}: ok ({kind}, {seconds:.1f} s)")
                    if os.environ.get("SFPMAP_DOCS_VERBOSE"):
                        print(tail(output))
            timings.append((rel(page), time.time() - page_start))
            shutil.rmtree(scratch, ignore_errors=True)
    finally:
        shutil.rmtree(bindir, ignore_errors=True)
        shutil.rmtree(scripts, ignore_errors=True)

    # Snippets write only into their scratch folder: nothing in the shared data may be newer.
    written = [os.path.join(d, f) for d, _, files in os.walk(shared) for f in files
               if os.lstat(os.path.join(d, f)).st_mtime >= started]
    for path in written[:20]:
        print(f"a snippet wrote into the shared data folder: {path}")
    if written:
        errors.append("shared data written")

    for name, seconds in timings:
        print(f"  {seconds:7.1f} s  {name}")
    print(f"snippets: {ran} run, {not_run} not run, {len(errors)} failed or missing, "
          f"{time.time() - started:.0f} s")
    return not errors


def main(argv):
    if len(argv) < 2 or argv[1] not in ("links", "run"):
        print(__doc__.strip().split("\n\n")[1])
        return 2
    ok = check_links() if argv[1] == "links" else run_snippets(argv[2:])
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main(sys.argv))
