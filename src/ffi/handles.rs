//! The handles C holds: plain integers, a registry slot and a generation, one registry for
//! maps and one for sessions (see the module's docs for why not pointers).

use super::map::MapHandle;
use super::SfpmStatus::*;
use super::{lock, FfiError, FfiResult};
use crate::session::Session;
use std::sync::{Arc, Mutex};

/// An open map: `0` is never a valid handle. Handles are plain integers (a registry slot and a
/// generation), so a handle used after `sfpm_close` is detected, never undefined behaviour.
pub type SfpmMap = u64;

/// An open localization session (`sfpm_session_open`): a map prepared for queries with a
/// fixed set of options, and a sequence's tracking. A plain integer like `SfpmMap`, never 0,
/// never equal to a map handle; a handle used after `sfpm_session_close` is detected.
pub type SfpmSession = u64;

struct Slot<T> {
    generation: u32,
    value: Option<Arc<T>>,
}

/// The live handles of one kind. A handle is `kind << 63 | generation << 32 | (slot + 1)`:
/// never 0, and a map handle is never a session handle.
pub(super) struct Registry<T> {
    slots: Mutex<Vec<Slot<T>>>,
    /// The handle's top bit.
    kind: u64,
    /// "map" or "session", in errors.
    what: &'static str,
    /// The function that makes a handle of this kind, in errors.
    opener: &'static str,
}

/// Generations run from 1 to this and wrap to 1, so they fit beside the kind bit.
const MAX_GENERATION: u32 = (1 << 31) - 1;

pub(super) static MAPS: Registry<MapHandle> = Registry::new(0, "map", "sfpm_open");
pub(super) static SESSIONS: Registry<Session> = Registry::new(1, "session", "sfpm_session_open");

impl<T> Registry<T> {
    const fn new(kind: u64, what: &'static str, opener: &'static str) -> Self {
        Registry {
            slots: Mutex::new(Vec::new()),
            kind,
            what,
            opener,
        }
    }

    pub(super) fn register(&self, value: T) -> u64 {
        let mut slots = lock(&self.slots);
        let index = match slots.iter().position(|s| s.value.is_none()) {
            Some(i) => i,
            None => {
                slots.push(Slot {
                    generation: 1,
                    value: None,
                });
                slots.len() - 1
            }
        };
        slots[index].value = Some(Arc::new(value));
        (self.kind << 63) | (u64::from(slots[index].generation) << 32) | (index as u64 + 1)
    }

    /// The slot and generation of `handle`, or why it cannot be one of this registry's.
    fn split(&self, handle: u64) -> FfiResult<(usize, u32)> {
        let what = self.what;
        if handle >> 63 != self.kind {
            let other = if self.kind == 0 { "a session" } else { "a map" };
            return Err(FfiError::new(
                SFPM_ERR_INVALID_HANDLE,
                format!("invalid {what} handle {handle:#x} ({other} handle?)"),
            ));
        }
        let index = (handle & 0xffff_ffff).checked_sub(1).ok_or_else(|| {
            FfiError::new(
                SFPM_ERR_INVALID_HANDLE,
                format!("invalid {what} handle {handle:#x}"),
            )
        })?;
        Ok((index as usize, ((handle >> 32) as u32) & MAX_GENERATION))
    }

    /// The live value, or `SFPM_ERR_INVALID_HANDLE`. The `Arc` keeps it alive for the call
    /// even if another thread closes the handle meanwhile.
    pub(super) fn get(&self, handle: u64) -> FfiResult<Arc<T>> {
        let (index, generation) = self.split(handle)?;
        let slots = lock(&self.slots);
        match slots.get(index) {
            Some(Slot {
                generation: g,
                value: Some(v),
            }) if *g == generation => Ok(v.clone()),
            _ => Err(FfiError::new(
                SFPM_ERR_INVALID_HANDLE,
                format!(
                    "invalid {} handle {handle:#x} (closed, or not from {})",
                    self.what, self.opener
                ),
            )),
        }
    }

    /// Ends `handle`: its slot's generation moves on, so it is invalid from now on. The value
    /// is dropped outside the registry's lock (unmapping may take a moment), once the calls
    /// still running with it have returned.
    pub(super) fn close(&self, handle: u64) -> FfiResult {
        let (index, generation) = self.split(handle)?;
        let taken = {
            let mut slots = lock(&self.slots);
            match slots.get_mut(index) {
                Some(slot) if slot.generation == generation && slot.value.is_some() => {
                    slot.generation = if slot.generation >= MAX_GENERATION {
                        1
                    } else {
                        slot.generation + 1
                    };
                    slot.value.take()
                }
                _ => None,
            }
        };
        match taken {
            Some(value) => {
                drop(value);
                Ok(())
            }
            None => Err(FfiError::new(
                SFPM_ERR_INVALID_HANDLE,
                format!("invalid {} handle {handle:#x} (already closed?)", self.what),
            )),
        }
    }
}

pub(super) fn get(map: SfpmMap) -> FfiResult<Arc<MapHandle>> {
    MAPS.get(map)
}
