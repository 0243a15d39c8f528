//! The one output policy: every file the crate writes goes through here.
//!
//! [`check_output`] says whether a command may write an output at all: not over an existing
//! file without `force`, never over one of its inputs (same device and inode, whatever path
//! reaches it), never over something that is not a regular file (a device such as
//! `/dev/full`, a FIFO, a folder). [`AtomicFile`] then writes it so that readers only ever see
//! the complete old or the complete new file:
//!
//! - On Linux the data goes to an unnamed file in the target folder (`O_TMPFILE`): a process
//!   killed while writing leaves nothing behind. Once written and fsynced it is linked in under
//!   a temp name and renamed over the target, and the folder is fsynced.
//! - Where the file system has no `O_TMPFILE`, a named temp file `.NAME.sfpmap-tmp.PID.RANDOM`
//!   in the target folder takes its place. Live temp names are kept in a process-wide list so
//!   that a signal handler can remove them ([`remove_pending_temps`]); after `kill -9`, the
//!   next write into that folder removes temp files whose process is gone.
//!
//! [`AtomicPath`] is the same for a file that another library writes by its path (SQLite): a
//! named temp file in the target folder, listed like the one above, renamed over the target
//! at the commit.
//!
//! Every step after the folder is opened is relative to that open folder (`openat` with
//! `O_EXCL|O_NOFOLLOW` for a named temp file, `linkat`, `renameat`, `unlinkat`), so a folder
//! swapped for a link meanwhile cannot aim the write elsewhere. Where the folder itself comes
//! open (the remote-read cache, whose folders another user might swap), [`write_bytes_in`]
//! never looks a path up at all; its temp files are `0600`.
//!
//! Errors name the path the caller gave, never a temp path. The library installs no signal
//! handler; the CLI does.

use std::ffi::OsString;
use std::fs::File;
use std::io::{self, BufWriter, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};
use std::sync::{Mutex, MutexGuard};

/// What marks a temp file of this module (between the output's name and the pid).
const TEMP_MARK: &str = ".sfpmap-tmp.";

/// The longest part of the output's name copied into a temp name (file names are limited to
/// 255 bytes and the temp name adds the mark, a pid and a random part).
const TEMP_NAME_PREFIX_MAX: usize = 160;

/// Why an output cannot be written.
#[derive(Debug)]
#[non_exhaustive]
pub enum OutputError {
    /// The output exists and replacing it was not asked for.
    Exists {
        /// The output.
        path: PathBuf,
    },
    /// The output is one of the command's inputs (the same file, by device and inode).
    IsInput {
        /// The output.
        path: PathBuf,
        /// The input it is, as the caller named it.
        input: PathBuf,
    },
    /// The output, existing or not, lies inside a folder the command reads (a kapture folder,
    /// the images folder): writing there would add to an input.
    InsideInput {
        /// The output.
        path: PathBuf,
        /// The input folder, as the caller named it.
        folder: PathBuf,
    },
    /// The output exists and is not a regular file.
    NotRegular {
        /// The output.
        path: PathBuf,
        /// What it is (`"a folder"`).
        kind: &'static str,
    },
    /// The path names no file (`/`, `..`, empty).
    NoFileName {
        /// The path given.
        path: PathBuf,
    },
    /// Creating, writing, syncing or renaming failed.
    Io {
        /// The output.
        path: PathBuf,
        /// Which step failed, in words (`"cannot name the temp file"`).
        action: &'static str,
        /// The operating system's error.
        source: io::Error,
    },
}

impl OutputError {
    /// The output path the caller gave.
    pub fn path(&self) -> &Path {
        match self {
            OutputError::Exists { path }
            | OutputError::IsInput { path, .. }
            | OutputError::InsideInput { path, .. }
            | OutputError::NotRegular { path, .. }
            | OutputError::NoFileName { path }
            | OutputError::Io { path, .. } => path,
        }
    }

    /// The message without the path in front and with the I/O cause, for error types that
    /// print the path themselves and keep no source.
    pub fn reason(&self) -> String {
        match self {
            OutputError::Io { action, source, .. } => format!("{action}: {source}"),
            _ => self.what(),
        }
    }

    /// The message without the path and without the cause (which [`Error::source`] gives).
    ///
    /// [`Error::source`]: std::error::Error::source
    fn what(&self) -> String {
        match self {
            OutputError::Exists { .. } => "exists; pass --force to overwrite".into(),
            OutputError::IsInput { path, input } if path == input => {
                "is an input of this command; choose another output".into()
            }
            OutputError::IsInput { input, .. } => format!(
                "is the same file as the input {}; choose another output",
                crate::escape::path(input)
            ),
            OutputError::InsideInput { folder, .. } => format!(
                "lies inside the input folder {}; write it outside that folder",
                crate::escape::path(folder)
            ),
            OutputError::NotRegular { kind, .. } => {
                format!("is {kind}, not a regular file; choose a file path")
            }
            OutputError::NoFileName { .. } => "names no file".into(),
            OutputError::Io { action, .. } => (*action).into(),
        }
    }

    /// A write of `path`'s data that failed (for encoders that write into an [`AtomicFile`]).
    pub fn cannot_write(path: &Path, source: io::Error) -> OutputError {
        OutputError::io(path, "cannot write")(source)
    }

    /// A read or write of a scratch file made for `path` ([`scratch_file`]) that failed (a
    /// full disk, most likely: the scratch file is in `path`'s folder).
    pub(crate) fn scratch(path: &Path, source: io::Error) -> OutputError {
        OutputError::io(path, "cannot use a scratch file in its folder")(source)
    }

    fn io<'a>(path: &'a Path, action: &'static str) -> impl FnOnce(io::Error) -> OutputError + 'a {
        move |source| OutputError::Io {
            path: path.to_path_buf(),
            action,
            source,
        }
    }
}

impl std::fmt::Display for OutputError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}: {}", crate::escape::path(self.path()), self.what())
    }
}

impl std::error::Error for OutputError {
    fn source(&self) -> Option<&(dyn std::error::Error + 'static)> {
        match self {
            OutputError::Io { source, .. } => Some(source),
            _ => None,
        }
    }
}

/// For the format's error, which prints the path itself and keeps messages as text.
impl From<OutputError> for crate::format::Error {
    fn from(e: OutputError) -> crate::format::Error {
        crate::format::Error::Io {
            path: e.path().to_path_buf(),
            message: e.reason(),
        }
    }
}

/// Refuses an output (which may not exist yet) that lies inside one of the input `folders`,
/// through links and `..` alike: it would land among a folder input's own files (a kapture
/// folder's `.kpt` files, a model's images), which the command must leave as they were.
pub fn check_outside(out: &Path, folders: &[&Path]) -> Result<(), OutputError> {
    let parent = match out.parent() {
        Some(p) if !p.as_os_str().is_empty() => p,
        _ => Path::new("."),
    };
    let Ok(parent) = parent.canonicalize() else {
        return Ok(());
    };
    for folder in folders {
        if folder.canonicalize().is_ok_and(|f| parent.starts_with(f)) {
            return Err(OutputError::InsideInput {
                path: out.to_path_buf(),
                folder: folder.to_path_buf(),
            });
        }
    }
    Ok(())
}

/// The policy for one output of a command that reads `inputs`: refuses an output that is one
/// of the inputs (also through symlinks, hard links or `..`), one that exists and is not a
/// regular file, and an existing one unless `force`. An output that does not exist yet is free.
pub fn check_output(out: &Path, inputs: &[&Path], force: bool) -> Result<(), OutputError> {
    // `symlink_metadata`: a dangling symlink is something there too.
    if std::fs::symlink_metadata(out).is_err() {
        return Ok(());
    }
    check_not_proc_link(out)?;
    let Ok(meta) = std::fs::metadata(out) else {
        // A dangling symlink: replacing it needs `force` like any existing entry.
        return if force {
            Ok(())
        } else {
            Err(OutputError::Exists {
                path: out.to_path_buf(),
            })
        };
    };
    for input in inputs {
        if let Ok(input_meta) = std::fs::metadata(input) {
            if same_file(&meta, &input_meta, out, input) {
                return Err(OutputError::IsInput {
                    path: out.to_path_buf(),
                    input: input.to_path_buf(),
                });
            }
        }
    }
    if let Some(kind) = crate::input::not_regular(&meta.file_type()) {
        return Err(OutputError::NotRegular {
            path: out.to_path_buf(),
            kind,
        });
    }
    if !force {
        return Err(OutputError::Exists {
            path: out.to_path_buf(),
        });
    }
    Ok(())
}

#[cfg(unix)]
fn same_file(a: &std::fs::Metadata, b: &std::fs::Metadata, _: &Path, _: &Path) -> bool {
    use std::os::unix::fs::MetadataExt;
    (a.dev(), a.ino()) == (b.dev(), b.ino())
}

#[cfg(not(unix))]
fn same_file(_: &std::fs::Metadata, _: &std::fs::Metadata, a: &Path, b: &Path) -> bool {
    matches!((a.canonicalize(), b.canonicalize()), (Ok(x), Ok(y)) if x == y)
}

/// Refuses a symlink into `/proc` (`/dev/stdout` is one to `/proc/self/fd/1`): it names an open
/// descriptor, not a file, and the rename would replace the link (in `/dev`) with a regular
/// file even when the descriptor is a regular file.
fn check_not_proc_link(path: &Path) -> Result<(), OutputError> {
    match std::fs::read_link(path) {
        Ok(target) if target.starts_with("/proc") => Err(OutputError::NotRegular {
            path: path.to_path_buf(),
            kind: "a link to a process's file descriptor",
        }),
        _ => Ok(()),
    }
}

/// Refuses to replace something that is not a regular file (the symlink followed), or a link
/// to a process's descriptor.
fn check_replaceable(path: &Path) -> Result<(), OutputError> {
    check_not_proc_link(path)?;
    match std::fs::metadata(path) {
        Ok(meta) => match crate::input::not_regular(&meta.file_type()) {
            Some(kind) => Err(OutputError::NotRegular {
                path: path.to_path_buf(),
                kind,
            }),
            None => Ok(()),
        },
        Err(_) => Ok(()),
    }
}

/// Temp files this process has in the file system right now (named ones only: unnamed
/// `O_TMPFILE` data vanishes with the process).
static PENDING: Mutex<Vec<PathBuf>> = Mutex::new(Vec::new());

fn pending() -> MutexGuard<'static, Vec<PathBuf>> {
    PENDING.lock().unwrap_or_else(|p| p.into_inner())
}

/// Removes every temp file of this process's unfinished writes; for a SIGINT/SIGTERM handler
/// that exits right after. The list stays locked until the process ends, so no write creates
/// or renames a temp file after this.
pub fn remove_pending_temps() {
    let mut list = pending();
    for path in list.drain(..) {
        let _ = std::fs::remove_file(path);
    }
    // Held on purpose: the caller exits; other threads' writes wait instead of going on.
    std::mem::forget(list);
}

/// How the data reaches the file system before the rename.
#[derive(Debug)]
enum Temp {
    /// An `O_TMPFILE` file: no name until [`AtomicFile::commit`].
    Unnamed,
    /// A named temp file (its full path), listed in [`PENDING`].
    Named(PathBuf),
}

/// A file written to a temp file in the target's folder and renamed over the target by
/// [`AtomicFile::commit`]; dropped without a commit, it leaves the target as it was and no
/// temp file behind. Implements [`Write`] and [`Seek`] (buffered). A symlink at the target is
/// replaced by the new file, not written through: written through, a link that another user
/// planted in a shared folder would aim the write at any file of ours. The new file's mode is
/// 0666 less the umask.
#[derive(Debug)]
pub struct AtomicFile {
    target: Target,
    out: BufWriter<File>,
    temp: Temp,
}

impl AtomicFile {
    /// Starts writing `path`. Refuses a `path` that exists and is not a regular file.
    ///
    /// `SFPMAP_NO_TMPFILE` set in the environment makes it use a named temp file even where
    /// `O_TMPFILE` works (the tests of that way; a file system that claims `O_TMPFILE` and
    /// fails it).
    pub fn create(path: &Path) -> Result<AtomicFile, OutputError> {
        AtomicFile::create_with(path, allow_unnamed())
    }

    /// Starts writing `name` in the open folder `dir`, never looking a path up: the folder is
    /// the one opened, whatever its path leads to by now. `name` is a plain file name (no
    /// `/`); an entry there that is a link is replaced, not followed; one that is not a
    /// regular file is refused. `dir_path` names the folder in errors only. The temp file is
    /// `0600`, and stale temp files of dead processes are not swept here (on Linux the data
    /// has no name until the commit anyway).
    #[cfg(unix)]
    pub(crate) fn create_in(
        dir: std::os::fd::BorrowedFd<'_>,
        dir_path: &Path,
        name: &str,
    ) -> Result<AtomicFile, OutputError> {
        AtomicFile::start(Target::open_in(dir, dir_path, name)?, allow_unnamed())
    }

    fn create_with(path: &Path, allow_unnamed: bool) -> Result<AtomicFile, OutputError> {
        AtomicFile::start(Target::open(path)?, allow_unnamed)
    }

    fn start(target: Target, allow_unnamed: bool) -> Result<AtomicFile, OutputError> {
        let unnamed = if allow_unnamed {
            open_unnamed(&target.dir_file, target.private)
                .map_err(OutputError::io(&target.path, "cannot create"))?
        } else {
            None
        };
        let (file, temp) = match unnamed {
            Some(file) => (file, Temp::Unnamed),
            None => {
                let (file, temp) = target.create_named()?;
                (file, Temp::Named(temp))
            }
        };
        Ok(AtomicFile {
            target,
            out: BufWriter::with_capacity(1 << 20, file),
            temp,
        })
    }

    /// Flushes, fsyncs and renames the file over the target, then fsyncs the folder.
    pub fn commit(mut self) -> Result<(), OutputError> {
        let path = &self.target.path;
        self.out
            .flush()
            .map_err(OutputError::io(path, "cannot write"))?;
        self.out
            .get_ref()
            .sync_all()
            .map_err(OutputError::io(path, "cannot sync"))?;
        let AtomicFile { target, out, temp } = &mut self;
        let target = &*target;
        target.replace(|list| match temp {
            Temp::Named(temp) => Ok(temp.clone()),
            Temp::Unnamed => target.link_unnamed(out.get_mut(), list),
        })
    }
}

impl Write for AtomicFile {
    fn write(&mut self, buf: &[u8]) -> io::Result<usize> {
        self.out.write(buf)
    }
    fn write_all(&mut self, buf: &[u8]) -> io::Result<()> {
        self.out.write_all(buf)
    }
    fn flush(&mut self) -> io::Result<()> {
        self.out.flush()
    }
}

impl Seek for AtomicFile {
    fn seek(&mut self, pos: SeekFrom) -> io::Result<u64> {
        self.out.seek(pos)
    }
}

impl Drop for AtomicFile {
    fn drop(&mut self) {
        if let Temp::Named(temp) = &self.temp {
            remove_if_pending(&self.target, temp);
        }
    }
}

/// The output a temp file replaces: the path the caller gave (the one errors name), its name
/// and its folder, open. What [`AtomicFile`] and [`AtomicPath`] share: the checks, the temp
/// names and the commit.
#[derive(Debug)]
struct Target {
    path: PathBuf,
    dir: PathBuf,
    /// The folder, open: for `openat`/`linkat`/`renameat`/`unlinkat` and its fsync.
    dir_file: File,
    name: OsString,
    /// The folder was given open ([`AtomicFile::create_in`]): `path` and `dir` name it in
    /// messages only and are never looked up; the temp file is `0600`.
    private: bool,
}

impl Target {
    /// Refuses a `path` that names no file or exists and is not a regular file; opens its
    /// folder and removes temp files that dead processes left there.
    fn open(path: &Path) -> Result<Target, OutputError> {
        check_replaceable(path)?;
        let name = path
            .file_name()
            .filter(|n| !n.is_empty())
            .ok_or_else(|| OutputError::NoFileName {
                path: path.to_path_buf(),
            })?
            .to_os_string();
        let dir = path
            .parent()
            .filter(|d| !d.as_os_str().is_empty())
            .unwrap_or(Path::new("."))
            .to_path_buf();
        let dir_file = File::open(&dir).map_err(OutputError::io(path, "cannot open its folder"))?;
        remove_stale_temps(&dir);
        Ok(Target {
            path: path.to_path_buf(),
            dir,
            dir_file,
            name,
            private: false,
        })
    }

    /// The target `name` in the open folder `dir` ([`AtomicFile::create_in`]).
    #[cfg(unix)]
    fn open_in(
        dir: std::os::fd::BorrowedFd<'_>,
        dir_path: &Path,
        name: &str,
    ) -> Result<Target, OutputError> {
        let path = dir_path.join(name);
        if name.is_empty() || name == "." || name == ".." || name.contains('/') {
            return Err(OutputError::NoFileName { path });
        }
        let dir_file = File::from(
            dir.try_clone_to_owned()
                .map_err(OutputError::io(&path, "cannot open its folder"))?,
        );
        let target = Target {
            path,
            dir: dir_path.to_path_buf(),
            dir_file,
            name: name.into(),
            private: true,
        };
        target.check_replaceable()?;
        Ok(target)
    }

    /// [`check_replaceable`], for a target in a folder given open: looked up in that folder,
    /// a link not followed (it is replaced).
    fn check_replaceable(&self) -> Result<(), OutputError> {
        #[cfg(unix)]
        if self.private {
            use rustix::fs::{AtFlags, FileType};
            let kind =
                match rustix::fs::statat(&self.dir_file, &*self.name, AtFlags::SYMLINK_NOFOLLOW) {
                    Ok(st) => match FileType::from_raw_mode(st.st_mode) {
                        FileType::RegularFile | FileType::Symlink => None,
                        FileType::Directory => Some("a folder"),
                        FileType::Fifo => Some("a FIFO"),
                        FileType::CharacterDevice => Some("a character device"),
                        FileType::BlockDevice => Some("a block device"),
                        FileType::Socket => Some("a socket"),
                        _ => Some("not a regular file"),
                    },
                    Err(_) => None,
                };
            return match kind {
                Some(kind) => Err(OutputError::NotRegular {
                    path: self.path.clone(),
                    kind,
                }),
                None => Ok(()),
            };
        }
        check_replaceable(&self.path)
    }

    /// Removes the temp file `temp` (in the open folder, by its name there).
    fn remove_temp(&self, temp: &Path) {
        #[cfg(unix)]
        {
            let name = temp.file_name().unwrap_or(temp.as_os_str());
            let _ = rustix::fs::unlinkat(&self.dir_file, name, rustix::fs::AtFlags::empty());
        }
        #[cfg(not(unix))]
        let _ = std::fs::remove_file(temp);
    }

    /// A new named temp file in the folder, listed in [`PENDING`].
    fn create_named(&self) -> Result<(File, PathBuf), OutputError> {
        let mut list = pending();
        self.create_named_locked(&mut list)
    }

    fn create_named_locked(&self, list: &mut Vec<PathBuf>) -> Result<(File, PathBuf), OutputError> {
        create_named_locked(self, list).map_err(OutputError::io(
            &self.path,
            "cannot create a temp file in its folder",
        ))
    }

    /// The commit, once the temp file is complete and fsynced: checks the target again, renames
    /// the temp file that `temp` names over it and fsyncs the folder. `temp` runs with
    /// [`PENDING`] locked and returns a listed temp file; whether the rename succeeds or not,
    /// that file is gone and unlisted afterwards.
    fn replace(
        &self,
        temp: impl FnOnce(&mut Vec<PathBuf>) -> Result<PathBuf, OutputError>,
    ) -> Result<(), OutputError> {
        // Checked again right before the rename: the target may have changed since `open`.
        self.check_replaceable()?;
        {
            // Locked from the temp name's creation to the rename: a signal handler's
            // [`remove_pending_temps`] runs entirely before or entirely after.
            let mut list = pending();
            let temp = temp(&mut list)?;
            let renamed = self
                .rename_into_place(&temp)
                .map_err(OutputError::io(&self.path, "cannot rename into place"));
            if renamed.is_err() {
                self.remove_temp(&temp);
            }
            list.retain(|p| p != &temp);
            renamed?;
        }
        sync_dir(&self.dir_file).map_err(OutputError::io(&self.path, "cannot sync its folder"))
    }

    /// Renames `temp` over the target relative to the open folder (`renameat`), so the file
    /// lands in the folder it was created in even if that folder's path is swapped meanwhile.
    fn rename_into_place(&self, temp: &Path) -> std::io::Result<()> {
        #[cfg(unix)]
        {
            let temp_name = temp.file_name().unwrap_or(temp.as_os_str());
            rustix::fs::renameat(&self.dir_file, temp_name, &self.dir_file, &self.name)
                .map_err(std::io::Error::from)
        }
        #[cfg(not(unix))]
        {
            std::fs::rename(temp, &self.path)
        }
    }

    /// Gives the unnamed `file` a temp name (listed in `list`), or copies it to a named temp
    /// file where `linkat` through `/proc` is refused.
    fn link_unnamed(
        &self,
        file: &mut File,
        list: &mut Vec<PathBuf>,
    ) -> Result<PathBuf, OutputError> {
        for _ in 0..16 {
            let temp = self.dir.join(temp_name(&self.name));
            list.push(temp.clone());
            match link_fd(file, &self.dir_file, &temp) {
                Ok(()) => return Ok(temp),
                Err(e) if e.kind() == io::ErrorKind::AlreadyExists => {
                    list.pop();
                }
                Err(_) => {
                    list.pop();
                    return self.copy_to_named(file, list);
                }
            }
        }
        Err(OutputError::Io {
            path: self.path.clone(),
            action: "cannot name the temp file",
            source: io::ErrorKind::AlreadyExists.into(),
        })
    }

    fn copy_to_named(
        &self,
        file: &mut File,
        list: &mut Vec<PathBuf>,
    ) -> Result<PathBuf, OutputError> {
        let (mut named, temp) = self.create_named_locked(list)?;
        let copied = (|| {
            file.seek(SeekFrom::Start(0))?;
            io::copy(file, &mut named)?;
            named.sync_all()
        })();
        if let Err(e) = copied {
            self.remove_temp(&temp);
            list.retain(|p| p != &temp);
            return Err(OutputError::cannot_write(&self.path, e));
        }
        Ok(temp)
    }
}

/// Removes the named temp file `temp` if it is still listed in [`PENDING`] (neither renamed
/// into place nor removed yet): what a writer dropped without a commit leaves.
fn remove_if_pending(target: &Target, temp: &Path) {
    let mut list = pending();
    if let Some(i) = list.iter().position(|p| p == temp) {
        target.remove_temp(temp);
        list.swap_remove(i);
    }
}

/// A named temp file in the target's folder that another library writes by its path (SQLite
/// writing a database), renamed over the target by [`AtomicPath::commit`]. It starts empty,
/// is listed for [`remove_pending_temps`] like [`AtomicFile`]'s named temp files, and dropped
/// without a commit it leaves the target as it was and no temp file behind. The same checks
/// as [`AtomicFile`]: a target that exists and is not a regular file is refused, a symlink
/// at the target is replaced, errors name the target, never the temp file.
///
/// Whatever writes the temp file must close it before [`AtomicPath::commit`] (or the drop),
/// and must create no files of its own next to it (an SQLite journal, say), which would be
/// left behind.
#[derive(Debug)]
pub struct AtomicPath {
    target: Target,
    temp: PathBuf,
    /// Held open: for the fsync at the commit, and its lock marks the temp file as in use
    /// for other processes' sweeps of stale temp files.
    file: File,
}

impl AtomicPath {
    /// Creates the empty temp file for `path`. Refuses a `path` that exists and is not a
    /// regular file.
    pub fn create(path: &Path) -> Result<AtomicPath, OutputError> {
        let target = Target::open(path)?;
        let (file, temp) = target.create_named()?;
        Ok(AtomicPath { target, temp, file })
    }

    /// The temp file to write.
    pub fn temp_path(&self) -> &Path {
        &self.temp
    }

    /// Fsyncs the temp file and renames it over the target, then fsyncs the folder.
    pub fn commit(self) -> Result<(), OutputError> {
        self.file
            .sync_all()
            .map_err(OutputError::io(&self.target.path, "cannot sync"))?;
        self.target.replace(|_| Ok(self.temp.clone()))
    }
}

impl Drop for AtomicPath {
    fn drop(&mut self) {
        remove_if_pending(&self.target, &self.temp);
    }
}

/// Writes `path` atomically with `write` ([`AtomicFile`]): committed when `write` succeeds,
/// dropped (nothing changed, nothing left) when it fails.
pub fn write_atomic<T, E>(
    path: &Path,
    write: impl FnOnce(&mut AtomicFile) -> Result<T, E>,
) -> Result<T, E>
where
    E: From<OutputError>,
{
    let mut file = AtomicFile::create(path)?;
    let value = write(&mut file)?;
    file.commit()?;
    Ok(value)
}

/// Writes `bytes` to `path` through [`write_atomic`].
pub fn write_bytes(path: &Path, bytes: &[u8]) -> Result<(), OutputError> {
    write_atomic(path, |out| {
        io::Write::write_all(out, bytes).map_err(|e| OutputError::cannot_write(path, e))
    })
}

/// Writes `bytes` as `name` in the open folder `dir` ([`AtomicFile::create_in`]): committed
/// when written, nothing left otherwise. `dir_path` names the folder in errors only.
#[cfg(unix)]
#[cfg_attr(not(feature = "remote"), allow(dead_code))] // the remote-read cache's writer
pub(crate) fn write_bytes_in(
    dir: std::os::fd::BorrowedFd<'_>,
    dir_path: &Path,
    name: &str,
    bytes: &[u8],
) -> Result<(), OutputError> {
    let mut out = AtomicFile::create_in(dir, dir_path, name)?;
    io::Write::write_all(&mut out, bytes)
        .map_err(|e| OutputError::cannot_write(&dir_path.join(name), e))?;
    out.commit()
}

/// A scratch file for making `path`: in its folder (the file system that will hold the
/// output, with room for it), read and written by the caller and gone once closed. It has no
/// name where the file system allows (`O_TMPFILE`, as [`AtomicFile`]'s temp file); elsewhere
/// it is a temp file of [`AtomicFile`]'s naming, removed as soon as it is open (unix), so a
/// crash leaves nothing behind either way. Refuses what [`AtomicFile::create`] refuses.
pub(crate) fn scratch_file(path: &Path) -> Result<File, OutputError> {
    let target = Target::open(path)?;
    if allow_unnamed() {
        let unnamed = open_unnamed(&target.dir_file, true).map_err(OutputError::io(
            path,
            "cannot create a scratch file in its folder",
        ))?;
        if let Some(file) = unnamed {
            return Ok(file);
        }
    }
    let (file, temp) = target.create_named()?;
    #[cfg(unix)]
    remove_if_pending(&target, &temp);
    #[cfg(not(unix))]
    let _ = temp; // removed with the other pending temp files at exit
    Ok(file)
}

/// Whether [`AtomicFile`] may use an unnamed temp file (`SFPMAP_NO_TMPFILE` unset).
fn allow_unnamed() -> bool {
    std::env::var_os("SFPMAP_NO_TMPFILE").is_none()
}

/// A fresh temp name for an output called `name`: `.NAME.sfpmap-tmp.PID.RANDOM`.
fn temp_name(name: &std::ffi::OsStr) -> String {
    let name = name.to_string_lossy();
    let mut end = name.len().min(TEMP_NAME_PREFIX_MAX);
    while !name.is_char_boundary(end) {
        end -= 1;
    }
    format!(
        ".{}{TEMP_MARK}{}.{:016x}",
        &name[..end],
        std::process::id(),
        random_u64()
    )
}

/// Not for secrets: only so that two writers of the same pid (threads) pick distinct names.
fn random_u64() -> u64 {
    use std::hash::{BuildHasher, Hasher};
    use std::sync::atomic::{AtomicU64, Ordering};
    static COUNTER: AtomicU64 = AtomicU64::new(0);
    let mut h = std::collections::hash_map::RandomState::new().build_hasher();
    h.write_u64(COUNTER.fetch_add(1, Ordering::Relaxed));
    if let Ok(t) = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH) {
        h.write_u128(t.as_nanos());
    }
    h.finish()
}

/// A new named temp file in `target`'s open folder, listed in `list` before it exists (a
/// handler that runs after this returns finds it; `list` is locked, so none runs in between).
fn create_named_locked(target: &Target, list: &mut Vec<PathBuf>) -> io::Result<(File, PathBuf)> {
    let mut last = io::Error::from(io::ErrorKind::AlreadyExists);
    for _ in 0..16 {
        let temp = target.dir.join(temp_name(&target.name));
        list.push(temp.clone());
        match open_new(target, &temp) {
            Ok(file) => {
                lock_temp(&file);
                return Ok((file, temp));
            }
            Err(e) => {
                list.pop();
                if e.kind() != io::ErrorKind::AlreadyExists {
                    return Err(e);
                }
                last = e;
            }
        }
    }
    Err(last)
}

/// Creates the temp file `temp` in `target`'s open folder (`O_EXCL`, a link not followed).
#[cfg(unix)]
fn open_new(target: &Target, temp: &Path) -> io::Result<File> {
    use rustix::fs::OFlags;
    let name = temp.file_name().unwrap_or(temp.as_os_str());
    let flags = OFlags::RDWR | OFlags::CREATE | OFlags::EXCL | OFlags::NOFOLLOW | OFlags::CLOEXEC;
    let fd = rustix::fs::openat(&target.dir_file, name, flags, temp_mode(target.private))?;
    Ok(File::from(fd))
}

#[cfg(not(unix))]
fn open_new(_: &Target, temp: &Path) -> io::Result<File> {
    std::fs::OpenOptions::new()
        .read(true)
        .write(true)
        .create_new(true)
        .open(temp)
}

/// A temp file's mode (less the umask): `0600` when `private`, else `0666`.
#[cfg(unix)]
fn temp_mode(private: bool) -> rustix::fs::Mode {
    use rustix::fs::Mode;
    let owner = Mode::RUSR | Mode::WUSR;
    if private {
        owner
    } else {
        owner | Mode::RGRP | Mode::WGRP | Mode::ROTH | Mode::WOTH
    }
}

/// Removes temp files in `dir` left by processes that no longer run (best effort), once per
/// folder per process: a command writing many files into one folder of 200 k entries would
/// otherwise list it for each file.
fn remove_stale_temps(dir: &Path) {
    static SWEPT: std::sync::Mutex<Vec<std::path::PathBuf>> = std::sync::Mutex::new(Vec::new());
    {
        let mut swept = SWEPT.lock().unwrap_or_else(|e| e.into_inner());
        if swept.iter().any(|d| d == dir) {
            return;
        }
        swept.push(dir.to_path_buf());
    }
    let Ok(entries) = std::fs::read_dir(dir) else {
        return;
    };
    let me = std::process::id();
    for entry in entries.flatten() {
        let name = entry.file_name();
        let Some(pid) = temp_pid(&name.to_string_lossy()) else {
            continue;
        };
        if pid != me && !process_alive(pid) {
            remove_if_unlocked(&entry.path());
        }
    }
}

/// Marks a temp file as in use until its last descriptor closes, which happens when the
/// writer ends, even by `kill -9`. Best effort: where the file system has no `flock`, the
/// sweep relies on the PID alone.
fn lock_temp(file: &File) {
    #[cfg(unix)]
    let _ = rustix::fs::flock(file, rustix::fs::FlockOperation::NonBlockingLockExclusive);
    #[cfg(not(unix))]
    let _ = file;
}

/// Removes a stale-looking temp file unless a live writer holds its lock. Why both checks:
/// a PID names a process only within one PID namespace (containers sharing a folder, NFS), so
/// a writer elsewhere can look dead; its lock shows it is not. The PID check covers the
/// instant between a writer creating its temp file and locking it.
fn remove_if_unlocked(path: &Path) {
    #[cfg(unix)]
    {
        use rustix::fs::{FlockOperation, Mode, OFlags};
        let flags = OFlags::RDONLY | OFlags::NOFOLLOW | OFlags::NONBLOCK | OFlags::CLOEXEC;
        let Ok(fd) = rustix::fs::open(path, flags, Mode::empty()) else {
            return;
        };
        if rustix::fs::flock(&fd, FlockOperation::NonBlockingLockExclusive)
            == Err(rustix::io::Errno::WOULDBLOCK)
        {
            return;
        }
        // Removed while holding the lock; it goes with `fd`.
        let _ = std::fs::remove_file(path);
    }
    #[cfg(not(unix))]
    let _ = std::fs::remove_file(path);
}

/// The pid in a temp name of this module (`.NAME.sfpmap-tmp.PID.RANDOM`), else `None`.
fn temp_pid(name: &str) -> Option<u32> {
    let rest = name.strip_prefix('.')?;
    let (head, random) = rest.rsplit_once('.')?;
    if random.len() != 16 || !random.bytes().all(|b| b.is_ascii_hexdigit()) {
        return None;
    }
    let (head, pid) = head.rsplit_once('.')?;
    if pid.is_empty() || !pid.bytes().all(|b| b.is_ascii_digit()) {
        return None;
    }
    let mark = TEMP_MARK.trim_end_matches('.');
    if head.len() <= mark.len() || !head.ends_with(mark) {
        return None;
    }
    pid.parse().ok()
}

#[cfg(unix)]
fn process_alive(pid: u32) -> bool {
    let Some(pid) = i32::try_from(pid)
        .ok()
        .and_then(rustix::process::Pid::from_raw)
    else {
        return false;
    };
    // EPERM: it runs, as another user.
    !matches!(
        rustix::process::test_kill_process(pid),
        Err(rustix::io::Errno::SRCH)
    )
}

#[cfg(not(unix))]
fn process_alive(_: u32) -> bool {
    // No cheap check: keep every temp file rather than remove a live one.
    true
}

/// An unnamed file in the folder, or `None` where the file system (or kernel) has none.
#[cfg(target_os = "linux")]
fn open_unnamed(dir: &File, private: bool) -> io::Result<Option<File>> {
    use rustix::fs::OFlags;
    use rustix::io::Errno;
    // `linkat` needs /proc/self/fd to give the file a name.
    if !Path::new("/proc/self/fd").is_dir() {
        return Ok(None);
    }
    match rustix::fs::openat(
        dir,
        ".",
        OFlags::TMPFILE | OFlags::RDWR | OFlags::CLOEXEC,
        temp_mode(private),
    ) {
        Ok(fd) => {
            let file = File::from(fd);
            // Held by the inode's open description, so the name it gets later is locked too.
            lock_temp(&file);
            Ok(Some(file))
        }
        // No O_TMPFILE here: EOPNOTSUPP (the file system), EISDIR (an old kernel), EINVAL.
        Err(Errno::OPNOTSUPP | Errno::ISDIR | Errno::INVAL | Errno::NOSYS) => Ok(None),
        Err(e) => Err(e.into()),
    }
}

#[cfg(not(target_os = "linux"))]
fn open_unnamed(_: &File, _: bool) -> io::Result<Option<File>> {
    Ok(None)
}

/// Links the unnamed `file` into `dir` as `temp`.
#[cfg(target_os = "linux")]
fn link_fd(file: &File, dir: &File, temp: &Path) -> io::Result<()> {
    use std::os::fd::AsRawFd;
    let name = temp.file_name().unwrap_or_default();
    rustix::fs::linkat(
        rustix::fs::CWD,
        format!("/proc/self/fd/{}", file.as_raw_fd()),
        dir,
        name,
        rustix::fs::AtFlags::SYMLINK_FOLLOW,
    )?;
    Ok(())
}

#[cfg(not(target_os = "linux"))]
fn link_fd(_: &File, _: &File, _: &Path) -> io::Result<()> {
    Err(io::ErrorKind::Unsupported.into())
}

/// Makes the rename durable. File systems that cannot fsync a folder say EINVAL: nothing to do.
fn sync_dir(dir: &File) -> io::Result<()> {
    match dir.sync_all() {
        Err(e) if e.kind() == io::ErrorKind::InvalidInput => Ok(()),
        other => other,
    }
}

#[cfg(all(test, unix))]
mod tests {
    use super::*;

    fn names(dir: &Path) -> Vec<String> {
        let mut v: Vec<String> = std::fs::read_dir(dir)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        v.sort();
        v
    }

    fn write_with(path: &Path, allow_unnamed: bool, body: &[u8]) -> Result<(), OutputError> {
        let mut f = AtomicFile::create_with(path, allow_unnamed)?;
        f.write_all(body).unwrap();
        f.commit()
    }

    #[test]
    fn both_ways_replace_the_file_and_leave_only_it() {
        for allow_unnamed in [true, false] {
            let dir = tempfile::tempdir().unwrap();
            let path = dir.path().join("out.bin");
            std::fs::write(&path, b"old").unwrap();
            let link = dir.path().join("old-link");
            std::fs::hard_link(&path, &link).unwrap();
            write_with(&path, allow_unnamed, b"new").unwrap();
            assert_eq!(std::fs::read(&path).unwrap(), b"new");
            // Renamed over, not rewritten in place: the old inode keeps the old bytes.
            assert_eq!(std::fs::read(&link).unwrap(), b"old");
            assert_eq!(names(dir.path()), ["old-link", "out.bin"]);
            assert!(!pending().iter().any(|p| p.starts_with(dir.path())));
        }
    }

    #[cfg(target_os = "linux")]
    #[test]
    fn the_unnamed_way_has_no_name_while_writing() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("out.bin");
        let mut f = AtomicFile::create(&path).unwrap();
        assert!(matches!(f.temp, Temp::Unnamed), "this test needs O_TMPFILE");
        f.write_all(b"data").unwrap();
        f.flush().unwrap();
        assert!(names(dir.path()).is_empty());
        f.commit().unwrap();
        assert_eq!(names(dir.path()), ["out.bin"]);
    }

    #[test]
    fn the_named_way_is_listed_while_writing_and_removed_when_dropped() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("out.bin");
        let mut f = AtomicFile::create_with(&path, false).unwrap();
        f.write_all(b"partial").unwrap();
        let listed = names(dir.path());
        assert_eq!(listed.len(), 1);
        assert_eq!(temp_pid(&listed[0]), Some(std::process::id()));
        assert!(pending().iter().any(|p| p.starts_with(dir.path())));
        drop(f);
        assert!(names(dir.path()).is_empty());
        assert!(!pending().iter().any(|p| p.starts_with(dir.path())));
    }

    #[test]
    fn a_path_written_by_another_library_replaces_the_target_or_leaves_nothing() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("out.db");
        std::fs::write(&path, b"old").unwrap();
        let p = AtomicPath::create(&path).unwrap();
        let temp = p.temp_path().to_path_buf();
        assert_eq!(temp.parent(), Some(dir.path()));
        assert_eq!(
            temp_pid(&temp.file_name().unwrap().to_string_lossy()),
            Some(std::process::id())
        );
        assert!(pending().contains(&temp));
        std::fs::write(&temp, b"new").unwrap();
        assert_eq!(std::fs::read(&path).unwrap(), b"old");
        p.commit().unwrap();
        assert_eq!(std::fs::read(&path).unwrap(), b"new");
        assert_eq!(names(dir.path()), ["out.db"]);
        assert!(!pending().contains(&temp));

        let p = AtomicPath::create(&path).unwrap();
        std::fs::write(p.temp_path(), b"partial").unwrap();
        drop(p);
        assert_eq!(names(dir.path()), ["out.db"]);
        assert_eq!(std::fs::read(&path).unwrap(), b"new");
        assert!(!pending().iter().any(|p| p.starts_with(dir.path())));
        let e = AtomicPath::create(Path::new("/dev/null")).unwrap_err();
        assert!(matches!(e, OutputError::NotRegular { .. }), "{e}");
    }

    #[test]
    fn seek_works_for_writers_that_patch_a_header() {
        for allow_unnamed in [true, false] {
            let dir = tempfile::tempdir().unwrap();
            let path = dir.path().join("out.bin");
            let mut f = AtomicFile::create_with(&path, allow_unnamed).unwrap();
            f.write_all(b"xxxxBODY").unwrap();
            f.seek(SeekFrom::Start(0)).unwrap();
            f.write_all(b"HEAD").unwrap();
            f.commit().unwrap();
            assert_eq!(std::fs::read(&path).unwrap(), b"HEADBODY");
        }
    }

    #[test]
    fn the_unnamed_copy_fallback_writes_the_whole_file() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("out.bin");
        let body: Vec<u8> = (0..3_000_000u32).map(|i| i as u8).collect();
        let mut f = AtomicFile::create(&path).unwrap();
        f.write_all(&body).unwrap();
        f.out.flush().unwrap();
        let temp = {
            let mut list = pending();
            let t = f.target.copy_to_named(f.out.get_mut(), &mut list).unwrap();
            list.retain(|p| p != &t);
            t
        };
        assert_eq!(std::fs::read(&temp).unwrap(), body);
        std::fs::remove_file(temp).unwrap();
    }

    #[test]
    fn stale_temps_of_dead_processes_go_live_ones_stay() {
        let dir = tempfile::tempdir().unwrap();
        let dead = {
            let mut child = std::process::Command::new("true").spawn().unwrap();
            let pid = child.id();
            child.wait().unwrap();
            pid
        };
        let stale = format!(".out.bin{TEMP_MARK}{dead}.0123456789abcdef");
        let live = format!(".out.bin{TEMP_MARK}1.0123456789abcdef"); // init never dies
        let other = ".out.bin.tmp123".to_string(); // not ours: never touched
        for n in [&stale, &live, &other] {
            std::fs::write(dir.path().join(n), b"x").unwrap();
        }
        write_with(&dir.path().join("out.bin"), true, b"new").unwrap();
        let left = names(dir.path());
        assert!(!left.contains(&stale), "{left:?}");
        assert!(left.contains(&live) && left.contains(&other), "{left:?}");
    }

    #[test]
    fn a_locked_temp_of_a_process_that_looks_dead_stays() {
        // A writer in another PID namespace: its PID means nothing here, its lock does.
        let dir = tempfile::tempdir().unwrap();
        let name = format!(".map.sfpm{}{}.0123456789abcdef", TEMP_MARK, u32::MAX - 7);
        let locked = dir.path().join(&name);
        let file = File::create(&locked).unwrap();
        lock_temp(&file);
        let unlocked = dir.path().join(name.replace("0123", "3210"));
        std::fs::write(&unlocked, b"left by kill -9").unwrap();
        remove_stale_temps(dir.path());
        assert!(locked.exists(), "removed a temp file a live writer holds");
        assert!(!unlocked.exists(), "kept a temp file nobody holds");
        drop(file);
    }

    #[test]
    fn temp_names_parse_back_and_others_do_not() {
        let n = temp_name(std::ffi::OsStr::new("map.v2.sfpm"));
        assert_eq!(temp_pid(&n), Some(std::process::id()));
        let long = "é".repeat(120);
        let n = temp_name(std::ffi::OsStr::new(&long));
        assert!(n.len() < 255 && temp_pid(&n).is_some());
        for n in [
            ".m.sfpm.tmp123",
            "m.sfpmap-tmp.12.0123456789abcdef",
            ".m.sfpmap-tmp..0123456789abcdef",
            ".m.sfpmap-tmp.12.0123",
            ".sfpmap-tmp.12.0123456789abcdef",
        ] {
            assert_eq!(temp_pid(n), None, "{n}");
        }
    }

    #[test]
    fn errors_name_the_output_not_the_temp() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("no/such/out.bin");
        for allow_unnamed in [true, false] {
            let e = write_with(&path, allow_unnamed, b"x").unwrap_err();
            let msg = e.to_string();
            assert!(msg.starts_with(&path.display().to_string()), "{msg}");
            assert!(!msg.contains(TEMP_MARK), "{msg}");
            assert!(std::error::Error::source(&e).is_some());
        }
    }

    #[test]
    fn the_policy_refuses_inputs_non_regular_files_and_existing_ones() {
        let dir = tempfile::tempdir().unwrap();
        let input = dir.path().join("in.sfpm");
        std::fs::write(&input, b"map").unwrap();
        let fresh = dir.path().join("new.sfpm");
        check_output(&fresh, &[&input], false).unwrap();
        // The same file by another path: `..`, a symlink, a hard link.
        std::fs::create_dir(dir.path().join("sub")).unwrap();
        let dotdot = dir.path().join("sub/../in.sfpm");
        let sym = dir.path().join("sym.sfpm");
        std::os::unix::fs::symlink(&input, &sym).unwrap();
        let hard = dir.path().join("hard.sfpm");
        std::fs::hard_link(&input, &hard).unwrap();
        for out in [&input, &dotdot, &sym, &hard] {
            let e = check_output(out, &[&input], true).unwrap_err();
            assert!(matches!(e, OutputError::IsInput { .. }), "{e}");
        }
        let e = check_output(dir.path(), &[], true).unwrap_err();
        assert!(
            matches!(
                e,
                OutputError::NotRegular {
                    kind: "a folder",
                    ..
                }
            ),
            "{e}"
        );
        let e = check_output(Path::new("/dev/null"), &[], true).unwrap_err();
        assert!(e.to_string().contains("character device"), "{e}");
        // And the writer itself never replaces one, policy or not.
        let e = AtomicFile::create(Path::new("/dev/null")).unwrap_err();
        assert!(matches!(e, OutputError::NotRegular { .. }), "{e}");
        let other = dir.path().join("other");
        std::fs::write(&other, b"x").unwrap();
        let e = check_output(&other, &[&input], false).unwrap_err();
        assert!(e.to_string().contains("--force"), "{e}");
        check_output(&other, &[&input], true).unwrap();
        let dangling = dir.path().join("dangling");
        std::os::unix::fs::symlink(dir.path().join("nothing"), &dangling).unwrap();
        assert!(check_output(&dangling, &[], false).is_err());
        check_output(&dangling, &[], true).unwrap();
    }

    #[test]
    fn a_symlink_is_replaced_not_written_through_and_proc_links_are_refused() {
        let dir = tempfile::tempdir().unwrap();
        let sub = dir.path().join("sub");
        std::fs::create_dir(&sub).unwrap();
        let real = sub.join("real.txt");
        std::fs::write(&real, b"old").unwrap();
        let link = dir.path().join("link.txt");
        std::os::unix::fs::symlink(&real, &link).unwrap();
        write_with(&link, true, b"new").unwrap();
        // What the link led to is untouched (a planted link cannot aim the write elsewhere).
        assert_eq!(std::fs::read(&real).unwrap(), b"old");
        assert!(!std::fs::symlink_metadata(&link)
            .unwrap()
            .file_type()
            .is_symlink());
        assert_eq!(std::fs::read(&link).unwrap(), b"new");
        // `/dev/stdout`'s kind of link: refused by the policy and by the writer, even when the
        // descriptor it names is a regular file (as it is with `> file`).
        let fd_file = File::create(dir.path().join("fd.txt")).unwrap();
        use std::os::fd::AsRawFd;
        let proc_link = dir.path().join("stdout");
        let target = format!("/proc/self/fd/{}", fd_file.as_raw_fd());
        std::os::unix::fs::symlink(&target, &proc_link).unwrap();
        let e = check_output(&proc_link, &[], true).unwrap_err();
        assert!(e.to_string().contains("file descriptor"), "{e}");
        let e = AtomicFile::create(&proc_link).unwrap_err();
        assert!(e.to_string().contains("file descriptor"), "{e}");
        assert_eq!(std::fs::read_link(&proc_link).unwrap(), Path::new(&target));
    }

    /// Writes `body` as `name` in the open folder `dir` ([`AtomicFile::create_in`]), the
    /// named or the unnamed way.
    fn write_in(
        dir: &File,
        name: &str,
        allow_unnamed: bool,
        body: &[u8],
    ) -> Result<(), OutputError> {
        use std::os::fd::AsFd;
        let target = Target::open_in(dir.as_fd(), Path::new("cache/dir"), name)?;
        let mut f = AtomicFile::start(target, allow_unnamed)?;
        f.write_all(body).unwrap();
        f.commit()
    }

    #[test]
    fn a_write_in_an_open_folder_lands_there_even_after_its_path_is_swapped_for_a_link() {
        use std::os::unix::fs::PermissionsExt;
        for allow_unnamed in [true, false] {
            let root = tempfile::tempdir().unwrap();
            let folder = root.path().join("folder");
            std::fs::create_dir(&folder).unwrap();
            let open = File::open(&folder).unwrap();
            // The folder's path now leads elsewhere: moved aside, a link to a victim in its place.
            let moved = root.path().join("moved");
            std::fs::rename(&folder, &moved).unwrap();
            let victim = root.path().join("victim");
            std::fs::create_dir(&victim).unwrap();
            std::os::unix::fs::symlink(&victim, &folder).unwrap();
            write_in(&open, "f.bin", allow_unnamed, b"bytes").unwrap();
            assert!(names(&victim).is_empty(), "written through the link");
            assert_eq!(names(&moved), ["f.bin"], "a temp file was left");
            assert_eq!(std::fs::read(moved.join("f.bin")).unwrap(), b"bytes");
            // Private: the cache's files are its user's alone.
            let mode = std::fs::metadata(moved.join("f.bin"))
                .unwrap()
                .permissions()
                .mode();
            assert_eq!(mode & 0o077, 0, "{mode:o}");
            // A link at the name is replaced, not written through.
            std::os::unix::fs::symlink(victim.join("g.bin"), moved.join("g.bin")).unwrap();
            write_in(&open, "g.bin", allow_unnamed, b"new").unwrap();
            assert!(
                names(&victim).is_empty(),
                "written through a link at the name"
            );
            assert_eq!(std::fs::read(moved.join("g.bin")).unwrap(), b"new");
            // Not a plain name, or a folder there: refused, nothing left.
            for bad in ["", ".", "..", "../victim/x.bin"] {
                let e = write_in(&open, bad, allow_unnamed, b"x").unwrap_err();
                assert!(matches!(e, OutputError::NoFileName { .. }), "{bad}: {e}");
            }
            std::fs::create_dir(moved.join("sub")).unwrap();
            let e = write_in(&open, "sub", allow_unnamed, b"x").unwrap_err();
            assert!(matches!(e, OutputError::NotRegular { .. }), "{e}");
            assert_eq!(e.path(), Path::new("cache/dir/sub"));
            assert_eq!(names(&moved), ["f.bin", "g.bin", "sub"]);
            assert!(names(&victim).is_empty());
        }
    }
}
