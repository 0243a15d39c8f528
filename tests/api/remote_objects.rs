//! `remote::objects` (what `python -m sfpmap.batch` stores and fetches with) against s3s-fs on
//! loopback: a small file in one PUT, a 70 MiB one in parts, listing by whole path segments,
//! downloads bounded and atomic, deletes, and the errors.
#![cfg(feature = "remote")]

use crate::servers::S3;
use sfpmap::remote::objects::{delete, download, head, list, upload};
use sfpmap::remote::RemoteOptions;

/// The server's `AWS_*` variables in this test's process (nextest runs one test per process).
fn point_at(s3: &S3) {
    for (k, v) in s3.env() {
        std::env::set_var(k, v);
    }
}

/// Bytes that do not repeat within a part, so a part sent twice or out of order shows.
fn pattern(len: usize) -> Vec<u8> {
    let mut x = 0x9e37_79b9_7f4a_7c15u64;
    (0..len)
        .map(|_| {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            x as u8
        })
        .collect()
}

#[test]
fn objects_round_trip_through_s3_in_one_put_and_in_parts() {
    let s3 = S3::start();
    std::fs::create_dir(s3.root.join("maps")).unwrap();
    point_at(&s3);
    let options = RemoteOptions::default();
    let dir = tempfile::tempdir().unwrap();

    let small = dir.path().join("small.bin");
    std::fs::write(&small, pattern(1000)).unwrap();
    let stored = upload(&small, "s3://maps/city/a/small.bin", &options).unwrap();
    assert_eq!(stored.size, 1000);
    assert_eq!(stored.url, "s3://maps/city/a/small.bin");
    // Past 64 MiB: a multipart upload, completed once every part is in.
    let large = dir.path().join("large.bin");
    let large_bytes = pattern((70 << 20) + 123);
    std::fs::write(&large, &large_bytes).unwrap();
    let stored = upload(&large, "s3://maps/city/ab/large.bin", &options).unwrap();
    assert_eq!(stored.size, large_bytes.len() as u64);
    assert_eq!(
        std::fs::read(s3.root.join("maps/city/ab/large.bin")).unwrap(),
        large_bytes
    );

    // A prefix is whole path segments: city/a lists a/, not ab/.
    let listed = list("s3://maps/city/a", 10, &options).unwrap();
    assert_eq!(listed.len(), 1);
    assert_eq!(listed[0].url, "s3://maps/city/a/small.bin");
    assert_eq!(list("s3://maps/city", 10, &options).unwrap().len(), 2);
    let err = list("s3://maps/city", 1, &options).unwrap_err().to_string();
    assert!(err.contains("more than 1 objects"), "{err}");

    let back = dir.path().join("back.bin");
    let got = download("s3://maps/city/ab/large.bin", &back, 1 << 30, &options).unwrap();
    assert_eq!(got.size, large_bytes.len() as u64);
    assert_eq!(std::fs::read(&back).unwrap(), large_bytes);
    // Over the bound: refused before a byte is written, the old file left as it was.
    std::fs::write(&back, b"old").unwrap();
    let err = download("s3://maps/city/ab/large.bin", &back, 1 << 20, &options)
        .unwrap_err()
        .to_string();
    assert!(err.contains("more than the 1048576 allowed"), "{err}");
    assert_eq!(std::fs::read(&back).unwrap(), b"old");

    assert!(head("s3://maps/city/a/small.bin", &options)
        .unwrap()
        .is_some());
    delete("s3://maps/city/a/small.bin", &options).unwrap();
    assert!(head("s3://maps/city/a/small.bin", &options)
        .unwrap()
        .is_none());
    delete("s3://maps/city/a/small.bin", &options).unwrap();

    // Errors name the URL or file.
    let err = download("s3://maps/none.bin", &back, 1 << 20, &options)
        .unwrap_err()
        .to_string();
    assert!(err.starts_with("s3://maps/none.bin: "), "{err}");
    let err = upload(dir.path(), "s3://maps/x", &options)
        .unwrap_err()
        .to_string();
    assert!(err.starts_with(&dir.path().display().to_string()), "{err}");
    let err = list("ftp://maps/x", 10, &options).unwrap_err().to_string();
    assert!(
        err.contains("not an s3://, http:// or https:// URL"),
        "{err}"
    );
    // A 403 (a wrong secret) is the server's refusal, named.
    std::env::set_var("AWS_SECRET_ACCESS_KEY", "not-the-secret");
    let err = upload(&small, "s3://maps/x", &options)
        .unwrap_err()
        .to_string();
    assert!(
        err.starts_with("s3://maps/x: ") && err.contains("403"),
        "{err}"
    );
    assert!(!s3.root.join("maps/x").exists());
}
