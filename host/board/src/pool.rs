//! Buffers kept from band to band. A band's grids are megabytes each, which glibc maps afresh
//! for every allocation and the kernel then zeroes page by page: over a quarter of `dpsa
//! board-bench`'s time on the paper board while every band allocated its own. The stitching's
//! layers ([`LAYERS`]) and the blend's band buffers ([`BAND_F32`], [`BAND_U8`]) take their
//! buffers here and hand them back when their band is done; a finished map empties the pools
//! ([`clear`]). Shared by the process, not per map: the line stitches two boards at a time and
//! a band's buffers are the same size in both.

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

/// Empties every pool (a map is finished: the memory goes back to the system).
pub(crate) fn clear() {
    LAYERS.empty();
    BAND_F32.empty();
    BAND_U8.empty();
}
