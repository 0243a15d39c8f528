//! `sfpmap completions`: a shell completion script, generated from the clap definitions.

use clap::CommandFactory;
use std::io::Write;
use std::process::ExitCode;

/// Print a shell completion script for sfpmap on stdout.
///
/// Example: `sfpmap completions bash > ~/.local/share/bash-completion/completions/sfpmap`
/// (zsh: `sfpmap completions zsh > ~/.zfunc/_sfpmap`, with `fpath=(~/.zfunc $fpath)` in
/// ~/.zshrc before `compinit`; fish: a file `~/.config/fish/completions/sfpmap.fish`).
#[derive(Debug, clap::Args)]
pub struct Args {
    /// The shell to complete for.
    #[arg(value_enum)]
    pub shell: clap_complete::Shell,
}

pub fn run(args: Args, _quiet: bool) -> anyhow::Result<ExitCode> {
    // Generated into memory first: clap_complete panics on a failed write, and
    // `sfpmap completions bash | head` closes the pipe early.
    let mut script = Vec::new();
    clap_complete::generate(args.shell, &mut completed(), "sfpmap", &mut script);
    let mut out = std::io::stdout().lock();
    out.write_all(&script)?;
    out.flush()?;
    Ok(ExitCode::SUCCESS)
}

/// The command line as completed: clap_complete offers hidden subcommands too (clap has no
/// `remove_subcommand`), so the root is put together again from `Cli`'s own arguments and its
/// visible subcommands, nothing restated by hand.
fn completed() -> clap::Command {
    let cli = super::Cli::command();
    let mut root = clap::Command::new("sfpmap")
        .version(env!("CARGO_PKG_VERSION"))
        .args(cli.get_arguments().cloned())
        .subcommands(cli.get_subcommands().filter(|s| !s.is_hide_set()).cloned());
    if let Some(about) = cli.get_about() {
        root = root.about(about.clone());
    }
    root
}
