#!/usr/bin/env python3
"""Checks the user guide (docs/src) and README.md: links and anchors, and runnable snippets.

    python3 .ci/doc_snippets.py links
    python3 .ci/doc_snippets.py rust
    SFPMAP_BIN=... SFPMAP_PYTHON=... SFPMAP_SHARED_DATA=... python3 .ci/doc_snippets.py run [PAGE ...]

`links`: every relative link and `#anchor` in docs/src/**/*.md and README.md must resolve to a
file, and an anchor to a heading of the target page (as mdBook and GitHub make heading ids).
Pages that `{{#include}}` another file get that file's headings; the included file's own links
are checked as the book renders them, from the including page.

`rust`: a page with a ```rust block not marked `ignore` must be a doctest of the crate, i.e.
included by src/lib.rs (`include_str!("../docs/src/PAGE.md")`); otherwise its code would never
be compiled.

`run`: the fenced blocks ```sh and ```python of every page and of README.md run, per page in
order, in one scratch folder per page (the convention is on docs/src/contributing.md, "Docs and
their snippets"). A failure prints `page:line`, the exit status and the output's tail;
SFPMAP_DOCS_VERBOSE=1 prints every block's. Pages named on the command line (a path suffix,
e.g. `remote.md`) run alone. Each block runs in a process group of its own, killed whole on
timeout; a block that leaves a process running fails. A `<!-- snippet-cwd: $SHARED/... -->`
must name a folder under the shared data. The run fails when a snippet changed anything under
$SFPMAP_SHARED_DATA (an entry added, removed, or of another type, size, mtime or inode) or the
repository (`git status --porcelain`, with the size and mtime of each file it lists), and when
no block or fewer blocks ran than were found.

Exit status 0 when everything passed, 1 otherwise. Python 3.8+, standard library only.
"""

import os
import re
import shutil
import signal
import stat
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
RUST_INCLUDE = re.compile(r'include_str!\(\s*"([^"]+\.md)"\s*\)')
SHARED_CWD = re.compile(r"^(?:\$SHARED|\$\{SHARED\})(/[^$`]*)?$")


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


ANCHORS = {}  # resolved page -> its heading ids


def anchors_of(path, cache=None):
    cache = ANCHORS if cache is None else cache
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


def fenced_blocks(page):
    """Every fenced block of a page: (line of the fence, language, attributes, code, the
    `snippet-cwd` directive right before it or None)."""
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
        cwd = None
        if start > 0:
            m = CWD_DIRECTIVE.match(lines[start - 1])
            if m:
                cwd = m.group(1)
        out.append((start + 1, lang, attrs, "\n".join(body) + "\n", cwd))
    return out


def snippets(page):
    """Runnable blocks of a page: (line of the fence, kind 'sh' | 'python', code, cwd or None)."""
    out = []
    for line, lang, attrs, code, cwd in fenced_blocks(page):
        kind = {"sh": "sh", "bash": "sh", "shell": "sh", "python": "python", "py": "python"}.get(lang)
        if kind is None or "ignore" in attrs:
            continue
        out.append((line, kind, code, cwd))
    return out


def doctest_pages():
    """The pages src/lib.rs includes (`include_str!("../docs/src/PAGE.md")`), resolved."""
    lib = ROOT / "src" / "lib.rs"
    text = lib.read_text(encoding="utf-8") if lib.is_file() else ""
    return {(lib.parent / m.group(1)).resolve() for m in RUST_INCLUDE.finditer(text)}


def check_rust_pages():
    """A ```rust block not marked `ignore` is only ever compiled as a doctest: its page must be
    included by src/lib.rs."""
    included = doctest_pages()
    missing = 0
    for page in pages():
        if page.resolve() in included:
            continue
        for line, lang, attrs, _, _ in fenced_blocks(page):
            if lang == "rust" and "ignore" not in attrs:
                print(f"{rel(page)}:{line}: a ```rust block that no test compiles: include "
                      f"{rel(page)} in src/lib.rs as a doctest (like GuideLibrary for "
                      f"docs/src/library.md), or mark the block `rust,ignore`")
                missing += 1
    print(f"rust blocks: {len(included)} page(s) included by src/lib.rs, "
          f"{missing} block(s) on other pages")
    return missing == 0


def snippet_cwd(cwd, shared, where):
    """The folder a `<!-- snippet-cwd: ... -->` names, or (None, why) when it does not name an
    existing folder under the shared data."""
    m = SHARED_CWD.match(cwd)
    if not m:
        return None, (f"{where}: snippet-cwd {cwd!r} refused: it must name a folder under "
                      f"$SHARED (e.g. $SHARED/scenes/south-building)")
    folder = os.path.realpath(shared + (m.group(1) or ""))
    root = os.path.realpath(shared)
    if os.path.commonpath([folder, root]) != root:
        return None, f"{where}: snippet-cwd {cwd!r} refused: {folder} is outside $SHARED ({root})"
    if not os.path.isdir(folder):
        return None, f"{where}: snippet-cwd {cwd!r} refused: {folder} is not a folder"
    return folder, None


def snapshot(root):
    """Every entry under `root` (itself included, links not followed): relative path ->
    (type, size, mtime_ns, inode)."""
    def entry(path):
        st = os.lstat(path)
        kind = ("dir" if stat.S_ISDIR(st.st_mode) else "file" if stat.S_ISREG(st.st_mode)
                else "symlink" if stat.S_ISLNK(st.st_mode) else "other")
        return kind, st.st_size, st.st_mtime_ns, st.st_ino

    out = {".": entry(root)}
    for d, dirs, files in os.walk(root):
        for name in dirs + files:
            path = os.path.join(d, name)
            try:
                out[os.path.relpath(path, root)] = entry(path)
            except FileNotFoundError:
                pass  # gone between the listing and the lstat: the later snapshot says so
    return out


def snapshot_changes(before, after):
    """Lines naming what differs between two snapshots."""
    out = []
    for path in sorted(set(before) | set(after)):
        a, b = before.get(path), after.get(path)
        if a == b:
            continue
        if a is None:
            out.append(f"new {b[0]}: {path}")
        elif b is None:
            out.append(f"deleted {a[0]}: {path}")
        else:
            what = [name for name, x, y in zip(("type", "size", "mtime", "inode"), a, b) if x != y]
            out.append(f"changed ({', '.join(what)}): {path}")
    return out


def git_status():
    """`git status --porcelain` of the repository (untracked files listed one by one) as path
    -> (status, size, mtime_ns) of the file, so that a snippet writing into a file that was
    already modified shows too; None when ROOT is not a git work tree. --no-optional-locks:
    never takes the index lock."""
    try:
        done = subprocess.run(["git", "--no-optional-locks", "status", "--porcelain", "-z",
                               "--untracked-files=all"], cwd=ROOT, stdin=subprocess.DEVNULL,
                              stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, check=True)
    except (OSError, subprocess.CalledProcessError):
        return None
    out = {}
    records = done.stdout.decode("utf-8", "replace").split("\0")
    i = 0
    while i < len(records):
        record = records[i]
        i += 1
        if not record:
            continue
        if record[0] in "RC":
            i += 1  # a rename's or copy's source path follows
        try:
            st = os.lstat(ROOT / record[3:])
            out[record[3:]] = (record[:2], st.st_size, st.st_mtime_ns)
        except OSError:
            out[record[3:]] = (record[:2], None, None)
    return out


def group_alive(pgid):
    try:
        os.killpg(pgid, 0)
        return True
    except ProcessLookupError:
        return False
    except PermissionError:
        return True


def run_block(command, workdir, env, log_path):
    """Runs one snippet in a process group of its own; the whole group is killed on timeout,
    and so is anything the snippet left running (reported). Returns (status, output,
    leftover): status is the exit code or a text."""
    with open(log_path, "wb") as log:
        proc = subprocess.Popen(command, cwd=workdir, env=env, stdin=subprocess.DEVNULL,
                                stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
        pgid = proc.pid  # start_new_session: the child leads a new session and process group
        try:
            status = proc.wait(timeout=TIMEOUT_S)
        except subprocess.TimeoutExpired:
            status = f"timeout after {TIMEOUT_S} s; its process group was killed"
            try:
                os.killpg(pgid, signal.SIGKILL)
            except (ProcessLookupError, PermissionError):
                pass
            proc.wait()
        # A trap's `kill` may take a moment to land: give the group a second to empty.
        leftover = False
        deadline = time.time() + 2
        while group_alive(pgid) and time.time() < deadline:
            time.sleep(0.05)
        if group_alive(pgid):
            leftover = True
            try:
                os.killpg(pgid, signal.SIGKILL)
            except (ProcessLookupError, PermissionError):
                pass
    with open(log_path, "rb") as log:
        output = log.read().decode("utf-8", "replace")
    return status, output, leftover


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

    selected = [(page, snippets(page)) for page in pages()
                if not only or any(rel(page).endswith(o) for o in only)]
    selected = [(page, blocks) for page, blocks in selected if blocks]
    found = sum(len(blocks) for _, blocks in selected)
    # Every snippet-cwd is checked before anything runs.
    refused = []
    for page, blocks in selected:
        for line, _, _, cwd in blocks:
            if cwd is not None:
                _, why = snippet_cwd(cwd, shared, f"{rel(page)}:{line}")
                if why:
                    refused.append(why)
    for why in refused:
        print(why)
    if refused:
        return False

    shared_before = snapshot(shared)
    repo_before = git_status()
    if repo_before is None:
        print(f"note: {ROOT} is not a git work tree: the check that snippets leave the "
              "repository alone is skipped")

    # sfpmap first on PATH: the binary under test, whatever its file name.
    bindir = tempfile.mkdtemp(prefix="sfpmap-docs-bin-")
    os.symlink(binary, os.path.join(bindir, "sfpmap"))
    scripts = tempfile.mkdtemp(prefix="sfpmap-docs-scripts-")
    started = time.time()
    ran = not_run = 0
    timings = []
    try:
        for page, blocks in selected:
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
                base = os.path.join(scripts, f"{len(timings)}-{number}")
                script = f"{base}.{'sh' if kind == 'sh' else 'py'}"
                with open(script, "w", encoding="utf-8") as f:
                    f.write("set -euo pipefail\n" + code if kind == "sh" else code)
                command = ["bash", script] if kind == "sh" else [python, script]
                workdir = snippet_cwd(cwd, shared, where)[0] if cwd else scratch
                block_start = time.time()
                status, output, leftover = run_block(command, workdir, env, base + ".log")
                seconds = time.time() - block_start
                ran += 1
                if status != 0:
                    print(f"{where}: {kind} snippet failed (exit {status}, {seconds:.1f} s); last lines:")
                    print(tail(output))
                    errors.append(where)
                    failed_here = True
                elif leftover:
                    print(f"{where}: {kind} snippet left processes running (killed): end what "
                          f"it starts, e.g. with `trap 'kill $pid' EXIT`; last lines:")
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

    # Snippets write only into their scratch folder: the shared data and the repository are
    # as they were.
    changes = snapshot_changes(shared_before, snapshot(shared))
    for change in changes[:50]:
        print(f"a snippet changed the shared data ({shared}): {change}")
    if len(changes) > 50:
        print(f"... and {len(changes) - 50} more changes in the shared data")
    if changes:
        errors.append("shared data changed")
    if repo_before is not None:
        repo_after = git_status()
        if repo_after is None:
            print("git status failed after the snippets")
            errors.append("repository status")
        else:
            changed = [path for path in sorted(set(repo_before) | set(repo_after))
                       if repo_before.get(path) != repo_after.get(path)]
            for path in changed:
                was = repo_before.get(path, ("  ",))[0]
                now = repo_after.get(path, ("  ",))[0]
                how = "written" if was == now else f"git status `{was}` -> `{now}`"
                print(f"a snippet changed the repository: {path} ({how})")
            if changed:
                errors.append("repository changed")

    if ran == 0 or ran < found:
        print(f"snippets: {found} runnable blocks found, only {ran} run")
        errors.append("blocks not run")

    for name, seconds in timings:
        print(f"  {seconds:7.1f} s  {name}")
    print(f"snippets: {found} found, {ran} run, {not_run} not run, {len(errors)} failed or missing, "
          f"{time.time() - started:.0f} s")
    return not errors


def main(argv):
    checks = {"links": check_links, "rust": check_rust_pages}
    if len(argv) < 2 or argv[1] not in ("links", "rust", "run"):
        print(__doc__.strip().split("\n\n")[1])
        return 2
    if argv[1] == "run":
        ok = run_snippets(argv[2:])
    else:
        ok = checks[argv[1]]()
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main(sys.argv))
