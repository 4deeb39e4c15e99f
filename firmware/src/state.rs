//! The configuration-sized state, with capacities fixed by the board (heapless: no allocator,
//! the capacity is in the type, the length is what the configuration needs). It lives in the
//! `.state` section (`memory.x`: DTCM on a real board).

use crate::board::qemu::cap;
use dpsa_core::frames::feed::Header;
use dpsa_core::frames::mono12p;
use dpsa_core::frames::registration::Slot;
use dpsa_core::packets;
use dpsa_core::pipeline::Layout;
use heapless::Vec;

/// Packet buffer for the widest line: header, worst-case payload, CRC.
pub const PACKET_CAP: usize = packets::max_packet_len(cap::WIDTH);

/// The pipeline's packing buffer for a 16-bit feed on a packed pool (`Layout::scratch_bytes`).
pub const SCRATCH_CAP: usize = mono12p::stored_len(cap::WIDTH);

/// Every buffer the firmware sizes by the configuration.
pub struct State {
    /// Raw-line pool of the pipeline. A plain array, not a `Vec`: before the configuration is
    /// known it is the scratch buffer for the feed's reference-phase table, and the benchmark
    /// reads samples from its whole capacity.
    pub lines: [u16; cap::POOL_SAMPLES],
    pub free: Vec<u16, { cap::POOL_LINES }>,
    pub slots: Vec<Slot, { cap::SLOTS }>,
    /// Output row: heights and validity.
    pub heights: Vec<i16, { cap::WIDTH }>,
    pub valid: Vec<u8, { cap::WIDTH / 8 }>,
    /// Reference phase `phi_0(c)` (calibration).
    pub ref_phase: Vec<u32, { cap::WIDTH }>,
    /// Per-column height-scale mantissas (calibration, `dpsa_core::height::ColumnScale`):
    /// `W` entries when the feed has the table, else empty.
    pub column_scale: Vec<u16, { cap::WIDTH }>,
    /// The line being received, as the feed sends it: `W` u16 samples, or Mono12p bytes
    /// (`ceil(3 ceil(W/2) / 2)` u16 units).
    pub line: Vec<u16, { cap::WIDTH }>,
    /// The pipeline's packing buffer: only for a 16-bit feed whose configuration packs the
    /// pool (`saturation <= 4095`); empty otherwise.
    pub scratch: Vec<u8, SCRATCH_CAP>,
    /// Codec reference row (the previous row, for predicted rows).
    pub codec_heights: Vec<i16, { cap::WIDTH }>,
    pub codec_valid: Vec<u8, { cap::WIDTH / 8 }>,
    /// One packet.
    pub packet: Vec<u8, PACKET_CAP>,
}

/// Why the state cannot hold a configuration.
#[derive(Clone, Copy, Debug, defmt::Format)]
pub struct TooSmall {
    pub needed_samples: usize,
    pub have_samples: usize,
}

/// Sets `v` to `len` zero elements.
fn zeroed<T: Clone + Default, const N: usize>(v: &mut Vec<T, N>, len: usize) -> Result<(), ()> {
    v.clear();
    v.resize(len, T::default()).map_err(|_| ())
}

impl State {
    /// Gives `ref_phase` and `column_scale` their full capacity, for reading a feed's tables of
    /// any supported width.
    pub fn open_ref_phase(&mut self) {
        let _ = zeroed(&mut self.ref_phase, cap::WIDTH);
        let _ = zeroed(&mut self.column_scale, cap::WIDTH);
    }

    /// Sizes every buffer for `cfg` (zeroed; `ref_phase` keeps its first `W` entries, and
    /// `column_scale` too with a height-scale `table`, else none), or says what is missing. The line pool is [`State::lines`] when it is large enough, else the
    /// external-RAM pool ([`PoolAt::External`], see [`ext_pool`]).
    pub fn size_for(&mut self, header: &Header) -> Result<(Layout, PoolAt), TooSmall> {
        let (cfg, table) = (&header.cfg, header.column_scale.is_some());
        let l = Layout::of(cfg).with_column_scale(table);
        let (w, nb) = (l.width, l.width.div_ceil(8));
        let needed = l.pool_units();
        let too_small = TooSmall {
            needed_samples: needed,
            have_samples: cap::EXT_POOL_SAMPLES,
        };
        let at = if needed <= cap::POOL_SAMPLES {
            PoolAt::State
        } else {
            PoolAt::External
        };
        if needed > cap::EXT_POOL_SAMPLES || w > self.ref_phase.len() {
            return Err(too_small);
        }
        self.ref_phase.truncate(w);
        self.column_scale.truncate(if table { w } else { 0 });
        (|| {
            zeroed(&mut self.free, l.pool_lines)?;
            zeroed(&mut self.slots, l.slots)?;
            zeroed(&mut self.heights, w)?;
            zeroed(&mut self.valid, nb)?;
            zeroed(&mut self.line, line_units(header))?;
            zeroed(&mut self.scratch, scratch_bytes(header))?;
            zeroed(&mut self.codec_heights, w)?;
            zeroed(&mut self.codec_valid, nb)?;
            zeroed(&mut self.packet, packets::max_packet_len(w))
        })()
        .map_err(|()| too_small)?;
        Ok((l, at))
    }

    /// Bytes of every buffer the firmware uses for a feed (the pipeline's [`Layout::bytes`]
    /// with or without the height-scale table, the line being received, the packing buffer
    /// if the feed needs one, the codec reference row and one packet).
    pub fn bytes_for(header: &Header) -> usize {
        let l = Layout::of(&header.cfg).with_column_scale(header.column_scale.is_some());
        let w = l.width;
        l.bytes()
            + line_units(header) * 2
            + scratch_bytes(header)
            + w * 2
            + w.div_ceil(8)
            + packets::max_packet_len(w)
    }
}

/// u16 units of the line being received: the feed's line length, rounded up.
pub fn line_units(header: &Header) -> usize {
    header.line_len().div_ceil(2)
}

/// Bytes of the pipeline's packing buffer: only a 16-bit feed on a packed pool needs one.
pub fn scratch_bytes(header: &Header) -> usize {
    if header.mono12p {
        0
    } else {
        Layout::of(&header.cfg).scratch_bytes()
    }
}

/// Where the line pool of a geometry lives.
#[derive(Clone, Copy, Debug, PartialEq, Eq, defmt::Format)]
pub enum PoolAt {
    /// [`State::lines`], in the state region.
    State,
    /// The external-RAM pool ([`ext_pool`]).
    External,
}

/// The external-RAM line pool, once: `memory.x` places it in the `.extram` NOLOAD section
/// (under QEMU the 16 MiB RAM of mps2-an500 at 0x60000000, on a frame grabber its SDRAM).
/// Not zeroed: the pipeline writes every sample before reading it.
#[allow(unsafe_code)] // a `static mut` handed out once
pub fn ext_pool() -> Option<&'static mut [u16]> {
    use core::sync::atomic::{AtomicBool, Ordering};
    #[link_section = ".extram"]
    static mut POOL: [u16; cap::EXT_POOL_SAMPLES] = [0; cap::EXT_POOL_SAMPLES];
    static TAKEN: AtomicBool = AtomicBool::new(false);
    if TAKEN.swap(true, Ordering::AcqRel) {
        return None;
    }
    // SAFETY: the flag makes this the only reference ever handed out. The section is NOLOAD
    // (never initialised), and any bytes are valid `u16`s.
    unsafe { Some(&mut *core::ptr::addr_of_mut!(POOL)) }
}

/// Takes the state, once, zeroed: every `Vec` empty.
#[allow(unsafe_code)] // a `static mut` handed out once, zeroed
pub fn take() -> Option<&'static mut State> {
    use core::mem::MaybeUninit;
    use core::sync::atomic::{AtomicBool, Ordering};
    #[link_section = ".state"]
    static mut STATE: MaybeUninit<State> = MaybeUninit::uninit();
    static TAKEN: AtomicBool = AtomicBool::new(false);
    if TAKEN.swap(true, Ordering::AcqRel) {
        return None;
    }
    // SAFETY: the flag makes this the only reference ever handed out. `.state` is NOLOAD, so it
    // is zeroed here, and all-zero bytes are a valid `State`: the pool is an array of integers,
    // and every field that is a `heapless::Vec` holds a length (0: empty) and a buffer of
    // `MaybeUninit` elements, for which any bytes are valid; so the zeroed memory is a `State`
    // whose vectors are all empty.
    unsafe {
        let p = &mut *core::ptr::addr_of_mut!(STATE);
        core::ptr::write_bytes(p.as_mut_ptr(), 0, 1);
        Some(p.assume_init_mut())
    }
}
