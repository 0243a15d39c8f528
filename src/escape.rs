//! Text a user or a file gave, shown in a message or a report: control characters escaped
//! so it stays on one line and cannot drive a terminal, long names cut. The one home of that
//! rule for every module (the COLMAP readers, query lists, pose files, MCAP logs, catalogs,
//! the CLI).

use std::fmt::Write as _;

/// `s` with each control character written as an escape (`\n`, `\r`, `\t`, else
/// `\xNN`; all control characters are below U+00A0), so it stays on one line; borrowed
/// when there is none, which is the usual case.
pub fn escape_control_characters(s: &str) -> std::borrow::Cow<'_, str> {
    if !s.chars().any(char::is_control) {
        return std::borrow::Cow::Borrowed(s);
    }
    let mut out = String::with_capacity(s.len() + 8);
    for c in s.chars() {
        match c {
            '\n' => out.push_str("\\n"),
            '\r' => out.push_str("\\r"),
            '\t' => out.push_str("\\t"),
            c if c.is_control() => {
                write!(out, "\\x{:02x}", u32::from(c)).ok();
            }
            c => out.push(c),
        }
    }
    std::borrow::Cow::Owned(out)
}

/// At most this many characters of a name go into a message.
const SHOWN_NAME: usize = 60;

/// `name` for a one-line message: quoted, control characters escaped, cut after 60
/// characters.
pub fn quoted_name(name: &str) -> String {
    let shown: String = name.chars().take(SHOWN_NAME).collect();
    let cut = if shown.len() < name.len() { "…" } else { "" };
    format!("\"{}{cut}\"", escape_control_characters(&shown))
}

/// `path` for a message, as [`Path::display`](std::path::Path::display) shows it with its
/// control characters escaped ([`escape_control_characters`]): a path a user or a file gave
/// (a catalog's place, a query list's image) may hold ESC, BEL or a newline, which would
/// drive the terminal or forge a line. Every error and progress line that names a path
/// shows it through this.
pub fn path(path: &std::path::Path) -> impl std::fmt::Display + '_ {
    EscapedPath(path)
}

/// [`path`]'s value.
struct EscapedPath<'a>(&'a std::path::Path);

impl std::fmt::Display for EscapedPath<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&escape_control_characters(&self.0.to_string_lossy()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn paths_are_shown_with_control_characters_escaped() {
        let p = std::path::Path::new("maps/p\u{1b}[2J\u{7}\nerror: forged.sfpm");
        assert_eq!(
            path(p).to_string(),
            r"maps/p\x1b[2J\x07\nerror: forged.sfpm"
        );
        assert_eq!(
            path(std::path::Path::new("a b.sfpm")).to_string(),
            "a b.sfpm"
        );
    }
}
