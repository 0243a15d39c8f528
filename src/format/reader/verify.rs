//! `Map::verify`: every section checked once, streaming, locally or by range (a child of
//! `reader`, whose private state it walks).

use super::*;

impl Map<'_> {
    /// Checks every section: checksums, decoding and contents, in table order, then what ties
    /// sections together. Stops at the first error. Streams: a zstd section not already
    /// decoded is decoded, checked and dropped (the image names excepted, which the last
    /// check needs whole), so memory stays at about one section whatever the map holds. Read
    /// by range, the same: sections are read in batches of neighbours (at most 32 MiB but for
    /// one larger section), checked and dropped, and a large skipped section is read and
    /// hashed in pieces, never held.
    pub fn verify(&self) -> Result<(), Error> {
        self.verify_keeping(|_| false)
    }

    /// [`Map::verify`], keeping the decoded bytes of the sections `keep` selects (those the
    /// caller reads next, so no section is decoded twice).
    pub(crate) fn verify_keeping(&self, keep: impl Fn(&Section) -> bool) -> Result<(), Error> {
        self.verify_selected(|_| true, keep, |_| false)
    }

    /// [`Map::verify_keeping`] of the sections `select` picks (all of them but those a slice
    /// of a map read by range drops, which are then never downloaded), then what ties
    /// sections together. Read by range, the stored bytes of the sections `hold` picks stay
    /// fetched (a slice copies them next); the others are dropped once checked.
    pub(crate) fn verify_selected(
        &self,
        select: impl Fn(&Section) -> bool,
        keep: impl Fn(&Section) -> bool,
        hold: impl Fn(&Section) -> bool,
    ) -> Result<(), Error> {
        // (1.2) Chunk sums are checked too, as a reader that reads by chunk would, unless a
        // slice of a map read by range leaves them out: fetching checks each section whole,
        // the slice gets chunk sums of its own, and they would cost a request at the file's
        // end.
        let chunks = self
            .chunks
            .as_ref()
            .is_some_and(|c| self.source().is_none() || select(&self.sections[c.section]));
        // Kept: what the caller reads next, the image names, which the last check needs, and
        // the chunk sums, which every section's check reads.
        let kept = |section: &Section| {
            keep(section)
                || section.skipped.is_none()
                    && (matches!(
                        section.kind,
                        SectionKind::ImageNameOffsets | SectionKind::ImageNames
                    ) || chunks && section.kind == SectionKind::ChunkChecksums)
        };
        let selected = self.sections.iter().filter(|s| select(s));
        if let Backing::Source { source, fetched } = &self.backing {
            let held = |s: &Section| kept(s) || hold(s);
            self.verify_by_range(source.as_ref(), fetched, selected, &kept, &held, chunks)?;
        } else {
            for section in selected {
                self.verify_one(section, kept(section), chunks)?;
            }
        }
        crate::format::views::check_cross_sections(self)
    }

    /// [`Map::verify_selected`]'s check of one section in memory, or fetched already.
    fn verify_one(&self, section: &Section, kept: bool, chunks: bool) -> Result<(), Error> {
        if kept {
            self.section_bytes(section)?;
        } else {
            self.check_section(section)?;
        }
        if chunks {
            self.check_chunks(section)?;
        }
        Ok(())
    }

    /// [`Map::verify_selected`] of a map read by range: the sections not fetched yet are read
    /// in batches of table neighbours of at most [`VERIFY_BATCH`] bytes (one request each,
    /// usually), checked from the batch's buffers and dropped (those `held` picks kept
    /// fetched, and those `kept` picks decoded), and a
    /// skipped section larger than [`VERIFY_PIECE`], which has only its checksums to check, is
    /// read and hashed a piece at a time. Memory: one batch, or one section of a known kind
    /// (its contents are checked whole), or one piece; never the map.
    fn verify_by_range<'s>(
        &self,
        source: &dyn RangeSource,
        fetched: &[OnceLock<Decoded>],
        selected: impl Iterator<Item = &'s Section>,
        kept: &dyn Fn(&Section) -> bool,
        held: &dyn Fn(&Section) -> bool,
        chunks: bool,
    ) -> Result<(), Error> {
        let pending =
            |s: &Section| fetched[s.index].get().is_none() && self.whole_check(s).is_none();
        let mut batch: Vec<&Section> = Vec::new();
        let mut batch_len = 0u64;
        // Checks the batch so far and starts the next one empty.
        let flush = |batch: &mut Vec<&Section>, batch_len: &mut u64| {
            *batch_len = 0;
            let done = std::mem::take(batch);
            self.verify_batch(source, fetched, &done, kept, held, chunks)
        };
        for section in selected {
            let len = section.offset + section.stored_len - section.padding_start;
            let streamed = pending(section)
                && !held(section)
                && len > VERIFY_PIECE
                && section
                    .skipped
                    .is_some_and(|why| why.hides_encoding() || section.codec == Codec::Raw);
            if streamed {
                flush(&mut batch, &mut batch_len)?;
                self.verify_in_pieces(source, section, chunks)?;
                continue;
            }
            if pending(section) && batch_len > 0 && batch_len.saturating_add(len) > VERIFY_BATCH {
                flush(&mut batch, &mut batch_len)?;
            }
            if pending(section) {
                batch_len = batch_len.saturating_add(len);
            }
            batch.push(section);
        }
        flush(&mut batch, &mut batch_len)
    }

    /// Reads the sections of `batch` not fetched yet (in as few requests as the source
    /// allows), then checks every section of it in order.
    fn verify_batch(
        &self,
        source: &dyn RangeSource,
        fetched: &[OnceLock<Decoded>],
        batch: &[&Section],
        kept: &dyn Fn(&Section) -> bool,
        held: &dyn Fn(&Section) -> bool,
        chunks: bool,
    ) -> Result<(), Error> {
        let pending: Vec<&Section> = batch
            .iter()
            .copied()
            .filter(|s| fetched[s.index].get().is_none() && self.whole_check(s).is_none())
            .collect();
        let mut got = HashMap::new();
        for (section, (want, bytes)) in
            pending
                .iter()
                .zip(read_checked(source, self.header.index_checksum, &pending)?)
        {
            // The held ones first: the chunk sums are read by the checks of the others.
            if held(section) {
                keep_fetched(&fetched[section.index], &want, &bytes);
            } else {
                got.insert(section.index, (want, bytes));
            }
        }
        for section in batch {
            let Some((want, bytes)) = got.remove(&section.index) else {
                self.verify_one(section, kept(section), chunks)?;
                continue;
            };
            let stored = &bytes[(want.offset - want.range.start) as usize..];
            self.prepare_from(section, stored)?;
            self.checked[section.index].store(true, Ordering::Release);
            if chunks {
                self.check_chunks_in(section, 0, stored)?;
            }
        }
        Ok(())
    }

    /// Checks a skipped `section` (only its checksums can be checked) read a
    /// [`VERIFY_PIECE`] at a time, hashing as the pieces arrive; read once more when it
    /// does not match, as a fetched section is.
    fn verify_in_pieces(
        &self,
        source: &dyn RangeSource,
        section: &Section,
        chunks: bool,
    ) -> Result<(), Error> {
        let mut last = None;
        for _ in 0..2 {
            let mut whole = xxhash_rust::xxh3::Xxh3::new();
            let mut chunk_error = None;
            read_in_pieces(source, section, |at, piece| {
                whole.update(piece);
                if chunks && chunk_error.is_none() {
                    chunk_error = self.check_chunks_in(section, at, piece).err();
                }
                Ok(())
            })?;
            let found = whole.digest();
            last = Some(if found != section.checksum {
                Error::ChecksumMismatch {
                    section: section.reference(),
                    expected: section.checksum,
                    found,
                }
            } else if let Some(e) = chunk_error {
                e
            } else {
                self.checked[section.index].store(true, Ordering::Release);
                return Ok(());
            });
        }
        Err(last.expect("two tries"))
    }
}
