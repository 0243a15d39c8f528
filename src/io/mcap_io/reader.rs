//! Reading an MCAP log that may be damaged or forged: every length is checked against the
//! file before anything is allocated, chunk CRCs are checked before a chunk's messages are
//! handed out, and a damaged chunk is skipped, not the end of the log.
//!
//! Limits (see [`Limits`]): no record is longer than the bytes left in the data section, nor
//! than [`MAX_RECORD`]; a chunk's uncompressed size is at most [`CHUNK_RATIO`] × the file's
//! length (at least [`CHUNK_FLOOR`]) and never more than [`MAX_RECORD`]; all chunks of a log
//! together decompress to at most that same amount ([`Limits::log_uncompressed`]), so time and
//! memory stay linear in the file size however many chunks it declares.
//!
//! Damage: a record whose framing holds (a chunk with a bad CRC, bad compressed data, a bad
//! field) is skipped alone. A record whose length cannot be right loses the framing; with an
//! intact summary (its CRC checked) reading goes on at the next chunk its chunk index lists,
//! without one the rest of the log is unreadable. Each skip is a [`Damage`] item of the
//! iterator, so the caller can say what was lost; the iterator goes on after it.

use super::records::{self, op, ChunkIndex, FOOTER_AND_MAGIC_LEN, RECORD_HEADER_LEN};
use super::McapIoError;
use mcap::{Channel, Message, Schema};
use std::borrow::Cow;
use std::collections::{BTreeMap, HashMap};
use std::fmt;
use std::fs::File;
use std::io::{BufReader, Read, Seek, SeekFrom};
use std::path::Path;
use std::sync::Arc;

/// No record body, and no uncompressed chunk, is larger than this (1 GiB).
pub const MAX_RECORD: u64 = 1 << 30;
/// A chunk may decompress to at most this many times the file's length...
pub const CHUNK_RATIO: u64 = 64;
/// ...or to this much (64 MiB) when that is more, so small logs of compressible images read.
pub const CHUNK_FLOOR: u64 = 64 << 20;

/// The size limits of one file, from its length.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Limits {
    /// The file's length.
    pub file_len: u64,
    /// The most a chunk may decompress to.
    pub chunk_uncompressed: u64,
    /// The most all chunks of the log may decompress to together.
    pub log_uncompressed: u64,
}

impl Limits {
    /// The limits of a file of `file_len` bytes.
    pub fn for_file(file_len: u64) -> Limits {
        let budget = file_len.saturating_mul(CHUNK_RATIO).max(CHUNK_FLOOR);
        Limits {
            file_len,
            chunk_uncompressed: budget.min(MAX_RECORD),
            // Why a budget per log: 470 chunks each declaring 64 MiB fit in a 998 KB file and
            // took 83 s to decompress, each chunk within its own limit.
            log_uncompressed: budget,
        }
    }
}

/// What the summary section says, when it is there and its CRC holds.
#[derive(Debug, Default, Clone)]
pub struct LogSummary {
    /// The channels, by id.
    pub channels: BTreeMap<u16, Arc<Channel<'static>>>,
    /// Messages per channel id, from the statistics record.
    pub message_counts: Option<BTreeMap<u16, u64>>,
    /// The chunks, in file order.
    pub chunks: Vec<ChunkIndex>,
}

/// What a [`Damage`] cost.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Skipped {
    /// One chunk, its records read until the damage (none when its CRC failed).
    Chunk,
    /// One record.
    Record,
    /// This many further records of the chunk named, after the first one reported (a chunk
    /// damaged all over is one or two items, not one per record).
    MoreRecords(u64),
    /// Everything up to the next chunk the chunk index lists, at this offset.
    UntilChunk(u64),
    /// The rest of the log.
    Rest,
}

/// A part of the log that could not be read and was skipped.
#[derive(Debug)]
pub struct Damage {
    /// Where the damaged record starts in the file (the chunk's, for damage inside a chunk).
    pub offset: u64,
    /// The record's kind (`"chunk"`, `"message"`, ...).
    pub record: &'static str,
    /// The chunk's number (1-based) and the chunk count, when the chunk index lists it.
    pub chunk: Option<(usize, usize)>,
    /// What is wrong with it.
    pub error: McapIoError,
    /// What was skipped.
    pub skipped: Skipped,
}

impl fmt::Display for Damage {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self.chunk {
            Some((i, n)) => write!(f, "chunk {i} of {n} at byte {}: ", self.offset)?,
            None if self.record == "chunk" => write!(f, "chunk at byte {}: ", self.offset)?,
            None => write!(f, "record at byte {}: ", self.offset)?,
        }
        write!(f, "{}; ", self.error)?;
        match self.skipped {
            Skipped::Chunk => write!(f, "chunk skipped"),
            Skipped::Record => write!(f, "record skipped"),
            Skipped::MoreRecords(n) => write!(f, "{n} more records of this chunk skipped"),
            Skipped::UntilChunk(to) => write!(
                f,
                "skipped to the next chunk in the chunk index, at byte {to}"
            ),
            Skipped::Rest => write!(f, "the rest of the log is unreadable"),
        }
    }
}

/// A decompressed chunk whose records are being handed out.
struct OpenChunk {
    records: Vec<u8>,
    pos: usize,
    offset: u64,
    number: Option<(usize, usize)>,
    /// Bad records seen; the first is reported at once, the others together when the chunk
    /// ends.
    bad: u64,
    /// The error of the latest bad record not yet reported.
    last_error: Option<McapIoError>,
}

/// Messages of an MCAP log in file order, with [`Damage`] items where parts were skipped.
pub struct LogReader<R> {
    source: BufReader<R>,
    /// Where `source` is (`u64::MAX` after a failed read).
    source_pos: u64,
    limits: Limits,
    /// The next top-level record.
    pos: u64,
    /// Where the data section ends: the summary, the footer, or the end of a cut-off file.
    data_end: u64,
    summary: Option<LogSummary>,
    summary_error: Option<McapIoError>,
    /// A log without a footer was cut off: its end is damage, not the end.
    has_footer: bool,
    schemas: HashMap<u16, Arc<Schema<'static>>>,
    channels: HashMap<u16, Arc<Channel<'static>>>,
    chunk: Option<OpenChunk>,
    /// Bytes all chunks so far declared they decompress to (charged before decompressing).
    decompressed: u64,
    /// With [`LogReader::data_of`]: messages of other topics come with empty `data`.
    data_topic: Option<String>,
    done: bool,
}

impl LogReader<File> {
    /// Opens a log file; an error when it is not MCAP (or cannot be read at all).
    pub fn open(path: &Path) -> Result<Self, McapIoError> {
        // Opening a FIFO would block until something writes to it.
        let file = crate::input::open_regular(path).map_err(|e| match e {
            crate::input::OpenError::Io(e) => McapIoError::from(e),
            crate::input::OpenError::NotRegular(kind) => McapIoError::NotRegularFile(kind),
        })?;
        let len = file.metadata()?.len();
        LogReader::new(file, len)
    }
}

impl<R: Read + Seek> LogReader<R> {
    /// A reader of `len` bytes of `source` (from its start).
    pub fn new(source: R, len: u64) -> Result<Self, McapIoError> {
        let mut source = BufReader::with_capacity(1 << 16, source);
        let mut magic = [0u8; 8];
        source.seek(SeekFrom::Start(0))?;
        if len < 8 || source.read_exact(&mut magic).is_err() || magic != mcap::MAGIC {
            return Err(McapIoError::NotMcap);
        }
        let mut reader = LogReader {
            source,
            source_pos: 8,
            limits: Limits::for_file(len),
            pos: 8,
            data_end: len,
            summary: None,
            summary_error: None,
            has_footer: false,
            schemas: HashMap::new(),
            channels: HashMap::new(),
            chunk: None,
            decompressed: 0,
            data_topic: None,
            done: false,
        };
        reader.read_footer_and_summary()?;
        Ok(reader)
    }

    /// Hands out the payload of `topic`'s messages only; the others come with empty `data`
    /// (their channel, times and sequence intact). A log of lidar and IMU beside the images
    /// then costs no copy of what is not used.
    pub fn data_of(mut self, topic: &str) -> Self {
        self.data_topic = Some(topic.to_owned());
        self
    }

    /// The summary, when the log has one that is intact.
    pub fn summary(&self) -> Option<&LogSummary> {
        self.summary.as_ref()
    }

    /// Why the summary the footer points to is not used.
    pub fn summary_error(&self) -> Option<&McapIoError> {
        self.summary_error.as_ref()
    }

    fn seek(&mut self, to: u64) -> Result<(), McapIoError> {
        if to == self.source_pos {
            return Ok(());
        }
        // Relative seeks keep what is buffered: records are skipped often.
        let delta = i64::try_from(to)
            .ok()
            .zip(i64::try_from(self.source_pos).ok())
            .and_then(|(to, from)| to.checked_sub(from));
        match delta {
            Some(d) => self.source.seek_relative(d)?,
            None => {
                self.source.seek(SeekFrom::Start(to))?;
            }
        }
        self.source_pos = to;
        Ok(())
    }

    fn read_at(&mut self, at: u64, buf: &mut [u8]) -> Result<(), McapIoError> {
        self.seek(at)?;
        let read = self.source.read_exact(buf);
        // After a failed read the position is unknown.
        self.source_pos = if read.is_ok() {
            at + buf.len() as u64
        } else {
            u64::MAX
        };
        read.map_err(McapIoError::from)
    }

    /// `len` bytes at `at`; `len` is already checked against the file and [`MAX_RECORD`].
    fn read_vec(&mut self, at: u64, len: u64) -> Result<Vec<u8>, McapIoError> {
        let mut buf = vec![0; len as usize];
        self.read_at(at, &mut buf)?;
        Ok(buf)
    }

    /// The footer tells where the data section ends; the summary is used only when its CRC
    /// (when it has one) holds.
    fn read_footer_and_summary(&mut self) -> Result<(), McapIoError> {
        let len = self.limits.file_len;
        if len < 8 + FOOTER_AND_MAGIC_LEN {
            return Ok(());
        }
        let footer_at = len - FOOTER_AND_MAGIC_LEN;
        let mut tail = [0u8; FOOTER_AND_MAGIC_LEN as usize];
        self.read_at(footer_at, &mut tail)?;
        // No footer: a cut-off log, read until its records stop.
        let Some(footer) = records::footer(&tail) else {
            return Ok(());
        };
        self.data_end = footer_at;
        self.has_footer = true;
        if footer.summary_start == 0 {
            return Ok(());
        }
        if !(8..=footer_at).contains(&footer.summary_start) {
            self.summary_error = Some(McapIoError::BadRecord {
                record: "footer",
                reason: format!(
                    "summary start {} is outside the file (footer at byte {footer_at})",
                    footer.summary_start
                ),
            });
            return Ok(());
        }
        // A summary that fails its CRC may have a wrong start too: then the data section is
        // read up to the footer (it ends at its data end record).
        match self.read_summary(footer.summary_start, footer_at, footer.summary_crc, &tail) {
            Ok(summary) => {
                self.data_end = footer.summary_start;
                self.summary = Some(summary);
            }
            Err(e) => self.summary_error = Some(e),
        }
        Ok(())
    }

    fn read_summary(
        &mut self,
        start: u64,
        end: u64,
        crc: u32,
        footer: &[u8],
    ) -> Result<LogSummary, McapIoError> {
        let mut hasher = crc32fast::Hasher::new();
        let mut schemas = HashMap::new();
        let mut summary = LogSummary::default();
        let mut channels = Vec::new();
        let mut buf = vec![0; 1 << 16];
        let mut at = start;
        while at < end {
            let (opcode, body_len) = self.record_header(at, end, "summary")?;
            let body_at = at + RECORD_HEADER_LEN;
            let mut header = [opcode; 9];
            header[1..].copy_from_slice(&body_len.to_le_bytes());
            hasher.update(&header);
            // Every byte is read for the CRC; bodies we do not parse are read in pieces.
            let parsed = matches!(
                opcode,
                op::SCHEMA | op::CHANNEL | op::CHUNK_INDEX | op::STATISTICS
            );
            if parsed {
                let body = self.read_vec(body_at, body_len)?;
                hasher.update(&body);
                match opcode {
                    op::SCHEMA => {
                        let s = records::schema(&body)?;
                        schemas.insert(s.id, Arc::new(owned_schema(s)));
                    }
                    op::CHANNEL => channels.push(records::channel(&body)?),
                    op::CHUNK_INDEX => summary.chunks.push(records::chunk_index(&body)?),
                    _ => summary.message_counts = Some(records::channel_message_counts(&body)?),
                }
            } else {
                let mut left = body_len;
                let mut piece_at = body_at;
                while left > 0 {
                    let n = left.min(buf.len() as u64) as usize;
                    self.read_at(piece_at, &mut buf[..n])?;
                    hasher.update(&buf[..n]);
                    left -= n as u64;
                    piece_at += n as u64;
                }
            }
            at = body_at + body_len;
        }
        // The CRC covers the summary and the footer up to its own field.
        hasher.update(&footer[..9 + 16]);
        let computed = hasher.finalize();
        if crc != 0 && computed != crc {
            return Err(McapIoError::SummaryCrc {
                stored: crc,
                computed,
            });
        }
        for c in channels {
            let schema = schemas.get(&c.schema_id).cloned();
            summary
                .channels
                .insert(c.id, Arc::new(owned_channel(c, schema)));
        }
        summary.chunks.sort_by_key(|c| c.offset);
        for c in &summary.chunks {
            let fits = c.length >= RECORD_HEADER_LEN
                && c.offset >= 8
                && c.offset.checked_add(c.length).is_some_and(|e| e <= start);
            if !fits {
                return Err(McapIoError::BadRecord {
                    record: "chunk index",
                    reason: format!(
                        "chunk at byte {} of {} bytes is outside the data section (bytes 8..{start})",
                        c.offset, c.length
                    ),
                });
            }
        }
        self.schemas = schemas;
        Ok(summary)
    }

    /// The opcode and body length of the record at `at`, the length checked to fit before
    /// `end` (the end of `within`) and under [`MAX_RECORD`].
    fn record_header(
        &mut self,
        at: u64,
        end: u64,
        within: &'static str,
    ) -> Result<(u8, u64), McapIoError> {
        let left = end.saturating_sub(at);
        if left < RECORD_HEADER_LEN {
            return Err(McapIoError::Truncated {
                needed: RECORD_HEADER_LEN,
                available: left,
                within,
            });
        }
        let mut header = [0u8; RECORD_HEADER_LEN as usize];
        self.read_at(at, &mut header)?;
        let opcode = header[0];
        let len = u64::from_le_bytes(header[1..].try_into().expect("8 bytes"));
        let record = records::record_name(opcode);
        let available = left - RECORD_HEADER_LEN;
        if len > available {
            return Err(McapIoError::RecordTooLong {
                record,
                len,
                available,
                within,
            });
        }
        // Only records read into memory have a size limit: an attachment of several GiB (a
        // point cloud, a video) is skipped with a seek and must not end the log.
        let read_whole = matches!(
            opcode,
            op::SCHEMA | op::CHANNEL | op::MESSAGE | op::CHUNK | op::CHUNK_INDEX | op::STATISTICS
        );
        if read_whole && len > MAX_RECORD {
            return Err(McapIoError::RecordOverLimit { record, len });
        }
        Ok((opcode, len))
    }

    /// The chunk's number in the chunk index.
    fn chunk_number(&self, at: u64) -> Option<(usize, usize)> {
        let chunks = &self.summary.as_ref()?.chunks;
        let i = chunks.binary_search_by_key(&at, |c| c.offset).ok()?;
        Some((i + 1, chunks.len()))
    }

    /// Damage that lost the framing at `at`: go on at the next indexed chunk after it.
    fn resync(&mut self, at: u64, record: &'static str, error: McapIoError) -> Damage {
        let next = self.summary.as_ref().and_then(|s| {
            let i = s.chunks.partition_point(|c| c.offset <= at);
            s.chunks.get(i).map(|c| c.offset)
        });
        let skipped = match next {
            Some(to) => {
                self.pos = to;
                Skipped::UntilChunk(to)
            }
            None => {
                self.done = true;
                Skipped::Rest
            }
        };
        Damage {
            offset: at,
            record,
            chunk: self.chunk_number(at),
            error,
            skipped,
        }
    }

    /// One top-level record.
    fn next_top_level(&mut self) -> Step {
        let at = self.pos;
        if at >= self.data_end {
            self.done = true;
            if self.has_footer {
                return Step::Done;
            }
            return Step::Item(Err(Damage {
                offset: at,
                record: "footer",
                chunk: None,
                error: McapIoError::CutOff,
                skipped: Skipped::Rest,
            }));
        }
        let (opcode, len) = match self.record_header(at, self.data_end, "data section") {
            Ok(h) => h,
            Err(e) => return Step::Item(Err(self.resync(at, "unknown", e))),
        };
        let record = records::record_name(opcode);
        let end = at + RECORD_HEADER_LEN + len;
        if opcode == 0 {
            let e = McapIoError::BadRecord {
                record,
                reason: "opcode 0x00 is not a record".into(),
            };
            return Step::Item(Err(self.resync(at, record, e)));
        }
        // A length that jumps over a chunk the (CRC-checked) index lists is wrong.
        if let Some(reason) = self.index_disagrees(at, opcode, end) {
            let e = McapIoError::BadRecord { record, reason };
            return Step::Item(Err(self.resync(at, record, e)));
        }
        self.pos = end;
        let body_at = at + RECORD_HEADER_LEN;
        match opcode {
            op::DATA_END | op::FOOTER => {
                self.done = true;
                Step::Done
            }
            op::CHUNK => {
                let body = match self.read_vec(body_at, len) {
                    Ok(b) => b,
                    Err(e) => return Step::Item(Err(self.resync(at, record, e))),
                };
                let number = self.chunk_number(at);
                match decompress_chunk(&body, &self.limits, &mut self.decompressed) {
                    Ok(records) => {
                        self.chunk = Some(OpenChunk {
                            records,
                            pos: 0,
                            offset: at,
                            number,
                            bad: 0,
                            last_error: None,
                        });
                        Step::Continue
                    }
                    Err(error) => Step::Item(Err(Damage {
                        offset: at,
                        record,
                        chunk: number,
                        error,
                        skipped: Skipped::Chunk,
                    })),
                }
            }
            op::SCHEMA | op::CHANNEL | op::MESSAGE => {
                let body = match self.read_vec(body_at, len) {
                    Ok(b) => b,
                    Err(e) => return Step::Item(Err(self.resync(at, record, e))),
                };
                match self.record(opcode, &body) {
                    Ok(Some(m)) => Step::Item(Ok(m)),
                    Ok(None) => Step::Continue,
                    Err(error) => Step::Item(Err(Damage {
                        offset: at,
                        record,
                        chunk: None,
                        error,
                        skipped: Skipped::Record,
                    })),
                }
            }
            // Header, indexes, attachments, metadata, unknown records: not needed.
            _ => Step::Continue,
        }
    }

    /// Why the record at `at` (ending at `end`) cannot be right by the chunk index.
    fn index_disagrees(&self, at: u64, opcode: u8, end: u64) -> Option<String> {
        let chunks = &self.summary.as_ref()?.chunks;
        let i = chunks.partition_point(|c| c.offset <= at);
        if let Some(c) = i
            .checked_sub(1)
            .map(|j| &chunks[j])
            .filter(|c| c.offset == at)
        {
            if opcode != op::CHUNK || c.length != end - at {
                return Some(format!(
                    "the chunk index has a chunk of {} bytes here, the file a {} record of {} bytes",
                    c.length,
                    records::record_name(opcode),
                    end - at
                ));
            }
        }
        let next = chunks.get(i).filter(|c| c.offset < end)?;
        Some(format!(
            "a {} record of {} bytes runs over the chunk the chunk index has at byte {}",
            records::record_name(opcode),
            end - at,
            next.offset
        ))
    }

    /// The next record of the open chunk.
    fn next_in_chunk(&mut self) -> Step {
        let Some(mut chunk) = self.chunk.take() else {
            return Step::Continue;
        };
        let damage = |chunk: &OpenChunk, error, skipped| Damage {
            offset: chunk.offset,
            record: "chunk",
            chunk: chunk.number,
            error,
            skipped,
        };
        let left = chunk.records.len() - chunk.pos;
        // The next record's framing, or how the chunk ends: cleanly (`None`) or on a record that
        // cannot be framed.
        let framed = match chunk
            .records
            .get(chunk.pos..chunk.pos + RECORD_HEADER_LEN as usize)
        {
            _ if left == 0 => Err(None),
            None => Err(Some(McapIoError::Truncated {
                needed: RECORD_HEADER_LEN,
                available: left as u64,
                within: "chunk",
            })),
            Some(header) => {
                let opcode = header[0];
                let len = u64::from_le_bytes(header[1..].try_into().expect("8 bytes"));
                let available = left as u64 - RECORD_HEADER_LEN;
                if len > available {
                    Err(Some(McapIoError::RecordTooLong {
                        record: records::record_name(opcode),
                        len,
                        available,
                        within: "chunk",
                    }))
                } else {
                    Ok((opcode, len))
                }
            }
        };
        let (opcode, len) = match framed {
            Ok(framed) => framed,
            Err(end) => {
                // The bad records not yet reported come first; a framing error is then found
                // again on the next call.
                if let Some(e) = chunk.last_error.take() {
                    let item = damage(&chunk, e, Skipped::MoreRecords(chunk.bad - 1));
                    if end.is_some() {
                        self.chunk = Some(chunk);
                    }
                    return Step::Item(Err(item));
                }
                return match end {
                    Some(e) => Step::Item(Err(damage(&chunk, e, Skipped::Chunk))),
                    None => Step::Continue,
                };
            }
        };
        let start = chunk.pos + RECORD_HEADER_LEN as usize;
        chunk.pos = start + len as usize;
        let result = self.record(opcode, &chunk.records[start..chunk.pos]);
        let step = match result {
            Ok(Some(m)) => Step::Item(Ok(m)),
            Ok(None) => Step::Continue,
            // The framing holds (the CRC did): only this record is lost. The first bad record
            // of a chunk is reported at once, the others together when the chunk ends.
            Err(e) => {
                chunk.bad += 1;
                if chunk.bad == 1 {
                    Step::Item(Err(damage(&chunk, e, Skipped::Record)))
                } else {
                    chunk.last_error = Some(e);
                    Step::Continue
                }
            }
        };
        self.chunk = Some(chunk);
        step
    }

    /// A schema or channel is remembered, a message linked to its channel.
    fn record(&mut self, opcode: u8, body: &[u8]) -> Result<Option<Message<'static>>, McapIoError> {
        match opcode {
            op::SCHEMA => {
                let s = records::schema(body)?;
                if s.id == 0 {
                    return Err(McapIoError::BadRecord {
                        record: "schema",
                        reason: "schema id 0 is reserved".into(),
                    });
                }
                self.schemas
                    .entry(s.id)
                    .or_insert_with(|| Arc::new(owned_schema(s)));
            }
            op::CHANNEL => {
                let c = records::channel(body)?;
                if !self.channels.contains_key(&c.id) {
                    let schema = self.schemas.get(&c.schema_id).cloned();
                    self.channels
                        .insert(c.id, Arc::new(owned_channel(c, schema)));
                }
            }
            op::MESSAGE => {
                let m = records::message(body)?;
                let channel = self
                    .channels
                    .get(&m.channel_id)
                    .or_else(|| self.summary.as_ref()?.channels.get(&m.channel_id))
                    .cloned()
                    .ok_or(McapIoError::UnknownChannel { id: m.channel_id })?;
                // Only the wanted topic's payloads are copied out of the chunk.
                let wanted = self
                    .data_topic
                    .as_deref()
                    .is_none_or(|t| t == channel.topic);
                return Ok(Some(Message {
                    channel,
                    sequence: m.sequence,
                    log_time: m.log_time,
                    publish_time: m.publish_time,
                    data: if wanted {
                        Cow::Owned(m.data.to_vec())
                    } else {
                        Cow::Borrowed(&[])
                    },
                }));
            }
            _ => {}
        }
        Ok(None)
    }
}

impl<R: Read + Seek> Iterator for LogReader<R> {
    type Item = Result<Message<'static>, Damage>;

    fn next(&mut self) -> Option<Self::Item> {
        // A loop, not recursion: a log may hold millions of records that yield nothing.
        loop {
            let step = if self.chunk.is_some() {
                self.next_in_chunk()
            } else if self.done {
                return None;
            } else {
                self.next_top_level()
            };
            match step {
                Step::Item(item) => return Some(item),
                Step::Continue => {}
                Step::Done => return None,
            }
        }
    }
}

/// What one record gave.
enum Step {
    Item(Result<Message<'static>, Damage>),
    Continue,
    Done,
}

fn owned_schema(s: records::Schema<'_>) -> Schema<'static> {
    Schema {
        id: s.id,
        name: s.name,
        encoding: s.encoding,
        data: Cow::Owned(s.data.to_vec()),
    }
}

fn owned_channel(c: records::Channel, schema: Option<Arc<Schema<'static>>>) -> Channel<'static> {
    Channel {
        id: c.id,
        topic: c.topic,
        schema,
        message_encoding: c.message_encoding,
        metadata: c.metadata,
    }
}

/// A chunk body's records, decompressed within the limits and checked against its CRC;
/// `decompressed` (the log's total so far) is charged before anything is allocated.
fn decompress_chunk(
    body: &[u8],
    limits: &Limits,
    decompressed: &mut u64,
) -> Result<Vec<u8>, McapIoError> {
    let chunk = records::chunk(body)?;
    let size = chunk.uncompressed_size;
    if size > limits.chunk_uncompressed {
        return Err(McapIoError::ChunkTooLarge {
            uncompressed: size,
            limit: limits.chunk_uncompressed,
        });
    }
    let total = decompressed.saturating_add(size);
    if total > limits.log_uncompressed {
        return Err(McapIoError::LogBudgetSpent {
            uncompressed: size,
            spent: *decompressed,
            limit: limits.log_uncompressed,
        });
    }
    *decompressed = total;
    // `size` is at most MAX_RECORD, so it fits a usize.
    let size = size as usize;
    let decompressed = match chunk.compression.as_str() {
        "" => {
            if chunk.records.len() != size {
                return Err(McapIoError::BadRecord {
                    record: "chunk",
                    reason: format!(
                        "uncompressed chunk of {} bytes says it holds {size}",
                        chunk.records.len()
                    ),
                });
            }
            chunk.records.to_vec()
        }
        "zstd" => {
            zstd::bulk::decompress(chunk.records, size).map_err(|e| McapIoError::Decompress {
                compression: "zstd",
                reason: e.to_string(),
            })?
        }
        "lz4" => {
            let mut out = Vec::new();
            lz4::Decoder::new(chunk.records)
                .and_then(|d| d.take(size as u64 + 1).read_to_end(&mut out))
                .map_err(|e| McapIoError::Decompress {
                    compression: "lz4",
                    reason: e.to_string(),
                })?;
            out
        }
        other => {
            return Err(McapIoError::UnsupportedCompression {
                compression: other.to_owned(),
            })
        }
    };
    if decompressed.len() != size {
        return Err(McapIoError::BadRecord {
            record: "chunk",
            reason: format!(
                "decompresses to {} bytes, its header says {size}",
                decompressed.len()
            ),
        });
    }
    let computed = crc32fast::hash(&decompressed);
    if chunk.uncompressed_crc != 0 && computed != chunk.uncompressed_crc {
        return Err(McapIoError::ChunkCrc {
            stored: chunk.uncompressed_crc,
            computed,
        });
    }
    Ok(decompressed)
}

#[cfg(test)]
#[path = "reader_tests.rs"]
mod tests;
