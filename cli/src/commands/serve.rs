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
    /// whoever reaches it (the pages only read).
    #[arg(long, default_value = dpsa_web::DEFAULT_BIND)]
    bind: SocketAddr,
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
    if !a.bind.ip().is_loopback() {
        eprintln!(
            "warning: serving on {} (not loopback): anyone who reaches it reads the line's pages",
            a.bind
        );
    }
    dpsa_web::run(
        dpsa_web::Site {
            store,
            line: a.line,
        },
        a.bind,
    )?;
    Ok(())
}
