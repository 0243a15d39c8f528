//! A level's `short` block replaced by fewer dimensions in another basis, with the projection
//! that takes a query's descriptor there (`slice --short-dims`; the basis is the builder's).

use super::error::Error;
use super::layout::{Dtype, SectionKind};
use super::writer::{owned_bytes, MapWriter};
use half::f16;

impl MapWriter<'_> {
    /// Replaces level `level`'s descriptors by `rows` (`[points × dims]`) and its projection
    /// by `projection` (`[dims × d_in]`): the level becomes `dim_short = dim_full = dims` with
    /// no `rest` block.
    pub fn set_level_short(
        &mut self,
        level: u16,
        dims: usize,
        rows: Vec<f16>,
        d_in: usize,
        projection: Vec<f32>,
    ) -> Result<&mut Self, Error> {
        let wrong = |what: String| Err(Error::invalid(format!("level {level}: {what}")));
        let points = self
            .sections
            .get(&(SectionKind::LevelPoints.code(), level))
            .map_or(0, |s| s.rows as usize);
        if dims == 0 || d_in < dims || rows.len() != points * dims {
            return wrong(format!(
                "{} values for {points} points x {dims} dims, or {dims} dims from {d_in}",
                rows.len()
            ));
        }
        if projection.len() != dims * d_in || projection.iter().any(|v| !v.is_finite()) {
            return wrong(format!(
                "a projection of {} values is not {dims} x {d_in} finite ones",
                projection.len()
            ));
        }
        let Some(info) = self.metadata.levels.iter_mut().find(|l| l.level == level) else {
            return wrong("add the level before its descriptors".into());
        };
        info.dim_short = dims as u32;
        info.dim_full = dims as u32;
        for kind in [SectionKind::LevelDescShort, SectionKind::LevelDescRest] {
            self.sections.remove(&(kind.code(), level));
        }
        self.push_array(
            SectionKind::LevelDescShort,
            level,
            Dtype::F16,
            points,
            dims,
            owned_bytes(rows),
        );
        self.set_level_projection(level, d_in, projection)?;
        Ok(self)
    }

    /// (1.3) Drops the image index over `of`'s rows, if the writer holds one: its lists were
    /// learned from rows that changed. (1.4) Each image's neighbours go with it, as a slice
    /// that drops the index drops them. Returns whether one was dropped.
    pub fn drop_image_index_of(&mut self, of: super::metadata::Retrieval) -> bool {
        if self.metadata.image_index.as_ref().and_then(|i| i.of()) != Some(of) {
            return false;
        }
        self.metadata.image_index = None;
        for kind in [
            SectionKind::ImageIndexCentroids,
            SectionKind::ImageIndexOffsets,
            SectionKind::ImageIndexImages,
            SectionKind::ImageIndexNeighbours,
        ] {
            self.sections
                .remove(&(kind.code(), super::layout::NO_LEVEL));
        }
        true
    }

    /// Drops the VLAD (codebook and image rows) and any image index over it; retrieval then
    /// goes by the global descriptors if the writer holds them, else by none.
    pub fn drop_vlad(&mut self) {
        use super::metadata::Retrieval;
        self.drop_image_index_of(Retrieval::Vlad);
        let codebook = SectionKind::LevelVladCentroids.code();
        self.sections.retain(|&(kind, _), _| kind != codebook);
        self.sections
            .remove(&(SectionKind::ImageVlad.code(), super::layout::NO_LEVEL));
        for info in &mut self.metadata.levels {
            info.extra.remove("vlad");
        }
        if self.metadata.retrieval() == Some(Retrieval::Vlad) {
            let global = self
                .sections
                .contains_key(&(SectionKind::ImageGlobal.code(), super::layout::NO_LEVEL));
            self.metadata.retrieval = global.then(|| Retrieval::Global.name().to_string());
        }
    }

    /// Whether the writer holds a VLAD codebook (on any level).
    pub fn has_vlad(&self) -> bool {
        let codebook = SectionKind::LevelVladCentroids.code();
        self.sections.keys().any(|&(kind, _)| kind == codebook)
    }
}
