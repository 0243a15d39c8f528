//! The `sfpmap` command-line tool. All logic is in the library; this only parses arguments,
//! draws progress and prints results.

use std::process::ExitCode;

mod cli;

fn main() -> ExitCode {
    // Before any work: a Ctrl-C while writing must not leave a temp file behind.
    cli::remove_temps_on_signal();
    match cli::run() {
        Ok(code) => code,
        Err(err) => {
            // `sfpmap info m.sfpm | head` closes the pipe early: that is not an error.
            if err
                .chain()
                .filter_map(|e| e.downcast_ref::<std::io::Error>())
                .any(|e| e.kind() == std::io::ErrorKind::BrokenPipe)
            {
                return ExitCode::SUCCESS;
            }
            eprintln!("error: {err:#}");
            ExitCode::from(1)
        }
    }
}
