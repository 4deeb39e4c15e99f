//! The QEMU board (`mps2-an500`, Cortex-M7): a feed file stands in for the camera and the
//! conveyor, a host file for the output link, SysTick for the instruction counter.
//!
//! Everything crosses to the host by semihosting: the command line names a feed
//! (format: [`dpsa_core::frames::feed`], written by `dpsa target-run`), the packet stream
//! file, and optionally a benchmark file. The feed is read the way the camera delivers
//! it: a trigger record (the pin goes high, the encoder count is latched), then the frame's
//! lines one by one. Nothing is read ahead.
//!
//! What a real board has that this one fakes: the trigger strobe and the encoder capture are
//! values in the file, not pins and a timer; lines arrive by a blocking host read instead of
//! camera DMA into a line ring; the link is a host file with no back-pressure; the clock counts
//! instructions (QEMU `-icount shift=0`), not cycles, so wait states and cache misses are not
//! seen.

use super::{Clock, EncoderCapture, LinePort};
use core::cell::RefCell;
use core::ffi::CStr;
use core::sync::atomic::{AtomicU32, Ordering};
use cortex_m::peripheral::{syst::SystClkSource, SYST};
use cortex_m_rt::exception;
use dpsa_core::frames::feed::{self, FeedError, Header};
use dpsa_core::frames::Trigger;
use dpsa_core::offload::{FrontEnd, FrontEndError, Line as OffloadLine, RowCoder, RowJob};
use dpsa_core::sink::Link;
use dpsa_core::Row;
use semihosting::fs::File;
use semihosting::io::{Read, Seek, SeekFrom, Write};

/// Capacities of the state buffers on this board (see `crate::state`).
pub mod cap {
    /// Widest line `W`.
    pub const WIDTH: usize = 2048;
    /// Samples in the raw-line pool in the state region (DTCM on a real board): the default
    /// geometry's 60 lines of 2048 px (`max_step_rows = 10`, `n = 4`).
    pub const POOL_SAMPLES: usize = 60 * 2048;
    /// Samples in the external-RAM line pool (`memory.x`: EXTRAM, 16 MiB), used when a
    /// geometry needs more than [`POOL_SAMPLES`]: the full-frame feed (H = 2048 rows, four
    /// frames about 520 rows apart, max step 650 rows, W = 2048) needs 3900 lines of 2048 px:
    /// 11.4 MiB as Mono12p (15.2 MiB as u16).
    pub const EXT_POOL_SAMPLES: usize = 8 * 1024 * 1024;
    /// Lines in the pool (free-list entries).
    pub const POOL_LINES: usize = 8192;
    /// Open-row slots.
    pub const SLOTS: usize = 4096;
}

/// A board failure.
#[derive(Clone, Copy, Debug)]
pub enum Error {
    /// A semihosting call failed (host errno, -1 if unknown).
    Io(i32),
    /// The feed ended inside frame `frame` at line `line` (byte `offset`).
    Truncated { frame: u32, line: u32, offset: u64 },
    /// The feed's header or reference table is malformed.
    Feed(FeedError),
    /// A line was read without a frame, or past the frame's last line.
    LineOrder { frame: u32, line: u32 },
    /// The encoder was read with no latched trigger.
    NoTrigger,
    /// The command line is not `dpsa-firmware FEED OUT [BENCH] [fabric=LOG [payloads=LOG]]`.
    Usage,
    /// The fabric log is not one for this feed (bad magic, version, width or run id).
    FabricLog,
    /// A path longer than the board's buffer.
    PathTooLong,
}

impl defmt::Format for Error {
    fn format(&self, f: defmt::Formatter<'_>) {
        match *self {
            Error::Io(e) => defmt::write!(f, "host I/O error (errno {=i32})", e),
            Error::Truncated {
                frame,
                line,
                offset,
            } => defmt::write!(
                f,
                "feed truncated in frame {=u32} at line {=u32} (byte {=u64})",
                frame,
                line,
                offset
            ),
            Error::Feed(e) => defmt::write!(f, "malformed feed: {}", e),
            Error::LineOrder { frame, line } => {
                defmt::write!(
                    f,
                    "line {=u32} of frame {=u32} read out of order",
                    line,
                    frame
                )
            }
            Error::NoTrigger => defmt::write!(f, "encoder read without a trigger"),
            Error::Usage => defmt::write!(
                f,
                "usage: dpsa-firmware FEED OUT [BENCH] [fabric=LOG [payloads=LOG]]"
            ),
            Error::FabricLog => defmt::write!(
                f,
                "the fabric log is not one for this feed (magic, version, width or run id)"
            ),
            Error::PathTooLong => defmt::write!(f, "path too long"),
        }
    }
}

impl embedded_hal::digital::Error for Error {
    fn kind(&self) -> embedded_hal::digital::ErrorKind {
        embedded_hal::digital::ErrorKind::Other
    }
}

fn io(e: semihosting::io::Error) -> Error {
    Error::Io(e.raw_os_error().unwrap_or(-1))
}

/// A NUL-terminated copy of a path.
pub struct Path {
    buf: [u8; 512],
}

impl Path {
    /// The empty path.
    pub const fn empty() -> Path {
        Path { buf: [0; 512] }
    }

    /// Sets the path in place (no 512-byte temporaries on the stack).
    pub fn set(&mut self, s: &str) -> Result<(), Error> {
        if s.len() >= self.buf.len() || s.as_bytes().contains(&0) {
            return Err(Error::PathTooLong);
        }
        self.buf.fill(0);
        self.buf[..s.len()].copy_from_slice(s.as_bytes());
        Ok(())
    }

    pub fn c_str(&self) -> &CStr {
        // The buffer holds a NUL by construction.
        CStr::from_bytes_until_nul(&self.buf).unwrap_or(c"")
    }
}

/// The command line: feed, packet stream, optional benchmark file, optional fabric log (the
/// FPGA front end's rows, [`FabricLog`]).
pub struct Args {
    pub feed: Path,
    pub out: Path,
    pub bench: Option<Path>,
    pub fabric: Option<Path>,
    pub payloads: Option<Path>,
}

impl Args {
    /// No paths yet (fill with [`Args::read`]).
    pub const fn empty() -> Args {
        Args {
            feed: Path::empty(),
            out: Path::empty(),
            bench: None,
            fabric: None,
            payloads: None,
        }
    }

    /// Reads the command line into `self`, in place (the paths are 1.5 KiB: a returned value
    /// would be copied through the caller's frame). Never inlined: the 2 KiB semihosting
    /// command-line buffer lives only in this frame, not in the caller's for the whole run
    /// (both count against the stack budget).
    #[inline(never)]
    pub fn read(&mut self) -> Result<(), Error> {
        let args = semihosting::experimental::env::args::<2048>().map_err(io)?;
        let mut given = 0;
        for a in (&args).skip(1) {
            let s = a.map_err(|_| Error::Usage)?;
            if let Some(log) = s.strip_prefix("fabric=") {
                if given < 2 || self.fabric.is_some() {
                    return Err(Error::Usage);
                }
                self.fabric.insert(Path::empty()).set(log)?;
                continue;
            }
            if let Some(log) = s.strip_prefix("payloads=") {
                if given < 2 || self.payloads.is_some() {
                    return Err(Error::Usage);
                }
                self.payloads.insert(Path::empty()).set(log)?;
                continue;
            }
            match given {
                0 => self.feed.set(s)?,
                1 => self.out.set(s)?,
                2 => self.bench.insert(Path::empty()).set(s)?,
                _ => return Err(Error::Usage),
            }
            given += 1;
        }
        if given < 2 {
            return Err(Error::Usage);
        }
        Ok(())
    }
}

/// Read position in the feed.
struct Reader {
    file: File,
    header: Header,
    /// Byte offset of the next unread byte.
    pos: u64,
    /// Frames whose trigger was taken.
    started: u32,
    /// Lines read of the current frame.
    line: u32,
    /// A trigger record read but not yet taken (the strobe is high).
    armed: Option<Trigger>,
    /// Byte offset where frame data begins.
    frames_at: u64,
}

impl Reader {
    fn read(&mut self, buf: &mut [u8], frame: u32, line: u32) -> Result<(), Error> {
        let mut done = 0;
        while done < buf.len() {
            let k = self.file.read(&mut buf[done..]).map_err(io)?;
            if k == 0 {
                return Err(Error::Truncated {
                    frame,
                    line,
                    offset: self.pos + done as u64,
                });
            }
            done += k;
        }
        self.pos += done as u64;
        Ok(())
    }

    fn frame_bytes(&self) -> u64 {
        self.header.frame_len() as u64
    }

    /// Raises the strobe if another frame follows: skips what is left of the current frame and
    /// reads the next trigger record.
    fn arm(&mut self) -> Result<bool, Error> {
        if self.armed.is_some() {
            return Ok(true);
        }
        if self.started >= self.header.frames {
            return Ok(false);
        }
        let next = self.frames_at + self.started as u64 * self.frame_bytes();
        if self.pos != next {
            self.file.seek(SeekFrom::Start(next)).map_err(io)?;
            self.pos = next;
        }
        let mut b = [0u8; feed::TRIGGER_LEN];
        self.read(&mut b, self.started, 0)?;
        self.armed = Some(Trigger::decode(&b).map_err(Error::Feed)?);
        Ok(true)
    }
}

/// The feed, opened: header, and the shared reader behind the board's parts.
pub struct Feed {
    reader: RefCell<Reader>,
}

impl Feed {
    /// Opens a feed and reads its header and reference-phase table into `ref_phase`
    /// (at least `W` entries), and its per-column height-scale table, if it has one, into
    /// `column_scale` (at least `W` entries; checked against the configuration).
    pub fn open(
        path: &Path,
        ref_phase: &mut [u32],
        column_scale: &mut [u16],
        scratch: &mut [u8],
    ) -> Result<Feed, Error> {
        let mut file = File::open(path.c_str()).map_err(io)?;
        let mut h = [0u8; feed::HEADER_LEN];
        let mut reader_pos = 0u64;
        read_exact(&mut file, &mut h, &mut reader_pos)?;
        let header = Header::decode(&h).map_err(Error::Feed)?;
        let w = header.cfg.width as usize;
        if w > ref_phase.len() || header.table_len() > scratch.len() {
            return Err(Error::Feed(FeedError::Length));
        }
        let t = &mut scratch[..header.table_len()];
        read_exact(&mut file, t, &mut reader_pos)?;
        feed::decode_table(t, &mut ref_phase[..w]).map_err(Error::Feed)?;
        if header.column_scale.is_some() {
            let n = header.scale_table_len();
            if w > column_scale.len() || n > scratch.len() {
                return Err(Error::Feed(FeedError::Length));
            }
            let t = &mut scratch[..n];
            read_exact(&mut file, t, &mut reader_pos)?;
            feed::decode_scale_table(t, &header, &mut column_scale[..w]).map_err(Error::Feed)?;
        }
        let reader = Reader {
            file,
            header,
            pos: reader_pos,
            started: 0,
            line: 0,
            armed: None,
            frames_at: reader_pos,
        };
        Ok(Feed {
            reader: RefCell::new(reader),
        })
    }

    pub fn header(&self) -> Header {
        self.reader.borrow().header
    }

    /// The board's parts over this feed.
    pub fn parts(&self) -> (Strobe<'_>, Capture<'_>, Lines<'_>) {
        (
            Strobe(&self.reader),
            Capture(&self.reader),
            Lines(&self.reader),
        )
    }
}

fn read_exact(file: &mut File, buf: &mut [u8], pos: &mut u64) -> Result<(), Error> {
    let mut done = 0;
    while done < buf.len() {
        let k = file.read(&mut buf[done..]).map_err(io)?;
        if k == 0 {
            return Err(Error::Feed(FeedError::Length));
        }
        done += k;
    }
    *pos += done as u64;
    Ok(())
}

/// The frame strobe: high while a trigger is latched and not yet taken.
pub struct Strobe<'a>(&'a RefCell<Reader>);
/// The encoder capture register.
pub struct Capture<'a>(&'a RefCell<Reader>);
/// The camera line port.
pub struct Lines<'a>(&'a RefCell<Reader>);

impl embedded_hal::digital::ErrorType for Strobe<'_> {
    type Error = Error;
}

impl embedded_hal::digital::InputPin for Strobe<'_> {
    fn is_high(&mut self) -> Result<bool, Error> {
        self.0.borrow_mut().arm()
    }

    fn is_low(&mut self) -> Result<bool, Error> {
        self.is_high().map(|h| !h)
    }
}

impl EncoderCapture for Capture<'_> {
    type Error = Error;
    fn captured(&mut self) -> Result<i64, Error> {
        self.0
            .borrow()
            .armed
            .map(|t| t.latch)
            .ok_or(Error::NoTrigger)
    }
}

impl LinePort for Lines<'_> {
    type Error = Error;

    fn frame_seq(&mut self) -> Result<u32, Error> {
        let mut r = self.0.borrow_mut();
        let t = r.armed.take().ok_or(Error::NoTrigger)?;
        r.started += 1;
        r.line = 0;
        Ok(t.seq)
    }

    fn read_line(&mut self, line: &mut [u8]) -> Result<(), Error> {
        let mut r = self.0.borrow_mut();
        let (frame, l) = (r.started, r.line);
        let c = r.header.cfg;
        if frame == 0 || l >= c.rows as u32 || line.len() != r.header.line_len() {
            return Err(Error::LineOrder { frame, line: l });
        }
        // u16 samples are little-endian, this core's byte order; Mono12p is bytes: read in
        // place either way.
        r.read(line, frame - 1, l)?;
        r.line += 1;
        Ok(())
    }

    fn ended(&mut self) -> Result<bool, Error> {
        let mut r = self.0.borrow_mut();
        Ok(!r.arm()?)
    }
}

/// The samples of a line as bytes (little-endian target, so the file's byte order).
pub fn as_bytes_mut(line: &mut [u16]) -> &mut [u8] {
    bytemuck::cast_slice_mut(line)
}

/// The output link: a host file.
pub struct HostFile {
    file: File,
}

impl HostFile {
    pub fn create(path: &Path) -> Result<HostFile, Error> {
        Ok(HostFile {
            file: File::create(path.c_str()).map_err(io)?,
        })
    }
}

impl Link for HostFile {
    type Error = Error;
    fn send(&mut self, packet: &[u8]) -> Result<(), Error> {
        self.file.write_all(packet).map_err(io)
    }
    fn flush(&mut self) -> Result<(), Error> {
        self.file.flush().map_err(io)
    }
}

/// The output link over the board's UART0 (the CMSDK APB UART of mps2-an500 at
/// `0x4000_4000`), which QEMU carries to the host as a TCP connection
/// (`-serial tcp:127.0.0.1:PORT`, `dpsa target-run --link`): the frame grabber's stream goes
/// live to `dpsa line run`. Byte by byte, waiting while the transmitter is full: QEMU holds
/// it full while the connection cannot take more, so the host's back-pressure reaches the
/// firmware (a real board's UART or Ethernet DMA would do the same with its FIFO).
pub struct Uart {
    _private: (),
}

/// CMSDK APB UART0 of mps2-an500.
const UART0: usize = 0x4000_4000;
/// Register offsets: data, state (bit 0: transmitter full), control (bit 0: transmit
/// enable), baud divider.
const UART_DATA: usize = 0x00;
const UART_STATE: usize = 0x04;
const UART_CTRL: usize = 0x08;
const UART_BAUDDIV: usize = 0x10;

impl Uart {
    /// Enables UART0's transmitter (the smallest baud divider the peripheral allows: the
    /// emulated line has no baud rate).
    pub fn open() -> Uart {
        // SAFETY: UART0 is this board's memory-mapped peripheral; nothing else in the
        // firmware touches it, and these are aligned 32-bit register writes.
        #[allow(unsafe_code)]
        unsafe {
            core::ptr::write_volatile((UART0 + UART_BAUDDIV) as *mut u32, 16);
            core::ptr::write_volatile((UART0 + UART_CTRL) as *mut u32, 1);
        }
        Uart { _private: () }
    }

    fn put(&mut self, b: u8) {
        // SAFETY: as in `open`: aligned reads of the state register, writes of the data
        // register of this board's UART0.
        #[allow(unsafe_code)]
        unsafe {
            while core::ptr::read_volatile((UART0 + UART_STATE) as *const u32) & 1 != 0 {}
            core::ptr::write_volatile((UART0 + UART_DATA) as *mut u32, u32::from(b));
        };
    }
}

impl Link for Uart {
    type Error = Error;
    fn send(&mut self, packet: &[u8]) -> Result<(), Error> {
        for &b in packet {
            self.put(b);
        }
        Ok(())
    }
    fn flush(&mut self) -> Result<(), Error> {
        // SAFETY: as in `put`.
        #[allow(unsafe_code)]
        unsafe {
            while core::ptr::read_volatile((UART0 + UART_STATE) as *const u32) & 1 != 0 {}
        }
        Ok(())
    }
}

/// The output link the command line names: a host file, or `uart:` for [`Uart`].
pub enum Output {
    /// A host file (semihosting).
    File(HostFile),
    /// UART0.
    Uart(Uart),
}

impl Output {
    /// The link `OUT` names.
    pub fn open(out: &Path) -> Result<Output, Error> {
        if out.c_str().to_bytes() == b"uart:" {
            Ok(Output::Uart(Uart::open()))
        } else {
            HostFile::create(out).map(Output::File)
        }
    }
}

impl Link for Output {
    type Error = Error;
    fn send(&mut self, packet: &[u8]) -> Result<(), Error> {
        match self {
            Output::File(f) => f.send(packet),
            Output::Uart(u) => u.send(packet),
        }
    }
    fn flush(&mut self) -> Result<(), Error> {
        match self {
            Output::File(f) => f.flush(),
            Output::Uart(u) => u.flush(),
        }
    }
}

/// SysTick wraps (every 2^24 ticks).
static WRAPS: AtomicU32 = AtomicU32::new(0);

#[exception]
fn SysTick() {
    WRAPS.fetch_add(1, Ordering::Relaxed);
}

/// SysTick on the core clock, extended to 64 bits by its wrap interrupt. On mps2 the core
/// clock is 25 MHz; under `-icount shift=0` one instruction is 1 ns, so a tick is 40
/// instructions (the benchmark calibrates this on a loop of known length).
pub struct SysTickClock {
    _syst: SYST,
}

impl SysTickClock {
    pub fn start(mut syst: SYST) -> SysTickClock {
        syst.set_clock_source(SystClkSource::Core);
        syst.set_reload(0x00FF_FFFF);
        syst.clear_current();
        syst.enable_interrupt();
        syst.enable_counter();
        SysTickClock { _syst: syst }
    }
}

impl Clock for SysTickClock {
    fn ticks(&self) -> u64 {
        loop {
            let w0 = WRAPS.load(Ordering::Acquire);
            let v = SYST::get_current();
            let w1 = WRAPS.load(Ordering::Acquire);
            if w0 == w1 {
                return ((w0 as u64) << 24) | (0x00FF_FFFF - v) as u64;
            }
        }
    }
}

/// Writes the benchmark results (`key value` lines).
pub fn write_text(path: &Path, text: &[u8]) -> Result<(), Error> {
    let mut f = File::create(path.c_str()).map_err(io)?;
    f.write_all(text).map_err(io)
}

/// Ends the QEMU run with an exit status.
pub fn exit(code: i32) -> ! {
    semihosting::process::exit(code)
}

/// The FPGA front end of this board (`docs/fpga.md`): the rows its completion DMA would write,
/// read from the fabric log that `dpsa target-run --front-end` made with the RTL's Verilator
/// model (format: `dpsa_fpga::front`). The camera's lines stay in the fabric's pool, so
/// [`FrontEnd::keep`] has nothing to do; a row is the next record, which must be the row the
/// pipeline asks for. Its reads are host I/O, counted apart ([`FabricLog::io_ticks`]).
pub struct FabricLog<'c, C: Clock> {
    file: File,
    width: usize,
    clock: &'c C,
    /// Ticks spent reading the log (host I/O, not the MCU's work).
    pub io_ticks: u64,
    /// Rows read.
    pub rows: u64,
    /// The host error behind a [`FrontEndError::Failed`], if any.
    pub error: Option<Error>,
}

/// The fabric log's header: magic, version 1, width, the recording's run id.
const FABRIC_MAGIC: [u8; 4] = *b"DPSF";
/// The payload log's magic (the same header).
const PAYLOAD_MAGIC: [u8; 4] = *b"DPSP";

fn check_log_header(h: &[u8; 16], magic: [u8; 4], width: usize, run_id: u64) -> Result<(), Error> {
    let version = u16::from_le_bytes([h[4], h[5]]);
    let w = u16::from_le_bytes([h[6], h[7]]) as usize;
    let mut id = [0u8; 8];
    id.copy_from_slice(&h[8..16]);
    if h[..4] != magic || version != 1 || w != width || u64::from_le_bytes(id) != run_id {
        return Err(Error::FabricLog);
    }
    Ok(())
}

impl<'c, C: Clock> FabricLog<'c, C> {
    /// Opens the log and checks its header against the feed's width and run id.
    pub fn open(path: &Path, width: usize, run_id: u64, clock: &'c C) -> Result<Self, Error> {
        let mut file = File::open(path.c_str()).map_err(io)?;
        let mut h = [0u8; 16];
        let mut pos = 0;
        read_exact(&mut file, &mut h, &mut pos)?;
        check_log_header(&h, FABRIC_MAGIC, width, run_id)?;
        Ok(FabricLog {
            file,
            width,
            clock,
            io_ticks: 0,
            rows: 0,
            error: None,
        })
    }

    fn read(&mut self, heights: &mut [i16], valid: &mut [u8]) -> Result<(i64, u16), Error> {
        let w = self.width;
        let mut head = [0u8; 12];
        let mut pos = 0;
        read_exact(&mut self.file, &mut head, &mut pos)?;
        let hb: &mut [u8] = bytemuck::cast_slice_mut(&mut heights[..w]);
        read_exact(&mut self.file, hb, &mut pos)?;
        read_exact(&mut self.file, &mut valid[..w.div_ceil(8)], &mut pos)?;
        let mut row = [0u8; 8];
        row.copy_from_slice(&head[..8]);
        Ok((
            i64::from_le_bytes(row),
            u16::from_le_bytes([head[8], head[9]]),
        ))
    }
}

impl<C: Clock> FrontEnd for FabricLog<'_, C> {
    fn keep(&mut self, _slot: u16, _line: OffloadLine<'_>) {}

    fn row(
        &mut self,
        job: &RowJob<'_>,
        _last: OffloadLine<'_>,
        heights: &mut [i16],
        valid: &mut [u8],
    ) -> Result<u16, FrontEndError> {
        let t0 = self.clock.ticks();
        let r = self.read(heights, valid);
        self.io_ticks += self.clock.ticks() - t0;
        match r {
            Ok((row, flags)) if row == job.row => {
                self.rows += 1;
                Ok(flags)
            }
            Ok((got, _)) => Err(FrontEndError::WrongRow {
                asked: job.row,
                got,
            }),
            Err(e) => {
                self.error = Some(e);
                Err(FrontEndError::Failed)
            }
        }
    }
}

/// The FPGA front end's row codec (`docs/fpga.md`): each row's payload as the fabric's payload
/// DMA would deliver it, read from the payload log that `dpsa target-run --front-end` made with
/// the codec's Verilator model. It must be the payload of the row the sink frames. Its reads
/// are host I/O, counted apart ([`FabricPayloads::io_ticks`]).
pub struct FabricPayloads<'c, C: Clock> {
    file: File,
    clock: &'c C,
    /// Ticks spent reading the log (host I/O, not the MCU's work).
    pub io_ticks: u64,
    /// Payloads read.
    pub rows: u64,
    /// The host error behind a [`FrontEndError::Failed`], if any.
    pub error: Option<Error>,
}

impl<'c, C: Clock> FabricPayloads<'c, C> {
    /// Opens the log and checks its header against the feed's width and run id.
    pub fn open(path: &Path, width: usize, run_id: u64, clock: &'c C) -> Result<Self, Error> {
        let mut file = File::open(path.c_str()).map_err(io)?;
        let mut h = [0u8; 16];
        let mut pos = 0;
        read_exact(&mut file, &mut h, &mut pos)?;
        check_log_header(&h, PAYLOAD_MAGIC, width, run_id)?;
        Ok(FabricPayloads {
            file,
            clock,
            io_ticks: 0,
            rows: 0,
            error: None,
        })
    }

    fn read(&mut self, payload: &mut [u8]) -> Result<(i64, usize), Error> {
        let mut head = [0u8; 12];
        let mut pos = 0;
        read_exact(&mut self.file, &mut head, &mut pos)?;
        let mut row = [0u8; 8];
        row.copy_from_slice(&head[..8]);
        let len = u32::from_le_bytes([head[8], head[9], head[10], head[11]]) as usize;
        let dst = payload.get_mut(..len).ok_or(Error::FabricLog)?;
        read_exact(&mut self.file, dst, &mut pos)?;
        Ok((i64::from_le_bytes(row), len))
    }
}

impl<C: Clock> RowCoder for FabricPayloads<'_, C> {
    fn code(&mut self, row: &Row<'_>, payload: &mut [u8]) -> Result<usize, FrontEndError> {
        let t0 = self.clock.ticks();
        let r = self.read(payload);
        self.io_ticks += self.clock.ticks() - t0;
        match r {
            Ok((got, len)) if got == row.header.row => {
                self.rows += 1;
                Ok(len)
            }
            Ok((got, _)) => Err(FrontEndError::WrongRow {
                asked: row.header.row,
                got,
            }),
            Err(e) => {
                self.error = Some(e);
                Err(FrontEndError::Failed)
            }
        }
    }
}
