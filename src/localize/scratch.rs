//! Per-thread scratch buffers of the query path: matching's score blocks and decoded tiles,
//! guided matching's rows in view. Allocated at every query, such a buffer lands in fresh
//! pages and pays their faults each time, so each thread keeps the ones it used for its next
//! query. What a thread keeps is bounded: at most [`KEEP_MAX_BUFFERS`] buffers of at most
//! [`KEEP_MAX_VALUES`] values (32 MB a thread; a `--threads` worker or a caller's thread keeps
//! them until it ends). A larger request gets a buffer of its own, dropped after use.

use std::cell::RefCell;

/// The longest buffer (values) a thread keeps: guided matching's rows in view fit
/// ([`super::guided`] decodes at most this many), as does a score block of 8,192 keypoints.
pub(super) const KEEP_MAX_VALUES: usize = 4 << 20;
/// Buffers a thread keeps at most: the query path nests two (a tile and its score block).
const KEEP_MAX_BUFFERS: usize = 2;

thread_local! {
    static FREE: RefCell<Vec<Vec<f32>>> = const { RefCell::new(Vec::new()) };
}

/// Runs `f` on `len` values of this thread's scratch, then keeps the buffer for the next call.
/// The values are whatever a previous use left, another query's among them: `f` must write
/// every value before it reads it (in tests and debug builds they start as `f32::MAX`, so a
/// value read unwritten wins every comparison and shows).
pub(crate) fn with_f32<R>(len: usize, f: impl FnOnce(&mut [f32]) -> R) -> R {
    if len > KEEP_MAX_VALUES {
        return f(&mut vec![0.0; len]);
    }
    let kept = FREE
        .try_with(|free| {
            let mut free = free.borrow_mut();
            // The smallest kept buffer that fits.
            let fits = (0..free.len())
                .filter(|&i| free[i].len() >= len)
                .min_by_key(|&i| free[i].len());
            fits.map(|i| free.swap_remove(i))
        })
        .ok()
        .flatten();
    // None fits: a new one of this exact size (growing a kept one would copy its old values
    // and could double its capacity past the bound).
    let mut buffer = kept.unwrap_or_else(|| vec![0.0; len]);
    if cfg!(any(test, debug_assertions)) {
        buffer[..len].fill(f32::MAX);
    }
    let out = f(&mut buffer[..len]);
    let _ = FREE.try_with(|free| {
        let mut free = free.borrow_mut();
        if free.len() < KEEP_MAX_BUFFERS {
            free.push(buffer);
        } else if let Some(shortest) = (0..free.len()).min_by_key(|&i| free[i].len()) {
            // Full: keep the longer ones, which serve every shorter request.
            if free[shortest].len() < buffer.len() {
                free[shortest] = buffer;
            }
        }
    });
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The lengths this thread keeps (each test runs on a thread of its own, so a test starts
    /// with none).
    fn kept() -> Vec<usize> {
        FREE.with(|free| free.borrow().iter().map(Vec::len).collect())
    }

    #[test]
    fn a_buffer_is_reused_by_the_next_call_and_nested_calls_get_their_own() {
        assert!(kept().is_empty());
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
        let mut lengths = kept();
        lengths.sort_unstable();
        assert_eq!(lengths, [100, 1000]);
        // A third nesting level: the shorter kept buffer gives way to a longer one.
        with_f32(10, |_| with_f32(10, |_| with_f32(5000, |_| ())));
        assert_eq!(kept().iter().max(), Some(&5000));
        assert_eq!(kept().len(), KEEP_MAX_BUFFERS);
    }

    #[test]
    fn what_a_previous_use_left_reads_as_max_in_tests() {
        with_f32(8, |b| b.fill(-1.0));
        with_f32(8, |b| assert!(b.iter().all(|&v| v == f32::MAX)));
    }

    #[test]
    fn a_request_over_the_bound_leaves_the_kept_buffers_alone() {
        with_f32(KEEP_MAX_VALUES, |_| ());
        let before = kept();
        with_f32(KEEP_MAX_VALUES + 1, |b| {
            assert_eq!(b.len(), KEEP_MAX_VALUES + 1)
        });
        assert_eq!(kept(), before);
        assert_eq!(before, [KEEP_MAX_VALUES]);
    }

    #[test]
    fn a_kept_buffer_too_short_is_not_grown_but_joined_by_one_of_the_exact_size() {
        with_f32(64, |_| ());
        with_f32(128, |b| assert_eq!(b.len(), 128));
        let mut lengths = kept();
        lengths.sort_unstable();
        assert_eq!(lengths, [64, 128]);
        FREE.with(|free| assert!(free.borrow().iter().all(|b| b.capacity() == b.len())));
    }
}
