//! `sfpmap generate-reference` (hidden): the committed CLI reference, generated from the clap
//! definitions as ripgrep's `rg --generate man` does, so it is never copied by hand.
//!
//! The markdown page comes from clap-markdown (it reads a `clap::Command` as clap 4 builds
//! it), the man pages from clap_mangen. Neither output holds a date, a path of this machine
//! or anything that depends on the terminal's width, so the committed files can be compared
//! byte for byte: tests/cli/cli_reference.rs fails, naming the subcommand, when they are stale.

use clap::CommandFactory;
use std::path::{Path, PathBuf};
use std::process::ExitCode;

/// The markdown page, relative to the docs folder.
pub const MARKDOWN_PAGE: &str = "src/reference/cli.md";
/// The folder of the man pages, relative to the docs folder.
pub const MAN_DIR: &str = "man";

/// Write the CLI reference: OUT/src/reference/cli.md and the man pages OUT/man/sfpmap*.1.
///
/// Man pages under OUT/man of subcommands that no longer exist are removed.
/// Example: `cargo run --release -- generate-reference --out docs`
#[derive(Debug, clap::Args)]
pub struct Args {
    /// The docs folder to write into.
    #[arg(long, value_name = "DIR")]
    pub out: PathBuf,
}

pub fn run(args: Args, quiet: bool) -> anyhow::Result<ExitCode> {
    let files = reference_files()?;
    let man_dir = args.out.join(MAN_DIR);
    for (name, bytes) in &files {
        let path = args.out.join(name);
        if let Some(dir) = path.parent() {
            std::fs::create_dir_all(dir)?;
        }
        sfpmap::output::write_bytes(&path, bytes)?;
    }
    let written: Vec<&Path> = files.iter().map(|(name, _)| name.as_path()).collect();
    let mut removed = 0;
    for entry in std::fs::read_dir(&man_dir)? {
        let path = entry?.path();
        let name = path
            .file_name()
            .and_then(|n| n.to_str())
            .unwrap_or_default();
        let ours = name.starts_with("sfpmap") && name.ends_with(".1");
        if ours && !written.contains(&Path::new(MAN_DIR).join(name).as_path()) {
            std::fs::remove_file(&path)?;
            removed += 1;
        }
    }
    if !quiet {
        eprintln!(
            "{}: wrote {} files of the CLI reference{}",
            args.out.display(),
            files.len(),
            match removed {
                0 => String::new(),
                n => format!(", removed {n} stale man page(s)"),
            }
        );
    }
    Ok(ExitCode::SUCCESS)
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
         (`docs/man/`) with `cargo run --release -- generate-reference --out docs`. \
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
