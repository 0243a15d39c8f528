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
