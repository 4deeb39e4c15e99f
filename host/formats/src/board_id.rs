//! The board identity every camera's recording, stream and map of one board carries.

use serde::{Deserialize, Serialize};

/// A board identity: a non-zero u64, written in JSON as 16 lowercase hex digits (a JSON
/// number would lose bits in readers that hold numbers as f64).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct BoardId(pub u64);

impl std::fmt::Display for BoardId {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{:016x}", self.0)
    }
}

impl std::str::FromStr for BoardId {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        let ok = s.len() == 16 && s.bytes().all(|b| b.is_ascii_hexdigit());
        match u64::from_str_radix(s, 16) {
            Ok(0) if ok => Err("a board id of 0 means none; expected a non-zero id".into()),
            Ok(v) if ok => Ok(BoardId(v)),
            _ => Err(format!("board id {s:?} is not 16 hex digits")),
        }
    }
}

impl Serialize for BoardId {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.collect_str(self)
    }
}

impl<'de> Deserialize<'de> for BoardId {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        let s = String::deserialize(d)?;
        s.parse().map_err(serde::de::Error::custom)
    }
}
