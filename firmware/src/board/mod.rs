//! What a frame grabber has, as traits; the pipeline code above this module knows nothing else.
//!
//! A frame grabber for the conveyor has four things the measurement depends on:
//! - a **trigger** input: the camera's frame strobe, an [`embedded_hal::digital::InputPin`]
//!   that goes high when a frame was exposed;
//! - an **encoder capture**: the quadrature counter of the conveyor, latched in hardware by
//!   that strobe ([`EncoderCapture`]);
//! - the camera's **line port**: the frame counter and the lines of the frame, in order, as the
//!   camera DMA delivers them ([`LinePort`]);
//! - an output **link** for the packet stream: Ethernet, USB, a FIFO to the host PC; it
//!   implements the core's [`dpsa_core::sink::Link`], over which `dpsa_core::sink::PacketSink`
//!   sends the packets.
//!
//! [`Triggered`] puts the first three together into the [`LineSource`] the firmware runs on.
//! A [`Clock`] counts instructions for the benchmark. Adding a real board means implementing
//! these traits in a module beside [`qemu`].

pub mod qemu;

use dpsa_core::Trigger;
use embedded_hal::digital::InputPin;

/// The encoder counter's capture register, latched by the frame trigger.
pub trait EncoderCapture {
    type Error: defmt::Format;
    /// The count latched at the last trigger edge.
    fn captured(&mut self) -> Result<i64, Self::Error>;
}

/// The camera's line port.
pub trait LinePort {
    type Error: defmt::Format;
    /// Frame counter of the frame whose trigger was seen last.
    fn frame_seq(&mut self) -> Result<u32, Self::Error>;
    /// The next line of that frame, in order `0..H`, as the camera sends it (`line` holds
    /// exactly one line: `2 W` bytes of u16 samples, or Mono12p).
    fn read_line(&mut self, line: &mut [u8]) -> Result<(), Self::Error>;
    /// No further frame will come (the board has left the field of view, the feed ended).
    fn ended(&mut self) -> Result<bool, Self::Error>;
}

/// Frames as the pipeline consumes them.
pub trait LineSource {
    type Error: defmt::Format;
    /// Waits for the next frame's trigger (frame counter, latched encoder count); `Ok(None)`
    /// when acquisition has ended.
    fn next_frame(&mut self) -> Result<Option<Trigger>, Self::Error>;
    /// The next line of the current frame, in order `0..H`, in the camera's format.
    fn read_line(&mut self, line: &mut [u8]) -> Result<(), Self::Error>;
}

/// A free-running tick counter for instruction counts (the benchmark only).
pub trait Clock {
    /// Ticks since start (monotonic, 64 bits so it never wraps in practice).
    fn ticks(&self) -> u64;
}

/// Why a [`Triggered`] source failed.
#[derive(Clone, Copy, Debug, defmt::Format)]
pub enum SourceError<T, E, P> {
    Trigger(T),
    Encoder(E),
    Port(P),
}

/// A [`LineSource`] from a trigger pin, an encoder capture and a line port.
pub struct Triggered<T, E, P> {
    pub trigger: T,
    pub encoder: E,
    pub port: P,
}

impl<T, E, P> LineSource for Triggered<T, E, P>
where
    T: InputPin,
    T::Error: defmt::Format,
    E: EncoderCapture,
    P: LinePort,
{
    type Error = SourceError<T::Error, E::Error, P::Error>;

    fn next_frame(&mut self) -> Result<Option<Trigger>, Self::Error> {
        loop {
            if self.trigger.is_high().map_err(SourceError::Trigger)? {
                let latch = self.encoder.captured().map_err(SourceError::Encoder)?;
                let seq = self.port.frame_seq().map_err(SourceError::Port)?;
                return Ok(Some(Trigger { seq, latch }));
            }
            if self.port.ended().map_err(SourceError::Port)? {
                return Ok(None);
            }
        }
    }

    fn read_line(&mut self, line: &mut [u8]) -> Result<(), Self::Error> {
        self.port.read_line(line).map_err(SourceError::Port)
    }
}
