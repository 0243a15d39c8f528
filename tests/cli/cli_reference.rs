//! The committed CLI reference (docs/src/reference/cli.md, docs/man/*.1) is what the binary
//! generates now, and `sfpmap completions SHELL` prints a script for each shell.
//!
//! Self-contained on purpose: it needs nothing from tests/support.
#![cfg(feature = "cli")]

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

const REGENERATE: &str = "cargo run --release -- generate-reference --out docs";
const MARKDOWN_PAGE: &str = "src/reference/cli.md";
const MAN_DIR: &str = "man";

fn sfpmap(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_sfpmap"))
        .args(args)
        .output()
        .expect("run sfpmap")
}

fn committed_docs() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("docs")
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
        assert!(
            !script.contains("generate-reference"),
            "{shell}: names a hidden command"
        );
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
    let out = tempfile::tempdir().unwrap();
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
    let (a, b) = (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
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
    assert_eq!(
        man_pages(&a.path().join(MAN_DIR)),
        man_pages(&b.path().join(MAN_DIR))
    );
    // Nothing of the machine it ran on: no temp path, no hidden command.
    let tmp = std::env::temp_dir();
    let tmp = tmp.to_str().unwrap();
    for (name, text) in
        std::iter::once(("cli.md".to_owned(), page(&a))).chain(man_pages(&a.path().join(MAN_DIR)))
    {
        assert!(!text.contains(tmp), "{name} names {tmp}");
        assert!(
            !text.contains("generate-reference --out DIR"),
            "{name} documents a hidden command"
        );
        assert!(
            !text.contains("bench-pose"),
            "{name} documents a hidden command"
        );
    }
    // A stale man page of a command that no longer exists is removed on regeneration.
    let old = a.path().join(MAN_DIR).join("sfpmap-retired.1");
    std::fs::write(&old, "stale").unwrap();
    let o = sfpmap(&[
        "-q",
        "generate-reference",
        "--out",
        a.path().to_str().unwrap(),
    ]);
    assert!(o.status.success());
    assert!(!old.exists());
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
