//! # dpsa-formats: the bottom of the host
//!
//! What every host crate above reads and writes, with no knowledge of how it was measured:
//!
//! | module | what |
//! | --- | --- |
//! | [`array`](mod@array) | the array recording's manifest `array.json`: the array's design and the board's size and identity |
//! | [`calibration`] | the calibration file: every camera's configuration of the core, its lateral mapping and dead pixels |
//! | [`files`] | bounded reads, atomic writes, output directories that appear whole, inputs never overwritten |
//! | [`height_code`] | a height's 16-bit code in `heights.png` and the kept maps |
//! | [`heightmap`] | the core's rows as a height map (the decoded stream, the reference) |
//! | [`grid`] | the board map's grids: heights in board millimetres and their placement |
//! | [`board_map`] | the board map directory's format name and colour scale |
//! | [`board_id`] | the board identity shared by a board's recordings, streams and maps |
//! | [`kind`] | what kind of file or directory a path is (from its first bytes or marker), to name a wrong input for what it is |
//! | [`images`] | 16-bit and false-colour PNGs |
//! | [`kept_map`] | a board's measured map as the line keeps it for its pages |
//! | [`labels`] | labels beside marks in a picture, none over another |
//! | [`progress`] | progress bars on stderr |
//! | [`recording`] | a camera's recording manifest (`manifest.json`): camera, calibration, processing, trigger log, and the range checks they share with the calibration file |

pub mod array;
pub mod board_id;
pub mod board_map;
pub mod calibration;
pub mod files;
pub mod grid;
pub mod height_code;
pub mod heightmap;
pub mod images;
pub mod instructions;
pub mod kept_map;
pub mod kind;
pub mod labels;
pub mod picture;
pub mod progress;
pub mod recording;
pub mod surface;
pub mod time;

pub use board_id::BoardId;
