//! Real servers for the remote-map tests, started on loopback on a free port and stopped when
//! dropped: nginx (Debian's package) serving a folder with range requests, and s3s-fs (an S3
//! server from crates.io) serving a folder as buckets. Tests install nothing: the README's test
//! command (`bash .ci/test`) installs both first; a test that finds one missing fails saying
//! how to get it.
#![allow(dead_code)]

use std::net::{TcpListener, TcpStream};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

/// A free loopback port (bound and released: the server binds it right after).
fn free_port() -> u16 {
    TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

fn wait_until_listening(port: u16, child: &mut Child, what: &str) {
    let start = Instant::now();
    while start.elapsed() < Duration::from_secs(20) {
        if TcpStream::connect(("127.0.0.1", port)).is_ok() {
            return;
        }
        if let Some(status) = child.try_wait().unwrap() {
            panic!("{what} exited before listening: {status}");
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    panic!("{what} did not listen on 127.0.0.1:{port} within 20 s");
}

fn which(program: &str) -> Option<PathBuf> {
    std::env::var_os("PATH")?
        .to_str()?
        .split(':')
        .chain(["/usr/sbin", "/sbin"])
        .map(|d| Path::new(d).join(program))
        .find(|p| p.is_file())
}

/// nginx serving `root` at `/`, the same folder without range support at `/norange/`
/// (`max_ranges 0`: every range request is answered 200 with the whole body) and 403 at
/// `/forbidden/`. The access log records each request's `Range` header.
pub struct Nginx {
    child: Child,
    pub port: u16,
    pub root: PathBuf,
    pub access_log: PathBuf,
    _dir: tempfile::TempDir,
}

impl Nginx {
    pub fn start() -> Nginx {
        let nginx = which("nginx").unwrap_or_else(|| {
            panic!(
                "nginx is missing: `bash .ci/test` installs it (or: apt-get install nginx-light)"
            )
        });
        let dir = tempfile::tempdir().unwrap();
        let root = dir.path().join("www");
        std::fs::create_dir(&root).unwrap();
        let port = free_port();
        let access_log = dir.path().join("access.log");
        let d = dir.path().display();
        let conf = format!(
            r#"daemon off;
master_process off;
pid {d}/nginx.pid;
error_log {d}/error.log;
events {{ worker_connections 64; }}
http {{
  log_format ranges '$request_method $uri $status $http_range $body_bytes_sent';
  access_log {log} ranges;
  client_body_temp_path {d}/body;
  proxy_temp_path {d}/proxy;
  fastcgi_temp_path {d}/fastcgi;
  uwsgi_temp_path {d}/uwsgi;
  scgi_temp_path {d}/scgi;
  types {{ application/octet-stream sfpm; }}
  server {{
    listen 127.0.0.1:{port};
    root {root};
    location /norange/ {{ alias {root}/; max_ranges 0; }}
    location /forbidden/ {{ return 403; }}
  }}
}}
"#,
            log = access_log.display(),
            root = root.display(),
        );
        let conf_path = dir.path().join("nginx.conf");
        std::fs::write(&conf_path, conf).unwrap();
        let mut child = Command::new(nginx)
            .arg("-c")
            .arg(&conf_path)
            .arg("-p")
            .arg(dir.path())
            .arg("-e")
            .arg(dir.path().join("error.log"))
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .expect("nginx starts");
        wait_until_listening(port, &mut child, "nginx");
        Nginx {
            child,
            port,
            root,
            access_log,
            _dir: dir,
        }
    }

    pub fn url(&self, path: &str) -> String {
        format!("http://127.0.0.1:{}/{path}", self.port)
    }

    /// The access log's lines so far (`METHOD URI STATUS RANGE BYTES`).
    pub fn requests(&self) -> Vec<String> {
        std::fs::read_to_string(&self.access_log)
            .unwrap_or_default()
            .lines()
            .map(String::from)
            .collect()
    }
}

impl Drop for Nginx {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

pub const S3_ACCESS_KEY: &str = "sfpmap-test";
pub const S3_SECRET_KEY: &str = "sfpmap-test-secret";

/// s3s-fs serving `root` (each folder a bucket) with one access key.
pub struct S3 {
    child: Child,
    pub port: u16,
    pub root: PathBuf,
    _dir: tempfile::TempDir,
}

impl S3 {
    pub fn start() -> S3 {
        let binary = s3s_fs();
        let dir = tempfile::tempdir().unwrap();
        let root = dir.path().join("buckets");
        std::fs::create_dir(&root).unwrap();
        let port = free_port();
        let mut child = Command::new(binary)
            .args(["--host", "127.0.0.1", "--port", &port.to_string()])
            .args(["--access-key", S3_ACCESS_KEY, "--secret-key", S3_SECRET_KEY])
            .arg(&root)
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .expect("s3s-fs starts");
        wait_until_listening(port, &mut child, "s3s-fs");
        S3 {
            child,
            port,
            root,
            _dir: dir,
        }
    }

    /// Puts `bytes` at `s3://bucket/key` (s3s-fs keeps objects as files).
    pub fn put(&self, bucket: &str, key: &str, bytes: &[u8]) {
        let path = self.root.join(bucket).join(key);
        std::fs::create_dir_all(path.parent().unwrap()).unwrap();
        std::fs::write(path, bytes).unwrap();
    }

    /// The `AWS_*` variables that point object_store at this server.
    pub fn env(&self) -> Vec<(&'static str, String)> {
        vec![
            (
                "AWS_ENDPOINT_URL",
                format!("http://127.0.0.1:{}", self.port),
            ),
            ("AWS_ACCESS_KEY_ID", S3_ACCESS_KEY.into()),
            ("AWS_SECRET_ACCESS_KEY", S3_SECRET_KEY.into()),
            ("AWS_REGION", "us-east-1".into()),
            ("AWS_ALLOW_HTTP", "true".into()),
        ]
    }
}

impl Drop for S3 {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// The s3s-fs binary, on PATH or in cargo's bin folder.
fn s3s_fs() -> PathBuf {
    which("s3s-fs")
        .or_else(|| {
            let home = std::env::var_os("CARGO_HOME")
                .map(PathBuf::from)
                .or_else(|| std::env::var_os("HOME").map(|h| Path::new(&h).join(".cargo")))?;
            Some(home.join("bin/s3s-fs")).filter(|p| p.is_file())
        })
        .unwrap_or_else(|| {
            panic!(
                "s3s-fs is missing: `bash .ci/test` installs it (or: cargo install s3s-fs \
                 --locked --version 0.14.1 --features binary)"
            )
        })
}
