//! A study from the line's store: the last boards of one product, inspected under one
//! program, with the program's names, components, package families and limits.
//!
//! A pad is known by its index in the program's paste layer, so boards inspected under
//! another program (another hash) are never mixed in: they are left out and counted. With the
//! program (`--program`) the study has its limits (the fail windows of each pad: volume, area
//! and height in % of nominal, the offsets at `+- offset fail % x the opening's width`), its
//! components and its package families (the placement file's package, else the pad's aperture
//! class, the same land pattern); without it, the pads' stored names only (a component from
//! `REF.PIN`), no families and no limits: the charts and rules without capability.

use crate::capability::SpecLimits;
use crate::study::{BoardRef, PadSpec, Study, StudyError};
use dpsa_inspect::program::{Program, Window};
use dpsa_line::store::{Location, Store, StoreError};
use std::path::{Path, PathBuf};

/// Why a study could not be loaded.
#[derive(Debug, thiserror::Error)]
pub enum LoadError {
    /// No SQLite store at the path (a reader never creates one).
    #[error("no store at {0}: give the line's store (DATA/line.sqlite) or a PostgreSQL URL")]
    NoStore(PathBuf),
    /// The store's error.
    #[error(transparent)]
    Store(#[from] StoreError),
    /// The program or its paste layer.
    #[error("program {path}: {why}")]
    Program {
        /// The program's path.
        path: PathBuf,
        /// What went wrong.
        why: String,
    },
    /// Nothing to study.
    #[error("{0}")]
    Nothing(String),
    /// The stored pads disagree with the program.
    #[error("board {board} ({run_id}): {why}")]
    Mismatch {
        /// The store's board id.
        board: i64,
        /// Its run id.
        run_id: String,
        /// How.
        why: String,
    },
    /// More values than a study holds in memory.
    #[error(
        "{boards} boards of {pads} pads need {} MB in memory, more than the {} MB a study \
         may take: ask for fewer boards (--last)",
        bytes >> 20,
        MAX_STUDY_BYTES >> 20
    )]
    TooLarge {
        /// Boards asked for.
        boards: usize,
        /// Pads a board.
        pads: usize,
        /// The memory they need.
        bytes: u64,
    },
    /// The study refused a board.
    #[error(transparent)]
    Study(#[from] StudyError),
}

/// The class of a pad the inspection could not measure, as the store holds it.
const NOT_MEASURABLE: &str = dpsa_inspect::verdict::Class::NotMeasurable.name();

/// Memory a study holds per pad and board: five measures as `f64`.
const STUDY_BYTES_PER_VALUE: u64 = 5 * 8;

/// Most memory a study takes: 1 GiB, about 4,400 boards of 6,000 pads.
const MAX_STUDY_BYTES: u64 = 1 << 30;

/// The classes of paste where it should not be: under the stencil, for the stencil's
/// cleaning ([`crate::stencil`]).
const SMEARS: [&str; 2] = [
    dpsa_inspect::verdict::Class::Bridge.name(),
    dpsa_inspect::verdict::Class::Shape.name(),
];

/// An aperture's area ratio: its area over its wall's (`perimeter x stencil thickness`).
fn area_ratio(outline: &dpsa_gerber::pads::Outline, stencil_um: f64) -> Option<f64> {
    let wall = outline.perimeter() * stencil_um / 1000.0;
    (wall > 0.0 && wall.is_finite()).then(|| outline.area() / wall)
}

/// What to load.
#[derive(Clone, Debug)]
pub struct Source<'a> {
    /// The store.
    pub store: &'a Location,
    /// The line whose boards are read.
    pub line: &'a str,
    /// The product (`None`: the newest inspected board's).
    pub product: Option<&'a str>,
    /// The program the boards were inspected under (`None`: the newest board's, unnamed).
    pub program: Option<&'a Path>,
    /// At most this many boards, the newest.
    pub last: usize,
    /// Open the store for reading only (the operator's pages); else as the line does
    /// (an older store migrated).
    pub read_only: bool,
}

/// A loaded study and what was left out.
#[derive(Debug)]
pub struct Loaded {
    /// The study, boards oldest first.
    pub study: Study,
    /// The product.
    pub product: String,
    /// The program's hash the boards share.
    pub program_hash: String,
    /// Whether the program (limits, families) was given.
    pub with_program: bool,
    /// Boards of the product among the last `last` inspected under another program.
    pub other_program: usize,
    /// Boards whose pad rows were pruned (retention).
    pub pruned: usize,
}

/// The pads of `program`: names, components, families, limits.
fn program_pads(path: &Path) -> Result<(Vec<PadSpec>, String), LoadError> {
    let bad = |why: String| LoadError::Program {
        path: path.to_owned(),
        why,
    };
    let prog_bytes = dpsa_formats::files::read_capped(path, 16 << 20, "inspection program")
        .map_err(|e| bad(e.to_string()))?;
    let mut program = Program::load(path).map_err(|e| bad(e.to_string()))?;
    let layer_path = program.paste_layer_path(path);
    let layer_bytes = dpsa_formats::files::read_capped(&layer_path, 256 << 20, "paste layer")
        .map_err(|e| bad(e.to_string()))?;
    let (mut pads, _) =
        dpsa_inspect::run::paste_layer_pads(&program, path).map_err(|e| bad(e.to_string()))?;
    dpsa_inspect::teach::apply_components(&mut program, path, &mut pads)
        .map_err(|e| bad(e.to_string()))?;
    let families =
        dpsa_inspect::teach::pad_families(&program, path, &pads).map_err(|e| bad(e.to_string()))?;
    let two = |w: Window| SpecLimits {
        lsl: Some(w.fail[0]),
        usl: Some(w.fail[1]),
    };
    let specs = pads
        .iter()
        .zip(families)
        .map(|(p, family)| {
            let w = program.windows_for(p);
            let (width_mm, _) = dpsa_inspect::measure::opening_size(&p.outline);
            let off = w.offset_pct.fail / 100.0 * width_mm * 1000.0;
            let offset = SpecLimits {
                lsl: Some(-off),
                usl: Some(off),
            };
            PadSpec {
                name: dpsa_inspect::report::cfx_pad(p),
                component: p.component.clone(),
                family,
                limits: [
                    two(w.volume_pct),
                    two(w.height_pct),
                    two(w.area_pct),
                    offset,
                    offset,
                ],
                at_mm: Some(p.outline.centroid()),
                area_ratio: area_ratio(&p.outline, program.stencil_um),
            }
        })
        .collect();
    let hash = dpsa_line::config::fnv_hex(&[&prog_bytes, &layer_bytes]);
    Ok((specs, hash))
}

/// The component of a stored pad name (`dpsa_inspect::report::cfx_pad`: `REF.PIN`, or
/// `REF#INDEX` for a pad without a pin; none for `#INDEX`).
fn component_of(name: &str) -> Option<String> {
    let (c, rest) = name.split_once('.').or_else(|| name.split_once('#'))?;
    (!c.is_empty() && !rest.is_empty()).then(|| c.to_owned())
}

/// Loads the study `src` asks for.
pub fn load(src: &Source) -> Result<Loaded, LoadError> {
    if let Location::Sqlite(p) = src.store {
        if !p.is_file() {
            return Err(LoadError::NoStore(p.clone()));
        }
    }
    let mut store = if src.read_only {
        Store::open_read_only(src.store, src.line)?
    } else {
        Store::open(src.store, src.line)?
    };
    let product = match src.product {
        Some(p) => p.to_owned(),
        None => store
            .inspected_boards(None, 1)?
            .first()
            .map(|b| b.product.clone())
            .ok_or_else(|| {
                LoadError::Nothing(format!(
                    "line {} of {} has no inspected board",
                    src.line, src.store
                ))
            })?,
    };
    let mut boards = store.inspected_boards(Some(&product), src.last)?;
    if boards.is_empty() {
        return Err(LoadError::Nothing(format!(
            "line {} of {} has no inspected board of product {product:?}",
            src.line, src.store
        )));
    }
    let (specs, hash) = match src.program {
        Some(p) => {
            let (s, h) = program_pads(p)?;
            (Some(s), h)
        }
        None => (None, boards[0].program_hash.clone()),
    };
    let before = boards.len();
    boards.retain(|b| b.program_hash == hash);
    let other_program = before - boards.len();
    if boards.is_empty() {
        return Err(LoadError::Nothing(format!(
            "none of the last {before} inspected boards of {product:?} was inspected under \
             this program (hash {hash})"
        )));
    }
    boards.reverse();
    let mut study: Option<Study> = specs.clone().map(Study::new);
    let mut pruned = 0;
    for b in &boards {
        let run_id = format!("{:016x}", b.run_id);
        let rows = store.pads(b.id)?;
        if rows.is_empty() {
            pruned += 1;
            continue;
        }
        let study = study.get_or_insert_with(|| {
            Study::new(
                rows.iter()
                    .map(|r| PadSpec {
                        name: r.name.clone(),
                        component: component_of(&r.name),
                        family: None,
                        limits: Default::default(),
                        at_mm: None,
                        area_ratio: None,
                    })
                    .collect(),
            )
        });
        let n = study.pads().len();
        let bytes = (boards.len() as u64) * (n as u64) * STUDY_BYTES_PER_VALUE;
        if bytes > MAX_STUDY_BYTES {
            return Err(LoadError::TooLarge {
                boards: boards.len(),
                pads: n,
                bytes,
            });
        }
        let mut values = vec![[None; 5]; n];
        for r in &rows {
            let i = r.pad as usize;
            let Some(spec) = study.pads().get(i) else {
                return Err(LoadError::Mismatch {
                    board: b.id,
                    run_id,
                    why: format!("a pad of index {i}, the program has {n}"),
                });
            };
            if spec.name != r.name {
                return Err(LoadError::Mismatch {
                    board: b.id,
                    run_id,
                    why: format!(
                        "pad {i} is {:?} in the store, {:?} in the program",
                        r.name, spec.name
                    ),
                });
            }
            // A pad the inspection could not measure gives no value, whatever numbers its
            // row holds: they are not a measurement to chart.
            if r.class.as_deref() == Some(NOT_MEASURABLE) {
                continue;
            }
            values[i] = [
                r.volume_pct,
                r.height_pct,
                r.area_pct,
                r.offset_x_um,
                r.offset_y_um,
            ];
        }
        study.push(
            BoardRef {
                id: b.id,
                run_id,
                started_unix_s: b.started_unix_s,
                ended_unix_s: b.ended_unix_s.unwrap_or(f64::NAN),
                smears: rows
                    .iter()
                    .filter(|r| matches!(r.class.as_deref(), Some(c) if SMEARS.contains(&c)))
                    .count(),
            },
            &values,
        )?;
    }
    let mut study = match study {
        Some(s) if !s.boards().is_empty() => s,
        _ => {
            return Err(LoadError::Nothing(format!(
                "the {} boards of {product:?} under this program have no pad rows left (pruned)",
                boards.len()
            )))
        }
    };
    // The newest recorded clean of the product's stencil on this line.
    study.set_cleans(
        store
            .cleans(&product, 1)?
            .iter()
            .map(|c| c.cleaned_unix_s)
            .collect(),
    );
    Ok(Loaded {
        study,
        product,
        program_hash: hash,
        with_program: specs.is_some(),
        other_program,
        pruned,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn components_come_from_the_stored_names() {
        assert_eq!(component_of("R12.1"), Some("R12".into()));
        assert_eq!(component_of("U-7.A14"), Some("U-7".into()));
        assert_eq!(component_of("U3#5"), Some("U3".into()));
        assert_eq!(component_of("#17"), None);
        assert_eq!(component_of("R12."), None);
        assert_eq!(component_of("R12"), None);
    }
}
