//! The committed CLI reference (docs/src/reference/cli.md, docs/man/man1/*.1) is what the binary
//! generates now, `generate-reference` writes and removes only what it should, and
//! `sfpmap completions SHELL` prints a script for each shell.

use crate::run::sfpmap;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::Output;

const REGENERATE: &str = "cargo run --release -- generate-reference --out docs";
const MARKDOWN_PAGE: &str = "src/reference/cli.md";
const MAN_DIR: &str = "man/man1";
/// The commands that are hidden: no completion, no section, no man page.
const HIDDEN: [&str; 2] = ["generate-reference", "bench-pose"];

fn committed_docs() -> PathBuf {
    crate::shared_data::repo_root().join("docs")
}

/// An empty folder that `generate-reference` accepts as the guide's: it holds a book.toml.
fn docs_folder() -> tempfile::TempDir {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("book.toml"), "[book]\n").unwrap();
    dir
}

/// `sfpmap -q generate-reference --out DIR`.
fn generate(dir: &Path) -> Output {
    sfpmap(&["-q", "generate-reference", "--out", dir.to_str().unwrap()])
}

#[test]
fn completions_name_real_subcommands_for_each_shell() {
    for shell in ["bash", "zsh", "fish", "elvish", "powershell"] {
        let o = sfpmap(&["completions", shell]);
        assert!(
            o.status.success(),
            "sfpmap completions {shell}: {}",
            String::from_utf8_lossy(&o.stderr)
        );
        let script = String::from_utf8(o.stdout).expect("a UTF-8 script");
        assert!(!script.trim().is_empty(), "{shell}: empty script");
        for sub in ["info", "slice", "verify", "completions"] {
            assert!(
                script.contains(sub),
                "{shell}: the script never names `{sub}`"
            );
        }
        // Hidden commands stay out of completion.
        for hidden in HIDDEN {
            assert!(!script.contains(hidden), "{shell}: names `{hidden}`");
        }
    }
}

#[test]
fn completions_refuse_an_unknown_shell() {
    let o = sfpmap(&["completions", "tcsh"]);
    assert!(!o.status.success());
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(stderr.contains("tcsh"), "{stderr}");
}

/// The markdown page cut at its `## \`sfpmap …\`` headings: (command, section text) in page
/// order; what comes before the first heading (title, note, contents) under "".
fn sections(page: &str) -> Vec<(String, String)> {
    let mut out = vec![(String::new(), String::new())];
    for line in page.split_inclusive('\n') {
        if let Some(name) = line
            .strip_prefix("## `")
            .and_then(|l| l.trim_end().strip_suffix('`'))
        {
            out.push((name.to_owned(), String::new()));
        }
        out.last_mut().unwrap().1.push_str(line);
    }
    out
}

/// The first line where `committed` and `generated` differ, for the failure message.
fn first_difference(committed: &str, generated: &str) -> String {
    let (mut c, mut g) = (committed.lines(), generated.lines());
    for n in 1.. {
        match (c.next(), g.next()) {
            (Some(a), Some(b)) if a == b => continue,
            (None, None) => break,
            (a, b) => {
                return format!(
                "first difference at line {n} of the section:\n  committed: {}\n  generated: {}",
                a.unwrap_or("(end)"),
                b.unwrap_or("(end)")
            )
            }
        }
    }
    "they differ in line endings".to_owned()
}

fn stale(file: &str, command: &str, detail: &str) -> String {
    format!("docs/{file} is stale for '{command}': regenerate with '{REGENERATE}'\n{detail}")
}

/// Compares the markdown page section by section; `Err` names the stale command: a command
/// added or gone, else the most specific changed one (a subcommand's new help also changes
/// its parent's list of subcommands, and the parent's section comes first).
fn check_markdown(committed: &str, generated: &str) -> Result<(), String> {
    let old: BTreeMap<String, String> = sections(committed).into_iter().collect();
    let new = sections(generated);
    let new_names: Vec<&str> = new.iter().map(|(n, _)| n.as_str()).collect();
    if let Some((added, _)) = new.iter().find(|(n, _)| !old.contains_key(n)) {
        return Err(stale(
            MARKDOWN_PAGE,
            added,
            "the page has no section for it",
        ));
    }
    if let Some(gone) = old.keys().find(|n| !new_names.contains(&n.as_str())) {
        return Err(stale(MARKDOWN_PAGE, gone, "the command no longer exists"));
    }
    let changed: Vec<&(String, String)> = new
        .iter()
        .filter(|(name, text)| !name.is_empty() && old[name] != *text)
        .collect();
    let parent_of = |a: &str, b: &str| b.starts_with(&format!("{a} "));
    if let Some((name, text)) = changed
        .iter()
        .find(|(a, _)| !changed.iter().any(|(b, _)| parent_of(a, b)))
    {
        return Err(stale(
            MARKDOWN_PAGE,
            name,
            &first_difference(&old[name], text),
        ));
    }
    if committed != generated {
        // Each section the same: the title, note, contents or order changed.
        let detail = first_difference(&old[""], &new[0].1);
        return Err(stale(MARKDOWN_PAGE, "sfpmap", &detail));
    }
    Ok(())
}

fn man_pages(dir: &Path) -> BTreeMap<String, String> {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return BTreeMap::new();
    };
    entries
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "1"))
        .map(|p| {
            let name = p.file_name().unwrap().to_string_lossy().into_owned();
            (name, std::fs::read_to_string(&p).unwrap())
        })
        .collect()
}

/// Compares the man pages; `Err` names the first stale command. `commands` maps a page's
/// file name to its command (`sfpmap-export-colmap.1` → `sfpmap export-colmap`).
fn check_man(
    committed: &BTreeMap<String, String>,
    generated: &BTreeMap<String, String>,
    commands: &BTreeMap<String, String>,
) -> Result<(), String> {
    let command = |file: &str| {
        commands
            .get(file)
            .cloned()
            .unwrap_or_else(|| file.trim_end_matches(".1").replace('-', " "))
    };
    for (file, page) in generated {
        let path = format!("{MAN_DIR}/{file}");
        match committed.get(file) {
            None => return Err(stale(&path, &command(file), "the page is missing")),
            Some(old) if old != page => {
                return Err(stale(&path, &command(file), &first_difference(old, page)))
            }
            Some(_) => {}
        }
    }
    if let Some(file) = committed.keys().find(|f| !generated.contains_key(*f)) {
        let detail = "the command no longer exists (regenerating removes the page)";
        return Err(stale(&format!("{MAN_DIR}/{file}"), &command(file), detail));
    }
    Ok(())
}

// The reference documents the full CLI: a build without some of its features lacks commands.
#[cfg(all(
    feature = "colmap",
    feature = "localize",
    feature = "onnx",
    feature = "mcap"
))]
#[test]
fn committed_reference_is_generated() {
    let out = docs_folder();
    let o = sfpmap(&["generate-reference", "--out", out.path().to_str().unwrap()]);
    assert!(
        o.status.success(),
        "sfpmap generate-reference: {}",
        String::from_utf8_lossy(&o.stderr)
    );
    let docs = committed_docs();
    let generated = std::fs::read_to_string(out.path().join(MARKDOWN_PAGE)).unwrap();
    let committed = std::fs::read_to_string(docs.join(MARKDOWN_PAGE)).unwrap_or_default();
    if let Err(message) = check_markdown(&committed, &generated) {
        panic!("{message}");
    }
    let commands: BTreeMap<String, String> = sections(&generated)
        .into_iter()
        .filter(|(name, _)| !name.is_empty())
        .map(|(name, _)| (format!("{}.1", name.replace(' ', "-")), name))
        .collect();
    let generated_man = man_pages(&out.path().join(MAN_DIR));
    assert!(generated_man.contains_key("sfpmap.1"), "{generated_man:?}");
    if let Err(message) = check_man(&man_pages(&docs.join(MAN_DIR)), &generated_man, &commands) {
        panic!("{message}");
    }
}

#[test]
fn generate_reference_is_deterministic_and_hidden() {
    let (a, b) = (docs_folder(), docs_folder());
    for dir in [&a, &b] {
        let o = sfpmap(&[
            "--quiet",
            "generate-reference",
            "--out",
            dir.path().to_str().unwrap(),
        ]);
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        assert!(o.stderr.is_empty() && o.stdout.is_empty());
    }
    let page =
        |d: &tempfile::TempDir| std::fs::read_to_string(d.path().join(MARKDOWN_PAGE)).unwrap();
    assert_eq!(page(&a), page(&b));
    let man = man_pages(&a.path().join(MAN_DIR));
    assert_eq!(man, man_pages(&b.path().join(MAN_DIR)));
    assert!(man.contains_key("sfpmap-info.1"), "{:?}", man.keys());
    // Nothing of the machine it ran on.
    let tmp = std::env::temp_dir();
    let tmp = tmp.to_str().unwrap();
    for (name, text) in std::iter::once(("cli.md".to_owned(), page(&a))).chain(man) {
        assert!(!text.contains(tmp), "{name} names {tmp}");
    }
    // No hidden command: no section of its own, no man page. (`sfpmap info` has both, so
    // the pattern is the one a leaked command would follow.)
    let headings: Vec<String> = sections(&page(&a)).into_iter().map(|(n, _)| n).collect();
    assert!(headings.iter().any(|h| h == "sfpmap info"), "{headings:?}");
    for hidden in HIDDEN {
        let command = format!("sfpmap {hidden}");
        assert!(
            !page(&a).contains(&format!("## `{command}`")),
            "cli.md documents the hidden command `{command}`"
        );
        let file = format!("sfpmap-{hidden}.1");
        assert!(
            !a.path().join(MAN_DIR).join(&file).exists(),
            "a man page documents the hidden command `{command}`"
        );
    }
}

/// A man page as clap_mangen writes them, titled for `command` (`sfpmap-retired`): the
/// generated `sfpmap.1` retitled.
fn generated_page(docs: &Path, command: &str) -> String {
    let root = std::fs::read_to_string(docs.join(MAN_DIR).join("sfpmap.1")).unwrap();
    assert!(root.contains("\n.TH sfpmap 1 "), "{root}");
    root.replacen("\n.TH sfpmap 1 ", &format!("\n.TH {command} 1 "), 1)
}

#[test]
fn generate_reference_removes_only_its_own_stale_pages() {
    let docs = docs_folder();
    let o = generate(docs.path());
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let man = docs.path().join(MAN_DIR);
    // A page generated for a command that no longer exists: removed, also one left in the
    // old flat folder docs/man.
    let stale = man.join("sfpmap-retired.1");
    std::fs::write(&stale, generated_page(docs.path(), "sfpmap-retired")).unwrap();
    let old_layout = docs.path().join("man").join("sfpmap-info.1");
    std::fs::write(&old_layout, generated_page(docs.path(), "sfpmap-info")).unwrap();
    // What is not one of its pages: kept.
    let notes = "\\\" my notes on sfpmap\n.TH sfpmap-notes 1\n";
    let kept = [
        // The name matches, the content is not a generated page.
        (man.join("sfpmap-notes.1"), notes.to_owned()),
        // A generated-looking page under a name clap_mangen never gives sfpmap.
        (
            man.join("sfpmapper.1"),
            generated_page(docs.path(), "sfpmapper"),
        ),
        (
            man.join("sfpmap-Upper.1"),
            generated_page(docs.path(), "sfpmap-Upper"),
        ),
        // The header of another command than the file's name says.
        (
            man.join("sfpmap-mine.1"),
            generated_page(docs.path(), "sfpmap-retired"),
        ),
        (man.join("sfpmap-empty.1"), String::new()),
    ];
    for (path, text) in &kept {
        std::fs::write(path, text).unwrap();
    }
    // A folder with a page's name.
    std::fs::create_dir(man.join("sfpmap-dir.1")).unwrap();
    // A symlink with a stale page's name, to a generated page elsewhere.
    #[cfg(unix)]
    let outside = {
        let outside = tempfile::tempdir().unwrap();
        let target = outside.path().join("sfpmap-linked.1");
        std::fs::write(&target, generated_page(docs.path(), "sfpmap-linked")).unwrap();
        std::os::unix::fs::symlink(&target, man.join("sfpmap-linked.1")).unwrap();
        (outside, target)
    };

    let o = sfpmap(&["generate-reference", "--out", docs.path().to_str().unwrap()]);
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{stderr}");
    assert!(stderr.contains("removed 2 stale man page(s)"), "{stderr}");
    assert!(!stale.exists(), "the stale page is left");
    assert!(
        !old_layout.exists(),
        "the stale page of the old layout is left"
    );
    for (path, text) in &kept {
        assert_eq!(&std::fs::read_to_string(path).unwrap(), text, "{path:?}");
    }
    assert!(man.join("sfpmap-dir.1").is_dir());
    #[cfg(unix)]
    {
        let link = man.join("sfpmap-linked.1");
        assert!(std::fs::symlink_metadata(&link)
            .unwrap()
            .file_type()
            .is_symlink());
        assert!(outside.1.exists());
    }
    // The generated pages themselves are all still there.
    assert!(man.join("sfpmap.1").exists() && man.join("sfpmap-info.1").exists());
}

#[test]
fn generate_reference_refuses_a_folder_without_book_toml() {
    let dir = tempfile::tempdir().unwrap();
    let o = generate(dir.path());
    assert!(!o.status.success());
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(
        stderr.contains(dir.path().to_str().unwrap()) && stderr.contains("book.toml"),
        "{stderr}"
    );
    // Nothing created.
    assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);
}

#[cfg(unix)]
#[test]
fn generate_reference_refuses_symlinked_folders() {
    for folder in ["man", MAN_DIR, "src", "src/reference"] {
        let docs = docs_folder();
        let elsewhere = tempfile::tempdir().unwrap();
        let link = docs.path().join(folder);
        std::fs::create_dir_all(link.parent().unwrap()).unwrap();
        std::os::unix::fs::symlink(elsewhere.path(), &link).unwrap();
        // A page of a retired command where the link points: must stay.
        let victim = elsewhere.path().join("sfpmap-retired.1");
        std::fs::write(&victim, "x").unwrap();
        let o = generate(docs.path());
        assert!(!o.status.success(), "{folder}: accepted");
        let stderr = String::from_utf8_lossy(&o.stderr);
        assert!(
            stderr.contains(link.to_str().unwrap()) && stderr.contains("symlink"),
            "{folder}: {stderr}"
        );
        // Nothing written through the link, nothing removed there.
        let names: Vec<_> = std::fs::read_dir(elsewhere.path())
            .unwrap()
            .map(|e| e.unwrap().file_name())
            .collect();
        assert_eq!(names, ["sfpmap-retired.1"], "{folder}");
    }
}

#[test]
fn generate_reference_errors_name_the_path() {
    // A file where the man folder goes.
    let docs = docs_folder();
    std::fs::write(docs.path().join("man"), "").unwrap();
    let o = generate(docs.path());
    assert!(!o.status.success());
    let stderr = String::from_utf8_lossy(&o.stderr);
    let man = docs.path().join("man");
    assert!(stderr.contains(man.to_str().unwrap()), "{stderr}");
    // A folder where the markdown page goes.
    let docs = docs_folder();
    std::fs::create_dir_all(docs.path().join(MARKDOWN_PAGE)).unwrap();
    let o = generate(docs.path());
    assert!(!o.status.success());
    let stderr = String::from_utf8_lossy(&o.stderr);
    let page = docs.path().join(MARKDOWN_PAGE);
    assert!(stderr.contains(page.to_str().unwrap()), "{stderr}");
}

#[test]
fn a_stale_section_is_named() {
    let page = "# T\n\nintro\n\n## `sfpmap`\n\ntop\n\n## `sfpmap convert`\n\n* `--levels` — old\n";
    assert_eq!(check_markdown(page, page), Ok(()));
    let changed = page.replace("old", "new");
    let err = check_markdown(page, &changed).unwrap_err();
    assert!(
        err.starts_with(&format!(
            "docs/src/reference/cli.md is stale for 'sfpmap convert': regenerate with '{REGENERATE}'"
        )),
        "{err}"
    );
    let added = format!("{page}## `sfpmap slice`\n\nnew\n").replace("top", "top, slice");
    assert!(check_markdown(page, &added)
        .unwrap_err()
        .contains("'sfpmap slice'"));
    assert!(check_markdown(&added, page)
        .unwrap_err()
        .contains("'sfpmap slice'"));
    // The parent's list of subcommands changes with the subcommand's help: the subcommand
    // is named.
    let both = changed.replace("top", "top, new");
    assert!(check_markdown(page, &both)
        .unwrap_err()
        .contains("'sfpmap convert'"));
    let retitled = page.replace("intro", "other");
    assert!(check_markdown(page, &retitled)
        .unwrap_err()
        .contains("'sfpmap'"));
}
