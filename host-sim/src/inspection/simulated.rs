//! A simulated board's print (`print.json`, `array::print`) as the inspection's truth.

use crate::array::print::{Defect, Deposit, DepositIndex, Material, Print};
use crate::{At, Result, SimError};
use dpsa_gerber::pads::{Point, Rigid};
use std::path::Path;

/// Largest print file read, bytes.
pub const MAX_PRINT_BYTES: u64 = 1 << 30;

/// The true placement, defects and paste surface of a printed board.
pub struct PrintTruth {
    /// The printed board's identity (None in prints written before it).
    pub board_id: Option<dpsa_formats::BoardId>,
    /// The true placement: design (paste layer) frame to board frame, mm.
    pub transform: Rigid,
    /// Per pad of the layer: the injected defect's name, None for a good print.
    pub defects: Vec<Option<String>>,
    deposits: Vec<Deposit>,
    index: DepositIndex,
}

impl PrintTruth {
    /// Reads `print.json`; `pads` is the paste layer's pad count, which it must match.
    pub fn load(path: &Path, pads: usize) -> Result<PrintTruth> {
        let bytes = crate::files::read_capped(path, MAX_PRINT_BYTES, "print truth")?;
        let print: Print = serde_json::from_slice(&bytes)
            .at(|| format!("{} is not a dpsa print truth", path.display()))?;
        PrintTruth::new(print, pads).at(|| format!("{}", path.display()))
    }

    /// Builds the truth from a parsed print; `pads` is the paste layer's pad count, which
    /// it must match.
    pub fn new(print: Print, pads: usize) -> Result<PrintTruth> {
        let mut defects = vec![None; pads];
        for p in &print.pads {
            let Some(slot) = defects.get_mut(p.pad) else {
                return Err(SimError::Refused(format!(
                    "the print has pad {} but the paste layer only {pads} pads: another layer",
                    p.pad
                )));
            };
            *slot = match p.defect {
                Defect::None => None,
                d => Some(
                    serde_json::to_value(d)?
                        .as_str()
                        .unwrap_or("unknown")
                        .to_string(),
                ),
            };
        }
        if print.pads.len() != pads {
            return Err(SimError::Refused(format!(
                "the print has {} pads, the paste layer {pads}: another layer",
                print.pads.len()
            )));
        }
        // Paste only: the fiducials' copper is not paste.
        let deposits: Vec<Deposit> = print
            .deposits
            .into_iter()
            .filter(|d| d.material == Material::Paste)
            .collect();
        let index = DepositIndex::new(&deposits);
        Ok(PrintTruth {
            board_id: print.board_id,
            transform: print.design_to_board,
            defects,
            deposits,
            index,
        })
    }

    /// The true paste height above the board at a board point, um.
    pub fn height(&self, p: Point) -> f64 {
        self.index
            .at(p)
            .iter()
            .map(|&k| self.deposits[k as usize].height(p))
            .sum()
    }
}
