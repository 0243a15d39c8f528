//! Per-thread scratch buffers of the query path: matching's score blocks and decoded map
//! rows, guided matching's rows in view. A buffer allocated at every query lands in fresh
//! pages and pays their faults each time (matching's 8 MB score block cost 0.8 ms a query on
//! the 1 M-point street), so each thread keeps the buffers it used for the next query.

use std::cell::RefCell;

/// A buffer longer than this (values) is dropped after use, not kept: what a thread keeps
/// stays bounded whatever one query asked for (guided matching's rows in view are at most
/// 4 Mi values, matching's blocks a few Mi).
const KEEP_MAX_VALUES: usize = 8 << 20;
/// Buffers a thread keeps at most (nested uses take one each).
const KEEP_MAX_BUFFERS: usize = 4;

thread_local! {
    static FREE: RefCell<Vec<Vec<f32>>> = const { RefCell::new(Vec::new()) };
}

/// Runs `f` on `len` values from this thread's scratch (their contents are whatever a previous
/// use left: `f` writes before it reads), then keeps the buffer for the next call.
pub(crate) fn with_f32<R>(len: usize, f: impl FnOnce(&mut [f32]) -> R) -> R {
    let mut buffer = FREE
        .with(|free| {
            let mut free = free.borrow_mut();
            // The smallest kept buffer that fits; else the largest, which grows least.
            let fits = (0..free.len())
                .filter(|&i| free[i].len() >= len)
                .min_by_key(|&i| free[i].len());
            let pick = fits.or_else(|| (0..free.len()).max_by_key(|&i| free[i].len()));
            pick.map(|i| free.swap_remove(i))
        })
        .unwrap_or_default();
    if buffer.len() < len {
        buffer.resize(len, 0.0);
    }
    let out = f(&mut buffer[..len]);
    if buffer.len() <= KEEP_MAX_VALUES {
        FREE.with(|free| {
            let mut free = free.borrow_mut();
            if free.len() < KEEP_MAX_BUFFERS {
                free.push(buffer);
            }
        });
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn kept() -> Vec<usize> {
        FREE.with(|free| free.borrow().iter().map(Vec::len).collect())
    }

    #[test]
    fn a_buffer_is_reused_by_the_next_call_and_nested_calls_get_their_own() {
        let first = with_f32(1000, |b| {
            b.fill(1.0);
            b.as_ptr() as usize
        });
        let again = with_f32(600, |b| {
            assert_eq!(b.len(), 600);
            b.as_ptr() as usize
        });
        assert_eq!(first, again, "the kept buffer is reused");
        with_f32(100, |outer| {
            outer.fill(2.0);
            with_f32(100, |inner| {
                assert_ne!(outer.as_ptr(), inner.as_ptr());
                inner.fill(3.0);
            });
            assert!(
                outer.iter().all(|&v| v == 2.0),
                "a nested call writes elsewhere"
            );
        });
        assert!(kept().len() <= KEEP_MAX_BUFFERS);
    }

    #[test]
    fn a_buffer_longer_than_the_limit_is_not_kept() {
        with_f32(KEEP_MAX_VALUES + 1, |b| {
            assert_eq!(b.len(), KEEP_MAX_VALUES + 1)
        });
        assert!(kept().iter().all(|&len| len <= KEEP_MAX_VALUES));
    }
}
