//! Codec 2 `delta` (1.1): integer arrays that are sorted or nearly so (a level's point list, an
//! image's visibility, offsets) as one zstd frame of the LEB128 varints of their zigzag
//! differences. Sorted indices differ by small numbers, which take one varint byte and compress
//! far better than the 4-byte values do (spec/format.md, "Codecs").

use super::layout::Dtype;

/// zstd level of `delta` sections up to [`SLOW_LEVEL_MAX`] of stream: their streams are 1–2
/// bytes per point, so level 19 takes ~10 % more off than level 3 at little cost on maps of
/// a few hundred thousand points.
pub const ZSTD_LEVEL: i32 = 19;
/// Streams longer than this (a street of a million points' visibility) use [`FAST_LEVEL`]:
/// level 19 runs at 2–4 MB/s.
pub const SLOW_LEVEL_MAX: usize = 4 << 20;
pub const FAST_LEVEL: i32 = 3;

/// The zstd skippable-frame magic (RFC 8878, 3.1.2) the writer pads with.
const SKIPPABLE_MAGIC: u32 = 0x184D_2A50;

/// Bits per value of the dtypes `delta` applies to; `None` for the others.
pub fn width(dtype: Dtype) -> Option<u32> {
    match dtype {
        Dtype::U32 => Some(32),
        Dtype::U64 => Some(64),
        _ => None,
    }
}

/// The longest varint stream `raw_len` bytes of `dtype` can have (every value in the longest
/// varint of its width): the decoder's output bound for the zstd frame.
pub fn max_stream_len(dtype: Dtype, raw_len: u64) -> u64 {
    let bits = u64::from(width(dtype).unwrap_or(64));
    (raw_len / (bits / 8)).saturating_mul(bits.div_ceil(7))
}

/// The varint stream of `raw` (little-endian values of `dtype`): each value's difference from
/// the one before (the first from 0), wrapping in the dtype's width, zigzag-mapped so small
/// steps down stay small.
pub fn encode(dtype: Dtype, raw: &[u8]) -> Vec<u8> {
    let mut out = Vec::with_capacity(raw.len() / 2);
    let mut put = |v: u64| {
        leb128::write::unsigned(&mut out, v).expect("writing to a Vec cannot fail");
    };
    match dtype {
        Dtype::U32 => {
            let mut prev = 0u32;
            for v in raw
                .chunks_exact(4)
                .map(|b| u32::from_le_bytes(b.try_into().unwrap()))
            {
                let d = v.wrapping_sub(prev) as i32;
                put(u64::from(((d << 1) ^ (d >> 31)) as u32));
                prev = v;
            }
        }
        _ => {
            let mut prev = 0u64;
            for v in raw
                .chunks_exact(8)
                .map(|b| u64::from_le_bytes(b.try_into().unwrap()))
            {
                let d = v.wrapping_sub(prev) as i64;
                put(((d << 1) ^ (d >> 63)) as u64);
                prev = v;
            }
        }
    }
    out
}

/// Decodes a varint stream into `out` (`out.len()` bytes of `dtype`, as the table declares).
/// The stream must hold exactly that many varints, each within the dtype's width.
pub fn decode(dtype: Dtype, mut stream: &[u8], out: &mut [u8]) -> Result<(), String> {
    let bytes = (width(dtype).ok_or("delta applies to u32 and u64 only")? / 8) as usize;
    let count = out.len() / bytes;
    let mut prev = 0u64;
    for (i, slot) in out.chunks_exact_mut(bytes).enumerate() {
        let z = leb128::read::unsigned(&mut stream).map_err(|e| match e {
            leb128::read::Error::IoError(_) => {
                format!("the varint stream ends at value {i} of {count}")
            }
            leb128::read::Error::Overflow => format!("value {i}: varint longer than 64 bits"),
        })?;
        if bytes == 4 {
            let z = u32::try_from(z).map_err(|_| format!("value {i}: {z} exceeds u32"))?;
            let d = ((z >> 1) as i32) ^ -((z & 1) as i32);
            let v = (prev as u32).wrapping_add(d as u32);
            slot.copy_from_slice(&v.to_le_bytes());
            prev = u64::from(v);
        } else {
            let d = ((z >> 1) as i64) ^ -((z & 1) as i64);
            let v = prev.wrapping_add(d as u64);
            slot.copy_from_slice(&v.to_le_bytes());
            prev = v;
        }
    }
    if !stream.is_empty() {
        return Err(format!(
            "{} bytes after the last value of the varint stream",
            stream.len()
        ));
    }
    Ok(())
}

/// Decodes stored `delta` bytes (a frame of a varint stream, at most
/// [`max_stream_len`] long, then the varints) into `out` (`raw_len` bytes of `dtype`). The
/// caller has checked `raw_len` against the decode caps; the transient stream is at most
/// 1.25 × `raw_len`.
pub fn decompress(dtype: Dtype, stored: &[u8], out: &mut [u8]) -> Result<(), String> {
    let bound = max_stream_len(dtype, out.len() as u64);
    let stream =
        zstd::bulk::decompress(stored, bound as usize).map_err(|e| format!("zstd: {e}"))?;
    decode(dtype, &stream, out)
}

/// One zstd frame of `stream`, padded with a skippable frame when it compresses past
/// `raw_len / ratio`: the reader's decode caps (spec, "Codecs") hold for every section the
/// writer writes, and an arithmetic sequence (a level holding every point) compresses to
/// almost nothing.
pub fn compress(stream: &[u8], raw_len: u64, ratio: u64) -> std::io::Result<Vec<u8>> {
    let level = if stream.len() <= SLOW_LEVEL_MAX {
        ZSTD_LEVEL
    } else {
        FAST_LEVEL
    };
    let mut z = zstd::bulk::compress(stream, level)?;
    let least = raw_len.div_ceil(ratio) as usize;
    if z.len() < least {
        let pad = (least - z.len()).max(8) - 8;
        let pad_len = u32::try_from(pad)
            .map_err(|_| std::io::Error::other("padding past a skippable frame's 4 GiB"))?;
        z.extend_from_slice(&SKIPPABLE_MAGIC.to_le_bytes());
        z.extend_from_slice(&pad_len.to_le_bytes());
        z.resize(z.len() + pad, 0);
    }
    Ok(z)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn roundtrip(dtype: Dtype, raw: &[u8]) -> Vec<u8> {
        let stream = encode(dtype, raw);
        assert!(stream.len() as u64 <= max_stream_len(dtype, raw.len() as u64));
        let mut out = vec![0u8; raw.len()];
        decode(dtype, &stream, &mut out).unwrap();
        assert_eq!(out, raw);
        stream
    }

    #[test]
    fn sorted_runs_and_extremes_round_trip() {
        let v: Vec<u32> = vec![0, 1, 2, 7, 3, u32::MAX, 0, 5, 5, 4_000_000_000];
        let stream = roundtrip(Dtype::U32, bytemuck::cast_slice(&v));
        assert_eq!(
            &stream[..3],
            &[0, 2, 2],
            "steps of 1 are one byte each (zigzag 2)"
        );
        let w: Vec<u64> = vec![u64::MAX, 0, 1 << 63, 12, 11];
        roundtrip(Dtype::U64, bytemuck::cast_slice(&w));
        roundtrip(Dtype::U32, &[]);
    }

    #[test]
    fn malformed_streams_are_errors() {
        let mut out = [0u8; 8];
        // Too few values, a trailing byte, a value past u32, an endless varint.
        assert!(decode(Dtype::U32, &[2], &mut out)
            .unwrap_err()
            .contains("ends"));
        assert!(decode(Dtype::U32, &[2, 2, 2], &mut out)
            .unwrap_err()
            .contains("after"));
        let big = [0xFF, 0xFF, 0xFF, 0xFF, 0x7F, 0];
        assert!(decode(Dtype::U32, &big, &mut out)
            .unwrap_err()
            .contains("exceeds"));
        let mut long = [0xFF; 12];
        long[11] = 0x01;
        assert!(decode(Dtype::U64, &long, &mut out)
            .unwrap_err()
            .contains("64 bits"));
        assert!(decode(Dtype::U64, &[0xFF; 11], &mut out)
            .unwrap_err()
            .contains("ends"));
        assert!(decode(Dtype::F32, &[], &mut out).is_err());
    }

    #[test]
    fn padding_keeps_the_ratio_and_decodes() {
        let v: Vec<u32> = (0..100_000).collect();
        let raw: &[u8] = bytemuck::cast_slice(&v);
        let stream = encode(Dtype::U32, raw);
        let z = compress(&stream, raw.len() as u64, 256).unwrap();
        assert!(crate::format::reader::within_decode_ratio(
            raw.len() as u64,
            z.len() as u64
        ));
        let mut back = vec![0u8; raw.len()];
        decompress(Dtype::U32, &z, &mut back).unwrap();
        assert_eq!(back, raw);
    }
}
