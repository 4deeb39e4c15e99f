//! Buffers kept from band to band, and on request from board to board. A band's grids are
//! megabytes each, which glibc maps afresh for every allocation and the kernel then zeroes
//! page by page: over a quarter of `dpsa board-bench`'s time on the paper board while every
//! band allocated its own. The stitching's layers (`LAYERS`) and the blend's band buffers
//! (`BAND_F32`, `BAND_U8`) take their buffers here and hand them back when their band is
//! done. Shared by the process, not per map: the line stitches two boards at a time and a
//! band's buffers are the same size in both.
//!
//! A finished map empties the pools (`clear`): one board, as `dpsa board` makes, gives its
//! memory back to the system. A process that makes board after board (the line) calls
//! [`keep_between_boards`] once: the band pools are then kept, the map's own buffers (its
//! heights, its cameras: a paper board's are 190 and 48 MB) come from `MAP_F32` and
//! `MAP_U8`, which the map's last user fills again with [`give_map`] and [`give_camera`],
//! and the chunks of rows handed between the stitching's stages (`ROWS`, [`give_rows`]) and
//! the stitcher's held rows (`HELD`) are reused too. A map grown into fresh memory has every
//! page of it faulted in and zeroed as its bands are copied in, on the blend's thread, after
//! the last row too: with the chunks, some 80,000 page faults a paper board
//! (`docs/board.md`, twenty-first part).

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Mutex;

/// A pool of at most `max` buffers of `T`.
pub(crate) struct Pool<T> {
    bufs: Mutex<Vec<Vec<T>>>,
    max: usize,
}

impl<T: Copy> Pool<T> {
    const fn new(max: usize) -> Pool<T> {
        Pool {
            bufs: Mutex::new(Vec::new()),
            max,
        }
    }

    /// A buffer of `n` values: the smallest kept one that holds them (else any kept one, else
    /// a new one). Its values are whatever its last user left (`fill` where it had fewer): the
    /// caller writes every one.
    pub(crate) fn take(&self, n: usize, fill: T) -> Vec<T> {
        let taken = self.bufs.lock().ok().and_then(|mut s| {
            let fits = (0..s.len())
                .filter(|&k| s[k].capacity() >= n)
                .min_by_key(|&k| s[k].capacity());
            let k = fits.or_else(|| s.len().checked_sub(1))?;
            Some(s.swap_remove(k))
        });
        let mut v = taken.unwrap_or_default();
        v.truncate(n);
        v.resize(n, fill);
        v
    }

    /// Keeps `v` for a later [`Pool::take`] (dropped when the pool is full).
    pub(crate) fn give(&self, v: Vec<T>) {
        if let Ok(mut s) = self.bufs.lock() {
            if s.len() < self.max && v.capacity() > 0 {
                s.push(v);
            }
        }
    }

    /// An empty buffer with room for `n` values: the smallest kept one that has it, else a
    /// new one (a kept one too small stays kept).
    pub(crate) fn take_empty(&self, n: usize) -> Vec<T> {
        let taken = self.bufs.lock().ok().and_then(|mut s| {
            let k = (0..s.len())
                .filter(|&k| s[k].capacity() >= n)
                .min_by_key(|&k| s[k].capacity())?;
            Some(s.swap_remove(k))
        });
        match taken {
            Some(mut v) => {
                v.clear();
                v
            }
            None => Vec::with_capacity(n),
        }
    }

    /// Keeps `v` as [`Pool::give`] does when the pools are kept between boards
    /// ([`keep_between_boards`]); else drops it.
    pub(crate) fn give_kept(&self, v: Vec<T>) {
        if kept_between_boards() {
            self.give(v);
        }
    }

    /// Buffers kept (for the tests).
    #[cfg(test)]
    fn kept(&self) -> usize {
        self.bufs.lock().map_or(0, |s| s.len())
    }

    fn empty(&self) {
        if let Ok(mut s) = self.bufs.lock() {
            *s = Vec::new();
        }
    }
}

/// The layers' grids: two bands' layers (up to four grids for each of three cameras; one band
/// is blended while the next is resampled, see `assemble`).
pub(crate) static LAYERS: Pool<f32> = Pool::new(36);

/// The blend's band heights and variances (of two boards at a time).
pub(crate) static BAND_F32: Pool<f32> = Pool::new(4);

/// The blend's band cameras.
pub(crate) static BAND_U8: Pool<u8> = Pool::new(4);

/// The maps' heights and variances: two boards stitched at a time and one being judged
/// or written.
pub(crate) static MAP_F32: Pool<f32> = Pool::new(4);

/// The maps' cameras.
pub(crate) static MAP_U8: Pool<u8> = Pool::new(3);

/// Rows handed from stage to stage of the stitching: a camera's chunks as they are taken
/// from its rows (`run::Collector::take_chunk`), as the stitcher hands them to its
/// unwrapping threads (`assemble::Stitcher::push`) and as they come back unwrapped
/// (`unwrap::Unwrapper::next`), each a few megabytes; handed back once copied on
/// ([`give_rows`]). Kept between boards only.
pub(crate) static ROWS: Pool<f32> = Pool::new(12);

/// The cameras' unwrapped rows a stitcher holds for its bands (grown to their largest
/// early in a board: kept for the next board's stitcher).
pub(crate) static HELD: Pool<f32> = Pool::new(6);

/// Whether the pools are kept from map to map ([`keep_between_boards`]).
static KEEP: AtomicBool = AtomicBool::new(false);

/// Keeps the pools from board to board for the rest of the process (a service that makes
/// board after board: their memory is reused instead of faulted in afresh for every board).
/// The memory kept is bounded by the pools' sizes.
pub fn keep_between_boards() {
    KEEP.store(true, Ordering::Relaxed);
}

/// Whether [`keep_between_boards`] was called.
pub fn kept_between_boards() -> bool {
    KEEP.load(Ordering::Relaxed)
}

/// Hands a finished map's heights (or variances) back for a later map, when the pools are
/// kept between boards; else drops them.
pub fn give_map(heights: crate::Grid) {
    MAP_F32.give_kept(heights.data);
}

/// Hands rows copied on back for later chunks, when the pools are kept between boards
/// (else drops them): a camera chunk's heights once the stitcher has them
/// (`assemble::Stitcher::push` copies them).
pub fn give_rows(rows: Vec<f32>) {
    ROWS.give_kept(rows);
}

/// Hands a finished map's cameras back, as [`give_map`].
pub fn give_camera(camera: Vec<u8>) {
    MAP_U8.give_kept(camera);
}

/// A map is finished: unless the pools are kept between boards, every pool is emptied (the
/// memory goes back to the system).
pub(crate) fn clear() {
    if kept_between_boards() {
        return;
    }
    LAYERS.empty();
    BAND_F32.empty();
    BAND_U8.empty();
    MAP_F32.empty();
    MAP_U8.empty();
    ROWS.empty();
    HELD.empty();
}

#[cfg(test)]
mod tests {
    use super::*;

    /// An empty buffer comes from the smallest kept one with room, leaves one too small
    /// kept, is new when none has room, and never holds more than the pool's bound.
    #[test]
    fn an_empty_buffer_is_the_smallest_kept_one_with_room() {
        let pool: Pool<u8> = Pool::new(3);
        pool.give(Vec::with_capacity(10));
        pool.give(vec![1; 100]);
        pool.give(vec![2; 50]);
        pool.give(vec![3; 70]);
        assert_eq!(pool.kept(), 3, "the bound");
        let v = pool.take_empty(40);
        assert!(
            v.is_empty() && v.capacity() >= 50 && v.capacity() < 100,
            "{}",
            v.capacity()
        );
        assert_eq!(pool.kept(), 2);
        let v = pool.take_empty(60);
        assert!(v.is_empty() && v.capacity() >= 100);
        assert_eq!(pool.kept(), 1);
        // Only the one of 10 is left: too small, so a new one, and the small one stays.
        let v = pool.take_empty(11);
        assert!(v.is_empty() && v.capacity() >= 11);
        assert_eq!(pool.kept(), 1);
        let v = pool.take_empty(10);
        assert!(v.is_empty() && v.capacity() >= 10);
        assert_eq!(pool.kept(), 0);
        pool.give(Vec::new());
        assert_eq!(pool.kept(), 0, "a buffer without room is not kept");
    }
}
