//! Opening what a user named as input: regular files only (a symlink to one is fine), and
//! never blocking. The one home of that rule: the map reader, the COLMAP readers, the
//! database, the MCAP reader and the output policy (which refuses to replace anything else)
//! all ask here. Each module wraps the answer in its own error type, naming the path.

use std::fs::{File, FileType, Metadata};
use std::path::Path;

/// Whether `name` is a URL (`http://`, `https://`, `s3://`, any case) rather than a local
/// path: maps by these names are read by range (`sfpmap::remote`, feature `remote`).
pub fn is_url(name: &str) -> bool {
    // Bytes, not a str slice: a name may start with a multi-byte character.
    ["http://", "https://", "s3://"].iter().any(|scheme| {
        name.len() > scheme.len()
            && name.as_bytes()[..scheme.len()].eq_ignore_ascii_case(scheme.as_bytes())
    })
}

/// `name`, a name a file gave (a query list's image), joined to `folder`, the folder the user
/// named for it (`localize --images`), if it stays inside: a relative path of plain
/// components. An absolute path, a `..` component or a drive prefix is refused with why, so
/// a list cannot make the tool read `/etc/passwd` or `/proc/self/mem`. The one rule for
/// such names: the session's image source and the CLI ask here.
pub fn join_inside(folder: &Path, name: &str) -> Result<std::path::PathBuf, &'static str> {
    use std::path::Component;
    for component in Path::new(name).components() {
        match component {
            Component::Normal(_) | Component::CurDir => {}
            Component::RootDir | Component::Prefix(_) => {
                return Err("an absolute path, not a name inside the images' folder")
            }
            Component::ParentDir => {
                return Err("a name with a \"..\" component, which leaves the images' folder")
            }
        }
    }
    Ok(folder.join(name))
}

/// Why an input cannot be read as a file.
#[derive(Debug)]
pub enum OpenError {
    /// `metadata` or `open` failed.
    Io(std::io::Error),
    /// It exists but is not a regular file; the value says what it is (`"a FIFO"`).
    NotRegular(&'static str),
}

impl std::fmt::Display for OpenError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            OpenError::Io(e) => e.fmt(f),
            OpenError::NotRegular(kind) => write!(f, "is {kind}, not a regular file"),
        }
    }
}

// No `source()`: `Io`'s message is its cause's, and `{:#}` would print it twice.
impl std::error::Error for OpenError {}

impl From<OpenError> for std::io::Error {
    fn from(e: OpenError) -> Self {
        match e {
            OpenError::Io(e) => e,
            e @ OpenError::NotRegular(_) => {
                std::io::Error::new(std::io::ErrorKind::InvalidInput, e.to_string())
            }
        }
    }
}

/// What a file is when it is not a regular file (`None` for a regular file): `"a folder"`,
/// `"a FIFO"`, `"a character device"`, `"a block device"`, `"a socket"`.
pub(crate) fn not_regular(t: &FileType) -> Option<&'static str> {
    if t.is_file() {
        return None;
    }
    if t.is_dir() {
        return Some("a folder");
    }
    #[cfg(unix)]
    {
        use std::os::unix::fs::FileTypeExt;
        if t.is_fifo() {
            return Some("a FIFO");
        }
        if t.is_char_device() {
            return Some("a character device");
        }
        if t.is_block_device() {
            return Some("a block device");
        }
        if t.is_socket() {
            return Some("a socket");
        }
    }
    Some("not a plain file")
}

fn check(meta: &Metadata) -> Result<(), OpenError> {
    match not_regular(&meta.file_type()) {
        None => Ok(()),
        Some(kind) => Err(OpenError::NotRegular(kind)),
    }
}

/// Checks that `path` is a regular file without opening it (for SQLite, which opens the
/// file itself).
pub(crate) fn check_regular_path(path: &Path) -> Result<Metadata, OpenError> {
    let meta = std::fs::metadata(path).map_err(OpenError::Io)?;
    check(&meta)?;
    Ok(meta)
}

/// Opens `path` for reading if it is a regular file.
///
/// The path is checked before opening (opening a FIFO waits for a writer, forever if none
/// comes); it is opened with `O_NONBLOCK`, so a path swapped for a FIFO in between cannot
/// block either (the flag means nothing for a regular file); and the opened file is checked
/// again (`fstat`), since that is the one that is read.
pub(crate) fn open_regular(path: &Path) -> Result<File, OpenError> {
    check_regular_path(path)?;
    let mut options = std::fs::OpenOptions::new();
    options.read(true);
    #[cfg(unix)]
    {
        use std::os::unix::fs::OpenOptionsExt;
        options.custom_flags(rustix::fs::OFlags::NONBLOCK.bits() as i32);
    }
    let file = options.open(path).map_err(OpenError::Io)?;
    check(&file.metadata().map_err(OpenError::Io)?)?;
    Ok(file)
}

/// The whole of `path`, read only if it is a regular file (so a FIFO never blocks and a
/// device such as `/dev/zero` is never read without end).
#[cfg(any(feature = "onnx", feature = "colmap-model", feature = "localize"))]
pub(crate) fn read_regular(path: &Path) -> Result<Vec<u8>, OpenError> {
    use std::io::Read;
    let mut file = open_regular(path)?;
    let len = file.metadata().map_err(OpenError::Io)?.len();
    let mut bytes = Vec::with_capacity(usize::try_from(len).unwrap_or(0));
    file.read_to_end(&mut bytes).map_err(OpenError::Io)?;
    Ok(bytes)
}

/// [`read_regular`] as UTF-8 text.
#[cfg(any(feature = "colmap-model", feature = "localize"))]
pub(crate) fn read_regular_to_string(path: &Path) -> Result<String, OpenError> {
    String::from_utf8(read_regular(path)?)
        .map_err(|e| OpenError::Io(std::io::Error::new(std::io::ErrorKind::InvalidData, e)))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_stay_inside_their_folder() {
        let folder = Path::new("images");
        for name in ["a.jpg", "db/a.jpg", "./a.jpg", "a..b.jpg", "..a.jpg"] {
            assert_eq!(join_inside(folder, name), Ok(folder.join(name)), "{name}");
        }
        for name in ["/etc/passwd", "/proc/self/mem", "//x"] {
            let why = join_inside(folder, name).unwrap_err();
            assert!(why.starts_with("an absolute path"), "{name}: {why}");
        }
        for name in ["..", "../a.jpg", "db/../../a.jpg", "./../a.jpg"] {
            let why = join_inside(folder, name).unwrap_err();
            assert!(why.contains(r#"a ".." component"#), "{name}: {why}");
        }
    }

    #[test]
    fn regular_files_open_and_everything_else_says_what_it_is() {
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("f");
        std::fs::write(&file, b"x").unwrap();
        assert!(open_regular(&file).is_ok());
        assert_eq!(read_regular(&file).unwrap(), b"x");
        let e = open_regular(dir.path()).unwrap_err();
        assert_eq!(e.to_string(), "is a folder, not a regular file");
        let missing = open_regular(&dir.path().join("missing")).unwrap_err();
        assert!(matches!(missing, OpenError::Io(_)), "{missing:?}");
        #[cfg(unix)]
        {
            let fifo = dir.path().join("fifo");
            rustix::fs::mknodat(
                rustix::fs::CWD,
                &fifo,
                rustix::fs::FileType::Fifo,
                rustix::fs::Mode::from_raw_mode(0o600),
                0,
            )
            .unwrap();
            // Returns at once: a blocking open would wait here for a writer forever.
            let e = open_regular(&fifo).unwrap_err();
            assert_eq!(e.to_string(), "is a FIFO, not a regular file");
            let e = read_regular_to_string(&fifo).unwrap_err();
            assert_eq!(e.to_string(), "is a FIFO, not a regular file");
            assert!(read_regular(Path::new("/dev/zero")).is_err());
            let e = check_regular_path(Path::new("/dev/null")).unwrap_err();
            assert_eq!(e.to_string(), "is a character device, not a regular file");
        }
    }
}
