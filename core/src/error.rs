//! `Display` and `core::error::Error` for every error type of the core, in one place.
//!
//! Messages are one sentence, lowercase, without a trailing period, and name the field or value
//! at fault. Wrapping variants ([`Error::Sink`], [`NewError::Config`], [`FeedError::Config`],
//! [`PacketError::Codec`], [`SinkError::Link`]) give the wrapped error as `source()`.

use crate::frames::feed::{FeedError, VERSION as FEED_VERSION};
use crate::frames::ConfigError;
use crate::height::{ColumnScaleError, Invalid, MAX_COLUMN_SHIFT};
use crate::offload::FrontEndError;
use crate::packets::codec::CodecError;
use crate::packets::{PacketError, VERSION as PACKET_VERSION};
use crate::pipeline::{Error, NewError};
use crate::sink::SinkError;
use crate::solve::{SolveError, MAX_N, MIN_N};
use core::error::Error as StdError;
use core::fmt::{self, Display, Formatter};

impl Display for ConfigError {
    fn fmt(&self, f: &mut Formatter<'_>) -> fmt::Result {
        match self {
            ConfigError::Width => f.write_str("width 0 is out of range (at least 1)"),
            ConfigError::Rows => f.write_str("rows 0 is out of range (at least 1)"),
            ConfigError::Count => write!(f, "n is out of range ({MIN_N}..={MAX_N})"),
            ConfigError::CountsPerPixel => {
                f.write_str("counts_per_pixel 0 is out of range (must be > 0)")
            }
            ConfigError::LsbPerTurn => {
                f.write_str("lsb_per_turn is out of range (0 < lsb_per_turn < 32768)")
            }
            ConfigError::NoiseGain => f.write_str("max_noise_gain is out of range (1..=8)"),
            ConfigError::MaxStep => f.write_str("max_step_rows is out of range (1..=rows)"),
        }
    }
}

impl StdError for ConfigError {}

impl Display for FeedError {
    fn fmt(&self, f: &mut Formatter<'_>) -> fmt::Result {
        match self {
            FeedError::Magic => f.write_str("the magic is not \"DPSR\": not a feed"),
            FeedError::Version(v) => write!(
                f,
                "feed version {v} is not supported (expected {FEED_VERSION})"
            ),
            FeedError::HeaderLen(l) => write!(f, "header length {l} is not 64"),
            FeedError::HeaderCrc => f.write_str("the header CRC does not match"),
            FeedError::Reserved => f.write_str("reserved bytes are not zero"),
            FeedError::Config(e) => write!(f, "configuration: {e}"),
            FeedError::IntraPeriod => f.write_str("intra period 0 is out of range (at least 1)"),
            FeedError::TableCrc => f.write_str("the reference-phase table CRC does not match"),
            FeedError::ScaleCrc => {
                f.write_str("the per-column height-scale table CRC does not match")
            }
            FeedError::ColumnScale(e) => write!(f, "per-column height scale: {e}"),
            FeedError::Length => {
                f.write_str("length does not match the feed layout (short or oversized input)")
            }
            FeedError::Mono12p => {
                f.write_str("Mono12p lines need a saturation level of at most 4095")
            }
        }
    }
}

impl StdError for FeedError {
    fn source(&self) -> Option<&(dyn StdError + 'static)> {
        match self {
            FeedError::Config(e) => Some(e),
            FeedError::ColumnScale(e) => Some(e),
            _ => None,
        }
    }
}

impl Display for NewError {
    fn fmt(&self, f: &mut Formatter<'_>) -> fmt::Result {
        match self {
            NewError::Config(e) => write!(f, "configuration: {e}"),
            NewError::Memory => {
                f.write_str("memory or reference-phase table smaller than the layout needs")
            }
            NewError::ColumnScale(e) => write!(f, "per-column height scale: {e}"),
        }
    }
}

impl Display for ColumnScaleError {
    fn fmt(&self, f: &mut Formatter<'_>) -> fmt::Result {
        match self {
            ColumnScaleError::Length { expected, got } => write!(
                f,
                "the table has {got} entries, expected one per column ({expected})"
            ),
            ColumnScaleError::Shift(s) => write!(
                f,
                "exponent {s} is out of range (0..={MAX_COLUMN_SHIFT})"
            ),
            ColumnScaleError::Range { column } => write!(
                f,
                "column {column}: LSB per turn is zero or more than a factor of 2 from lsb_per_turn (or not below 32768)"
            ),
        }
    }
}

impl StdError for ColumnScaleError {}

impl StdError for NewError {
    fn source(&self) -> Option<&(dyn StdError + 'static)> {
        match self {
            NewError::Config(e) => Some(e),
            NewError::ColumnScale(e) => Some(e),
            NewError::Memory => None,
        }
    }
}

impl<E: Display> Display for Error<E> {
    fn fmt(&self, f: &mut Formatter<'_>) -> fmt::Result {
        match self {
            Error::Sink(e) => write!(f, "sink: {e}"),
            Error::FrameOpen => f.write_str("begin_frame while a frame is open"),
            Error::NoFrame => f.write_str("line or frame end without an open frame"),
            Error::LineOrder { expected, got } => {
                write!(f, "line {got} out of order (expected line {expected})")
            }
            Error::LineWidth { expected, got } => {
                write!(f, "line of {got} samples (expected width {expected})")
            }
            Error::Finished => f.write_str("begin_frame after finish"),
            Error::LineFormat => f.write_str(
                "a packed line for a 16-bit line pool, or a 16-bit line for a packed pool \
                 without its scratch line (Layout::scratch_bytes)",
            ),
            Error::FrontEnd(e) => write!(f, "front end: {e}"),
        }
    }
}

impl<E: StdError + 'static> StdError for Error<E> {
    fn source(&self) -> Option<&(dyn StdError + 'static)> {
        match self {
            Error::Sink(e) => Some(e),
            _ => None,
        }
    }
}

impl Display for SolveError {
    fn fmt(&self, f: &mut Formatter<'_>) -> fmt::Result {
        match self {
            SolveError::BadCount => {
                write!(f, "window size is out of range ({MIN_N}..={MAX_N} shifts)")
            }
            SolveError::IllConditioned => {
                f.write_str("window noise gain above max_noise_gain (ill-conditioned shifts)")
            }
        }
    }
}

impl StdError for SolveError {}

impl Display for Invalid {
    fn fmt(&self, f: &mut Formatter<'_>) -> fmt::Result {
        match self {
            Invalid::Saturated => f.write_str("a sample is at or above saturation"),
            Invalid::LowModulation => f.write_str("modulation below min_modulation"),
        }
    }
}

impl StdError for Invalid {}

impl Display for FrontEndError {
    fn fmt(&self, f: &mut Formatter<'_>) -> fmt::Result {
        match self {
            FrontEndError::WrongRow { asked, got } => {
                write!(f, "delivered board row {got} when row {asked} was due")
            }
            FrontEndError::Failed => f.write_str("no row came (the front end failed or stopped)"),
        }
    }
}

impl StdError for FrontEndError {}

impl Display for PacketError {
    fn fmt(&self, f: &mut Formatter<'_>) -> fmt::Result {
        match self {
            PacketError::BufferTooSmall => f.write_str("buffer too small for the packet"),
            PacketError::Truncated => f.write_str("packet truncated"),
            PacketError::BadSync => f.write_str("no sync word"),
            PacketError::BadVersion(v) => write!(
                f,
                "packet version {v} is not supported (expected 1 or {PACKET_VERSION})"
            ),
            PacketError::BadCodec(c) => write!(f, "payload codec {c} is unknown"),
            PacketError::BadLength => {
                f.write_str("payload length does not fit the kind, codec and width")
            }
            PacketError::BadCrc => f.write_str("CRC mismatch"),
            PacketError::BadKind(k) => write!(f, "packet kind {k} is unknown"),
            PacketError::BadWidth(w) => write!(f, "width {w} is out of range (1..=8192)"),
            PacketError::BadHeaderCrc => f.write_str("header CRC mismatch"),
            PacketError::Unchecked => f.write_str(
                "version 1 packet not checked: the CRC budget for false sync words is spent",
            ),
            PacketError::Codec(e) => write!(f, "payload: {e}"),
        }
    }
}

impl StdError for PacketError {
    fn source(&self) -> Option<&(dyn StdError + 'static)> {
        match self {
            PacketError::Codec(e) => Some(e),
            _ => None,
        }
    }
}

impl Display for CodecError {
    fn fmt(&self, f: &mut Formatter<'_>) -> fmt::Result {
        match self {
            CodecError::BufferTooSmall => f.write_str("row buffer too small for the width"),
            CodecError::Truncated => f.write_str("payload ends before the row does"),
            CodecError::Corrupt => f.write_str("payload is not a valid row code"),
            CodecError::MissingReference => f.write_str("predicted row without its reference row"),
        }
    }
}

impl StdError for CodecError {}

impl<E: Display> Display for SinkError<E> {
    fn fmt(&self, f: &mut Formatter<'_>) -> fmt::Result {
        match self {
            SinkError::Encode(e) => write!(f, "packet encode: {e}"),
            SinkError::Link(e) => write!(f, "link: {e}"),
            SinkError::FrontEnd(e) => write!(f, "front end's row codec: {e}"),
        }
    }
}

impl<E: StdError + 'static> StdError for SinkError<E> {
    fn source(&self) -> Option<&(dyn StdError + 'static)> {
        match self {
            SinkError::Encode(e) => Some(e),
            SinkError::Link(e) => Some(e),
            SinkError::FrontEnd(e) => Some(e),
        }
    }
}
