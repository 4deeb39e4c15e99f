//! The configuration-sized state, with capacities fixed by the board (heapless style: no
//! allocator, the capacity is in the type). It lives in the `.state` section (`memory.x`:
//! DTCM on a real board).

use crate::board::qemu::cap;
use dpsa_core::accumulate::V;
use dpsa_core::packets;
use dpsa_core::pipeline::{Layout, Slot};
use dpsa_core::Config;

/// Packet buffer for the widest line: header, worst-case payload, CRC.
pub const PACKET_CAP: usize = packets::max_packet_len(cap::WIDTH);

/// Every buffer the firmware sizes by the configuration.
pub struct State {
    /// Raw-line pool of the pipeline.
    pub lines: [u16; cap::POOL_SAMPLES],
    pub free: [u16; cap::POOL_LINES],
    pub slots: [Slot; cap::SLOTS],
    /// Output row: heights and validity.
    pub heights: [i16; cap::WIDTH],
    pub valid: [u8; cap::WIDTH / 8],
    /// Reference phase `phi_0(c)` (calibration).
    pub ref_phase: [u32; cap::WIDTH],
    /// The line being received.
    pub line: [u16; cap::WIDTH],
    /// Codec reference row (the previous row, for predicted rows).
    pub codec_heights: [i16; cap::WIDTH],
    pub codec_valid: [u8; cap::WIDTH / 8],
    /// One packet.
    pub packet: [u8; PACKET_CAP],
    /// Benchmark only: one row of reduced pixels, between the two timed stages.
    pub bench_acc: [V; cap::WIDTH],
}

/// Why the state cannot hold a configuration.
#[derive(Clone, Copy, Debug, defmt::Format)]
pub struct TooSmall {
    pub needed_samples: usize,
    pub have_samples: usize,
}

impl State {
    /// The pipeline memory for `cfg`, or what is missing.
    pub fn check(cfg: &Config) -> Result<Layout, TooSmall> {
        let l = Layout::of(cfg);
        let needed = l.pool_lines * l.width;
        if l.width > cap::WIDTH || l.pool_lines > cap::POOL_LINES || l.slots > cap::SLOTS || needed > cap::POOL_SAMPLES {
            return Err(TooSmall { needed_samples: needed, have_samples: cap::POOL_SAMPLES });
        }
        Ok(l)
    }

    /// Bytes of every buffer the firmware uses for `cfg` (the pipeline's [`Layout::bytes`], the
    /// line being received, the codec reference row and one packet).
    pub fn bytes_for(cfg: &Config) -> usize {
        let l = Layout::of(cfg);
        let w = l.width;
        l.bytes() + w * 2 + w * 2 + w.div_ceil(8) + packets::max_packet_len(w)
    }
}

/// Takes the state, once, zeroed.
pub fn take() -> Option<&'static mut State> {
    use core::mem::MaybeUninit;
    use core::sync::atomic::{AtomicBool, Ordering};
    #[link_section = ".state"]
    static mut STATE: MaybeUninit<State> = MaybeUninit::uninit();
    static TAKEN: AtomicBool = AtomicBool::new(false);
    if TAKEN.swap(true, Ordering::AcqRel) {
        return None;
    }
    // SAFETY: the flag makes this the only reference ever handed out. Every field is an array
    // of integers or of `Slot` (integers only), for which all-zero bytes are a valid value, so
    // the zeroed memory is an initialised `State`. `.state` is NOLOAD: it must be zeroed here.
    unsafe {
        let p = &mut *core::ptr::addr_of_mut!(STATE);
        core::ptr::write_bytes(p.as_mut_ptr(), 0, 1);
        Some(p.assume_init_mut())
    }
}
