//! `defmt::Format` for the core's types and errors (`defmt` feature), all in this file.
//!
//! Error messages say the same as their `Display` (`src/error.rs`), so a firmware log reads like
//! a host error.

use crate::frames::feed::{self, FeedError};
use crate::frames::{Config, ConfigError, Trigger};
use crate::height::{ColumnScaleError, Invalid, MAX_COLUMN_SHIFT};
use crate::offload::FrontEndError;
use crate::packets::codec::CodecError;
use crate::packets::PacketError;
use crate::pipeline::{Error, Layout, NewError};
use crate::row::RowHeader;
use crate::sink::SinkError;
use crate::solve::{SolveError, MAX_N, MIN_N};
use ::defmt::{write, Format, Formatter};

impl Format for ConfigError {
    fn format(&self, f: Formatter<'_>) {
        match self {
            ConfigError::Width => write!(f, "width 0 is out of range (at least 1)"),
            ConfigError::Rows => write!(f, "rows 0 is out of range (at least 1)"),
            ConfigError::Count => {
                write!(f, "n is out of range ({=usize}..={=usize})", MIN_N, MAX_N)
            }
            ConfigError::CountsPerPixel => {
                write!(f, "counts_per_pixel 0 is out of range (must be > 0)")
            }
            ConfigError::LsbPerTurn => {
                write!(f, "lsb_per_turn is out of range (0 < lsb_per_turn < 32768)")
            }
            ConfigError::NoiseGain => write!(f, "max_noise_gain is out of range (1..=8)"),
            ConfigError::MaxStep => write!(f, "max_step_rows is out of range (1..=rows)"),
        }
    }
}

impl Format for FeedError {
    fn format(&self, f: Formatter<'_>) {
        match self {
            FeedError::Magic => write!(f, "the magic is not \"DPSR\": not a feed"),
            FeedError::Version(v) => {
                write!(
                    f,
                    "feed version {=u16} is not supported (expected {=u16})",
                    v,
                    feed::VERSION
                )
            }
            FeedError::HeaderLen(l) => write!(f, "header length {=u16} is not 64", l),
            FeedError::HeaderCrc => write!(f, "the header CRC does not match"),
            FeedError::Reserved => write!(f, "reserved bytes are not zero"),
            FeedError::Config(e) => write!(f, "configuration: {}", e),
            FeedError::IntraPeriod => write!(f, "intra period 0 is out of range (at least 1)"),
            FeedError::TableCrc => write!(f, "the reference-phase table CRC does not match"),
            FeedError::ScaleCrc => {
                write!(f, "the per-column height-scale table CRC does not match")
            }
            FeedError::ColumnScale(e) => write!(f, "per-column height scale: {}", e),
            FeedError::Length => write!(
                f,
                "length does not match the feed layout (short or oversized input)"
            ),
            FeedError::Mono12p => {
                write!(f, "Mono12p lines need a saturation level of at most 4095")
            }
        }
    }
}

impl Format for NewError {
    fn format(&self, f: Formatter<'_>) {
        match self {
            NewError::Config(e) => write!(f, "configuration: {}", e),
            NewError::Memory => write!(
                f,
                "memory or reference-phase table smaller than the layout needs"
            ),
            NewError::ColumnScale(e) => write!(f, "per-column height scale: {}", e),
        }
    }
}

impl Format for ColumnScaleError {
    fn format(&self, f: Formatter<'_>) {
        match self {
            ColumnScaleError::Length { expected, got } => write!(
                f,
                "the table has {=usize} entries, expected one per column ({=u16})",
                got,
                expected
            ),
            ColumnScaleError::Shift(s) => write!(
                f,
                "exponent {=u8} is out of range (0..={=u8})",
                s,
                MAX_COLUMN_SHIFT
            ),
            ColumnScaleError::Range { column } => write!(
                f,
                "column {=u16}: LSB per turn is zero or more than a factor of 2 from lsb_per_turn (or not below 32768)",
                column
            ),
        }
    }
}

impl<E: Format> Format for Error<E> {
    fn format(&self, f: Formatter<'_>) {
        match self {
            Error::Sink(e) => write!(f, "sink: {}", e),
            Error::FrameOpen => write!(f, "begin_frame while a frame is open"),
            Error::NoFrame => write!(f, "line or frame end without an open frame"),
            Error::LineOrder { expected, got } => {
                write!(
                    f,
                    "line {=u16} out of order (expected line {=u16})",
                    got, expected
                )
            }
            Error::LineWidth { expected, got } => {
                write!(
                    f,
                    "line of {=usize} samples (expected width {=u16})",
                    got, expected
                )
            }
            Error::Finished => write!(f, "begin_frame after finish"),
            Error::LineFormat => write!(f, "line format does not fit the line pool"),
            Error::FrontEnd(e) => write!(f, "front end: {}", e),
        }
    }
}

impl Format for SolveError {
    fn format(&self, f: Formatter<'_>) {
        match self {
            SolveError::BadCount => write!(
                f,
                "window size is out of range ({=usize}..={=usize} shifts)",
                MIN_N, MAX_N
            ),
            SolveError::IllConditioned => write!(
                f,
                "window noise gain above max_noise_gain (ill-conditioned shifts)"
            ),
        }
    }
}

impl Format for FrontEndError {
    fn format(&self, f: Formatter<'_>) {
        match self {
            FrontEndError::WrongRow { asked, got } => write!(
                f,
                "delivered board row {=i64} when row {=i64} was due",
                got, asked
            ),
            FrontEndError::Failed => write!(f, "no row came (the front end failed or stopped)"),
        }
    }
}

impl Format for Invalid {
    fn format(&self, f: Formatter<'_>) {
        match self {
            Invalid::Saturated => write!(f, "a sample is at or above saturation"),
            Invalid::LowModulation => write!(f, "modulation below min_modulation"),
        }
    }
}

impl Format for PacketError {
    fn format(&self, f: Formatter<'_>) {
        match self {
            PacketError::BufferTooSmall => write!(f, "buffer too small for the packet"),
            PacketError::Truncated => write!(f, "packet truncated"),
            PacketError::BadSync => write!(f, "no sync word"),
            PacketError::BadVersion(v) => write!(
                f,
                "packet version {=u8} is not supported (expected 1 or {=u8})",
                v,
                crate::packets::VERSION
            ),
            PacketError::BadCodec(c) => write!(f, "payload codec {=u8} is unknown", c),
            PacketError::BadLength => {
                write!(f, "payload length does not fit the kind, codec and width")
            }
            PacketError::BadCrc => write!(f, "CRC mismatch"),
            PacketError::BadKind(k) => write!(f, "packet kind {=u8} is unknown", k),
            PacketError::BadWidth(w) => write!(f, "width {=u16} is out of range (1..=8192)", w),
            PacketError::BadHeaderCrc => write!(f, "header CRC mismatch"),
            PacketError::Unchecked => write!(f, "version 1 packet not checked (CRC budget)"),
            PacketError::Codec(e) => write!(f, "payload: {}", e),
        }
    }
}

impl Format for CodecError {
    fn format(&self, f: Formatter<'_>) {
        match self {
            CodecError::BufferTooSmall => write!(f, "row buffer too small for the width"),
            CodecError::Truncated => write!(f, "payload ends before the row does"),
            CodecError::Corrupt => write!(f, "payload is not a valid row code"),
            CodecError::MissingReference => write!(f, "predicted row without its reference row"),
        }
    }
}

impl<E: Format> Format for SinkError<E> {
    fn format(&self, f: Formatter<'_>) {
        match self {
            SinkError::Encode(e) => write!(f, "packet encode: {}", e),
            SinkError::Link(e) => write!(f, "link: {}", e),
            SinkError::FrontEnd(e) => write!(f, "front end's row codec: {}", e),
        }
    }
}

impl Format for Trigger {
    fn format(&self, f: Formatter<'_>) {
        write!(
            f,
            "Trigger {{ seq: {=u32}, latch: {=i64} }}",
            self.seq, self.latch
        )
    }
}

impl Format for Config {
    fn format(&self, f: Formatter<'_>) {
        write!(
            f,
            "Config {{ width: {=u16}, rows: {=u16}, n: {=u8}, camera: {=u8}, max_step_rows: {=u16} }}",
            self.width,
            self.rows,
            self.n,
            self.camera,
            self.max_step_rows
        )
    }
}

impl Format for feed::Header {
    fn format(&self, f: Formatter<'_>) {
        write!(
            f,
            "{} frames {=u32} intra_period {=u32}",
            self.cfg, self.frames, self.intra_period
        )
    }
}

impl Format for Layout {
    fn format(&self, f: Formatter<'_>) {
        write!(
            f,
            "Layout {{ width: {=usize}, pool_lines: {=usize}, slots: {=usize}, scale_columns: {=usize}, packed: {=bool} }}",
            self.width, self.pool_lines, self.slots, self.scale_columns, self.packed
        )
    }
}

impl Format for RowHeader {
    fn format(&self, f: Formatter<'_>) {
        write!(
            f,
            "RowHeader {{ camera: {=u8}, n: {=u8}, row: {=i64}, latch: {=i64}, flags: {=u16:#x}, width: {=u16} }}",
            self.camera,
            self.n,
            self.row,
            self.latch,
            self.flags,
            self.width
        )
    }
}
