//! The host's packet link: the core's [`PacketSink`](dpsa_core::sink::PacketSink) writes its
//! packets to any `std::io::Write` (a file, a pipe, memory) through [`IoLink`].

use dpsa_core::sink::Link;
use std::io::Write;

/// A [`Link`] over any writer: the packet stream goes to a file, a pipe or memory.
pub struct IoLink<W: Write>(pub W);

impl<W: Write> Link for IoLink<W> {
    type Error = std::io::Error;
    fn send(&mut self, packet: &[u8]) -> std::io::Result<()> {
        self.0.write_all(packet)
    }
    fn flush(&mut self) -> std::io::Result<()> {
        self.0.flush()
    }
}
