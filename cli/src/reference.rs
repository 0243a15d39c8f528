//! `sfpmap generate-reference` (hidden): the committed CLI reference, generated from the clap
//! definitions as ripgrep's `rg --generate man` does, so it is never copied by hand.
//!
//! The markdown page comes from clap-markdown (it reads a `clap::Command` as clap 4 builds
//! it), the man pages from clap_mangen. Neither output holds a date, a path of this machine
//! or anything that depends on the terminal's width, so the committed files can be compared
//! byte for byte: cli/tests/cli/cli_reference.rs fails, naming the subcommand, when they are
//! stale.
//!
//! It writes only into the guide's folder (the one holding `book.toml`), never through a
//! symlinked folder under it, and removes only man pages it generated itself: regular files
//! named `sfpmap.1` or `sfpmap-NAME.1` that begin with the header clap_mangen writes for
//! that command. Every error names the path at fault.

use anyhow::{bail, Context};
use clap::CommandFactory;
use std::io::Read;
use std::path::{Path, PathBuf};
use std::process::ExitCode;

/// The markdown page, relative to the docs folder.
pub const MARKDOWN_PAGE: &str = "src/reference/cli.md";
/// The folder of the man pages, relative to the docs folder: section 1 of a `MANPATH` entry,
/// so that `MANPATH=$PWD/docs/man man sfpmap` finds them.
pub const MAN_DIR: &str = "man/man1";
/// Where the man pages were before they moved into `man1`: stale generated pages there are
/// removed too.
const OLD_MAN_DIR: &str = "man";
/// What marks the docs folder: mdBook's configuration.
const BOOK_TOML: &str = "book.toml";
/// The folders written into, relative to the docs folder, parents first; none may be a
/// symlink.
const FOLDERS: [&str; 4] = ["src", "src/reference", "man", MAN_DIR];
/// How much of a man page is read to tell whether it is one of ours.
const HEADER_MAX: u64 = 1024;

/// Write the CLI reference: OUT/src/reference/cli.md and the man pages OUT/man/man1/sfpmap*.1.
///
/// OUT must be the guide's folder (it holds book.toml). Man pages that sfpmap generated for
/// subcommands that no longer exist are removed; other files are left alone.
/// Example: `cargo run --release -- generate-reference --out docs`
#[derive(Debug, clap::Args)]
pub struct Args {
    /// The docs folder to write into (the one holding book.toml).
    #[arg(long, value_name = "DIR")]
    pub out: PathBuf,
}

pub fn run(args: Args, quiet: bool) -> anyhow::Result<ExitCode> {
    let out = &args.out;
    let book = out.join(BOOK_TOML);
    match std::fs::symlink_metadata(&book) {
        Ok(_) => {}
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => bail!(
            "{}: not the guide's folder (it has no {BOOK_TOML}); pass the docs folder, \
             e.g. --out docs",
            sfpmap::escape::path(out)
        ),
        Err(e) => return Err(e).with_context(|| sfpmap::escape::path(&book).to_string()),
    }
    let files = reference_files()?;
    // All checked before any is created: a refusal leaves nothing behind.
    for folder in FOLDERS {
        check_folder(&out.join(folder))?;
    }
    for folder in FOLDERS {
        let path = out.join(folder);
        if !check_folder(&path)? {
            std::fs::create_dir(&path).with_context(|| {
                format!("{}: cannot create the folder", sfpmap::escape::path(&path))
            })?;
        }
    }
    for (name, bytes) in &files {
        let path = out.join(name);
        // Its errors name the path.
        sfpmap::output::write_bytes(&path, bytes)?;
    }
    let written: Vec<&Path> = files.iter().map(|(name, _)| name.as_path()).collect();
    let preamble = preamble(&files);
    let mut removed = 0;
    for dir in [MAN_DIR, OLD_MAN_DIR] {
        removed += remove_stale(out, Path::new(dir), &written, preamble)?;
    }
    if !quiet {
        eprintln!(
            "{}: wrote {} files of the CLI reference{}",
            sfpmap::escape::path(out),
            files.len(),
            match removed {
                0 => String::new(),
                n => format!(", removed {n} stale man page(s)"),
            }
        );
    }
    Ok(ExitCode::SUCCESS)
}

/// Whether a folder is at `path` (false: nothing is there); an error naming it if it is a
/// symlink (to a folder or not) or anything else.
fn check_folder(path: &Path) -> anyhow::Result<bool> {
    match std::fs::symlink_metadata(path) {
        Ok(meta) if meta.file_type().is_symlink() => bail!(
            "{}: is a symlink; the CLI reference is only written into real folders",
            sfpmap::escape::path(path)
        ),
        Ok(meta) if meta.is_dir() => Ok(true),
        Ok(_) => bail!("{}: exists and is not a folder", sfpmap::escape::path(path)),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(false),
        Err(e) => Err(e).with_context(|| sfpmap::escape::path(path).to_string()),
    }
}

/// What clap_mangen writes before the `.TH` line (its string definitions), taken from a page
/// just rendered.
fn preamble(files: &[(PathBuf, Vec<u8>)]) -> &[u8] {
    files
        .iter()
        .filter(|(name, _)| name.starts_with(MAN_DIR))
        .find_map(|(_, page)| {
            let at = page.windows(4).position(|w| w == b"\n.TH")?;
            Some(&page[..at + 1])
        })
        .unwrap_or_default()
}

/// Removes the man pages in OUT/`dir` that sfpmap generated and `written` no longer holds;
/// returns how many. A missing `dir` holds none.
fn remove_stale(
    out: &Path,
    dir: &Path,
    written: &[&Path],
    preamble: &[u8],
) -> anyhow::Result<usize> {
    let folder = out.join(dir);
    match std::fs::symlink_metadata(&folder) {
        Ok(meta) if meta.is_dir() => {}
        Ok(_) => bail!("{}: is not a folder", sfpmap::escape::path(&folder)),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(0),
        Err(e) => return Err(e).with_context(|| sfpmap::escape::path(&folder).to_string()),
    }
    let entries = std::fs::read_dir(&folder)
        .with_context(|| format!("{}: cannot list the folder", sfpmap::escape::path(&folder)))?;
    let mut removed = 0;
    for entry in entries {
        let entry = entry.with_context(|| {
            format!("{}: cannot list the folder", sfpmap::escape::path(&folder))
        })?;
        let path = entry.path();
        let Some(name) = entry.file_name().to_str().map(str::to_owned) else {
            continue;
        };
        let Some(command) = page_command(&name) else {
            continue;
        };
        if written.contains(&dir.join(&name).as_path()) {
            continue;
        }
        // The entry itself, not what a symlink points at.
        let kind = entry
            .file_type()
            .with_context(|| sfpmap::escape::path(&path).to_string())?;
        if !kind.is_file() || !generated_by_us(&path, command, preamble)? {
            continue;
        }
        std::fs::remove_file(&path).with_context(|| {
            format!(
                "{}: cannot remove the stale man page",
                sfpmap::escape::path(&path)
            )
        })?;
        removed += 1;
    }
    Ok(removed)
}

/// The page's command name (its `.TH` title) if `name` is one clap_mangen gives sfpmap's
/// pages: `^sfpmap(-[a-z0-9-]+)?\.1$`.
fn page_command(name: &str) -> Option<&str> {
    let stem = name.strip_suffix(".1")?;
    let ok = stem == "sfpmap"
        || stem.strip_prefix("sfpmap-").is_some_and(|sub| {
            !sub.is_empty()
                && sub
                    .bytes()
                    .all(|b| b.is_ascii_lowercase() || b.is_ascii_digit() || b == b'-')
        });
    ok.then_some(stem)
}

/// Whether the regular file `path` begins as clap_mangen begins sfpmap's page of `command`:
/// `preamble`, then `.TH COMMAND 1 ` and the source `"sfpmap VERSION"` on that line. Reads
/// at most [`HEADER_MAX`] bytes, never through a symlink, never blocking on a FIFO.
fn generated_by_us(path: &Path, command: &str, preamble: &[u8]) -> anyhow::Result<bool> {
    let mut options = std::fs::OpenOptions::new();
    options.read(true);
    #[cfg(unix)]
    {
        use std::os::unix::fs::OpenOptionsExt;
        let flags = rustix::fs::OFlags::NOFOLLOW | rustix::fs::OFlags::NONBLOCK;
        options.custom_flags(flags.bits() as i32);
    }
    let file = match options.open(path) {
        Ok(file) => file,
        // Swapped for a symlink since it was listed (ELOOP), or gone: not ours to remove.
        Err(_) if !std::fs::symlink_metadata(path).is_ok_and(|m| m.is_file()) => return Ok(false),
        Err(e) => {
            return Err(e).with_context(|| format!("{}: cannot open", sfpmap::escape::path(path)))
        }
    };
    let meta = file
        .metadata()
        .with_context(|| format!("{}: cannot read", sfpmap::escape::path(path)))?;
    if !meta.is_file() {
        return Ok(false);
    }
    let mut head = Vec::new();
    file.take(HEADER_MAX)
        .read_to_end(&mut head)
        .with_context(|| format!("{}: cannot read", sfpmap::escape::path(path)))?;
    let Some(rest) = head.strip_prefix(preamble) else {
        return Ok(false);
    };
    let title = format!(".TH {command} 1 ");
    let Some(rest) = rest.strip_prefix(title.as_bytes()) else {
        return Ok(false);
    };
    // The rest of the `.TH` line, which must end within what was read.
    let Some(end) = rest.iter().position(|&b| b == b'\n') else {
        return Ok(false);
    };
    let line = String::from_utf8_lossy(&rest[..end]);
    Ok(line.trim_start().starts_with("\"sfpmap "))
}

/// Each file of the reference: its path relative to the docs folder, and its bytes.
fn reference_files() -> anyhow::Result<Vec<(PathBuf, Vec<u8>)>> {
    let cmd = super::Cli::command();
    let mut files = vec![(PathBuf::from(MARKDOWN_PAGE), markdown(&cmd).into_bytes())];
    // As `clap_mangen::generate_to`: no page for `help` or hidden subcommands.
    let mut cmd = cmd.disable_help_subcommand(true);
    cmd.build();
    let source = format!("sfpmap {}", cmd.get_version().unwrap_or_default());
    let mut commands = Vec::new();
    documented(&cmd, &mut commands);
    for command in commands {
        let man = clap_mangen::Man::new(command).source(source.clone());
        let mut page = Vec::new();
        man.render(&mut page)?;
        files.push((Path::new(MAN_DIR).join(man.get_filename()), page));
    }
    Ok(files)
}

/// `cmd` and its subcommands at every depth, parents first, without hidden ones or `help`.
fn documented(cmd: &clap::Command, into: &mut Vec<clap::Command>) {
    into.push(cmd.clone());
    for sub in cmd.get_subcommands() {
        if !sub.is_hide_set() && sub.get_name() != "help" {
            documented(sub, into);
        }
    }
}

/// One markdown page: a title, a note on where it comes from, then one `## \`sfpmap SUB\``
/// section per subcommand (about, usage, arguments and options with their help).
fn markdown(cmd: &clap::Command) -> String {
    let options = clap_markdown::MarkdownOptions::new()
        .title("Command-line reference".to_owned())
        .show_footer(false);
    let page = clap_markdown::help_markdown_command_custom(cmd, &options);
    let globals: Vec<String> = cmd
        .get_arguments()
        .filter(|a| a.is_global_set())
        .filter_map(|a| a.get_long().map(|l| format!("`--{l}`")))
        .collect();
    let note = format!(
        "Generated from sfpmap's argument definitions by `sfpmap generate-reference`; do not edit \
         by hand. After changing a flag or its help, regenerate this page and the man pages \
         (`docs/man/man1/`) with `cargo run --release -- generate-reference --out docs`. \
         The options of `sfpmap` itself ({}) work with every subcommand; every command \
         takes `--help`.\n\n",
        globals.join(", ")
    );
    // After the title line and its blank line.
    match page.find("\n\n") {
        Some(at) => format!("{}{note}{}", &page[..at + 2], &page[at + 2..]),
        None => page + "\n" + &note,
    }
}
