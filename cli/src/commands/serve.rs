//! `dpsa serve`: the operator's web pages over the line's store (docs/web.md).

use anyhow::{bail, Result};
use dpsa_line::store::Location;
use std::net::SocketAddr;

#[derive(clap::Args)]
pub struct Args {
    /// The line's store: its SQLite file (DATA/line.sqlite) or a PostgreSQL URL. Opened
    /// read-only.
    #[arg(long)]
    store: String,
    /// The line whose boards are shown.
    #[arg(long, default_value = dpsa_line::store::DEFAULT_LINE)]
    line: String,
    /// The address to listen on. Loopback unless given: another address shows the line to
    /// whoever reaches it (reviews then need --token-file).
    #[arg(long, default_value = dpsa_web::DEFAULT_BIND)]
    bind: SocketAddr,
    /// A file whose first line is the token every review must carry (16 to 256 bytes).
    /// Without one, reviews are open on loopback and off on any other address.
    #[arg(long)]
    token_file: Option<std::path::PathBuf>,
    /// The inspection program (program.toml) of the boards, to draw them; may be given once
    /// per program (a board is drawn by the program whose hash it carries).
    #[arg(long = "program", value_name = "PROG")]
    programs: Vec<std::path::PathBuf>,
    /// The directory of the measured maps the line keeps (LINE.toml's `[maps] dir`), for the
    /// board page's zoom and pan. Default: `maps` beside an SQLite store, if there.
    #[arg(long, value_name = "DIR")]
    maps: Option<std::path::PathBuf>,
}

pub fn run(a: Args) -> Result<()> {
    super::log_to_stderr();
    let store = Location::from_arg(&a.store).map_err(|why| anyhow::anyhow!("--store: {why}"))?;
    if let Location::Sqlite(p) = &store {
        if !p.is_file() {
            bail!(
                "--store {}: no store there (give the line's DATA/line.sqlite or a PostgreSQL URL)",
                p.display()
            );
        }
    }
    let maps = match (&a.maps, &store) {
        (Some(d), _) if !d.is_dir() => bail!("--maps {}: no such directory", d.display()),
        (Some(d), _) => Some(d.clone()),
        (None, Location::Sqlite(p)) => p.parent().map(|d| d.join("maps")).filter(|d| d.is_dir()),
        (None, _) => None,
    };
    match &maps {
        Some(d) => tracing::info!(maps = %d.display(), "the boards' measured maps"),
        None => tracing::info!("no maps directory: the board pages show no measured map"),
    }
    let reviews = review_policy(a.token_file.as_deref(), a.bind)?;
    let paths: Vec<&std::path::Path> = a.programs.iter().map(|p| p.as_path()).collect();
    let designs = dpsa_web::board_view::Designs::load(&paths)?;
    dpsa_web::run(
        dpsa_web::Site {
            store,
            line: a.line,
            reviews,
            spc: Default::default(),
            maps,
            map_cache: Default::default(),
            designs: std::sync::Arc::new(designs),
        },
        a.bind,
    )?;
    Ok(())
}

/// Who may review on the pages served on `bind`: the token of `token_file` if given; without
/// one, open on loopback and off beyond it (said in the log either way).
pub fn review_policy(
    token_file: Option<&std::path::Path>,
    bind: SocketAddr,
) -> Result<dpsa_web::review::Policy> {
    let token = token_file
        .map(dpsa_web::review::read_token)
        .transpose()
        .map_err(|why| anyhow::anyhow!("--token-file: {why}"))?;
    let policy = dpsa_web::review::Policy {
        token,
        beyond_loopback: !bind.ip().is_loopback(),
    };
    if policy.beyond_loopback {
        if policy.needs_token() {
            tracing::warn!(address = %bind, "the pages are served beyond loopback: anyone who reaches them reads them; reviews need the token");
        } else {
            tracing::warn!(address = %bind, "the pages are served beyond loopback: anyone who reaches them reads them; reviews are off (no token)");
        }
    }
    Ok(policy)
}
