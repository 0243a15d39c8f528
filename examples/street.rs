//! Writes the generated street scene (`sfpmap::demo::street`) into a folder:
//! `cargo run --release --example street -- [--points N] [--queries Q] [--seed S] DIR`.
//! DIR must not exist; it gets `sparse/*.bin`, `database.db`, `queries.db`, `queries.txt`
//! and `gt_poses.txt`.

use sfpmap::demo::street::{write_street, StreetOptions};
use std::path::PathBuf;
use std::process::ExitCode;

fn main() -> ExitCode {
    let mut options = StreetOptions::default();
    let mut dir = None;
    let mut args = std::env::args().skip(1);
    while let Some(arg) = args.next() {
        let mut number = |name: &str| -> Option<u64> {
            let value = args.next().and_then(|v| v.parse().ok());
            if value.is_none() {
                eprintln!("street: {name} needs a whole number");
            }
            value
        };
        match arg.as_str() {
            "--points" => match number("--points") {
                Some(n) => options.points = n as usize,
                None => return ExitCode::FAILURE,
            },
            "--queries" => match number("--queries") {
                Some(n) => options.queries = n as usize,
                None => return ExitCode::FAILURE,
            },
            "--seed" => match number("--seed") {
                Some(n) => options.seed = n,
                None => return ExitCode::FAILURE,
            },
            _ if dir.is_none() && !arg.starts_with('-') => dir = Some(PathBuf::from(arg)),
            _ => {
                eprintln!("usage: street [--points N] [--queries Q] [--seed S] DIR");
                return ExitCode::FAILURE;
            }
        }
    }
    let Some(dir) = dir else {
        eprintln!("usage: street [--points N] [--queries Q] [--seed S] DIR");
        return ExitCode::FAILURE;
    };
    if dir.exists() {
        eprintln!("street: {} exists; give a new folder", dir.display());
        return ExitCode::FAILURE;
    }
    if let Err(e) = std::fs::create_dir_all(&dir) {
        eprintln!("street: {}: {e}", dir.display());
        return ExitCode::FAILURE;
    }
    let start = std::time::Instant::now();
    match write_street(&dir, &options) {
        Ok(s) => {
            println!(
                "{}: street of {:.0} m, {} points, {} images, {} observations, {} queries ({:.1} s)",
                dir.display(),
                s.length_m,
                s.points,
                s.images,
                s.observations,
                s.queries,
                start.elapsed().as_secs_f64()
            );
            ExitCode::SUCCESS
        }
        Err(e) => {
            // With its causes (SQLite's own message), as the CLI prints errors.
            let mut message = e.to_string();
            let mut cause = std::error::Error::source(&e);
            while let Some(c) = cause {
                message += &format!(": {c}");
                cause = c.source();
            }
            eprintln!("street: {message}");
            ExitCode::FAILURE
        }
    }
}
