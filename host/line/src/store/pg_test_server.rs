//! A throwaway PostgreSQL server for the tests: Debian's server programs
//! (`/usr/lib/postgresql/VERSION/bin`), a cluster made by `initdb` in a fresh directory under
//! `/tmp`, listening on a free port of 127.0.0.1 only (its Unix socket in that directory),
//! trust authentication (nobody else can reach it). One server per test process, started by
//! the first test that asks ([`database`]); each test gets a database of its own.
//!
//! Stopping: a server of a `static` is never dropped, so a guardian process is started with
//! it: a shell that waits for the end of a pipe this process holds (closed by the kernel when
//! the test process ends, however it ends: passed, panicked, killed) and then stops the
//! server (`pg_ctl stop -m immediate`) and removes the directory. It runs in its own process
//! group, so a Ctrl-C of the tests does not stop it before it has cleaned up. A
//! [`PgServer`] dropped (not the shared one) stops its server and removes its directory at
//! once.
//!
//! `initdb` refuses to run as root, and CI runs as root: then every server program runs as
//! the `postgres` user (`runuser -u postgres --`), in a directory under `/tmp` given to that
//! user. Without the programs the tests fail, saying what to install: never skipped.

use super::Location;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::OnceLock;
use std::time::Duration;

/// Where Debian installs the server programs, one directory per major version.
const DEBIAN_PG: &str = "/usr/lib/postgresql";

/// What to say when the programs are missing.
const INSTALL: &str = "install Debian's PostgreSQL server (apt-get install postgresql; \
     tests/run.sh installs it when /usr/lib/postgresql/*/bin/initdb is missing)";

/// A running server.
pub(crate) struct PgServer {
    /// Its directory: `data/` (the cluster), `server.log`, the Unix socket.
    dir: PathBuf,
    /// `/usr/lib/postgresql/VERSION/bin`.
    bin: PathBuf,
    /// Its port on 127.0.0.1.
    port: u16,
    /// Whether the programs run as the `postgres` user (this process is root).
    as_postgres: bool,
    /// The guardian (see the module documentation); its stdin is the pipe it waits on.
    guardian: Option<Child>,
}

/// The newest `/usr/lib/postgresql/*/bin` that has `initdb` and `pg_ctl`.
fn server_bin() -> Result<PathBuf, String> {
    let mut found: Vec<(u32, PathBuf)> = std::fs::read_dir(DEBIAN_PG)
        .map_err(|e| format!("no {DEBIAN_PG} ({e}): {INSTALL}"))?
        .flatten()
        .filter_map(|e| {
            let version: u32 = e.file_name().to_str()?.parse().ok()?;
            let bin = e.path().join("bin");
            (bin.join("initdb").is_file() && bin.join("pg_ctl").is_file()).then_some((version, bin))
        })
        .collect();
    found.sort();
    found
        .pop()
        .map(|(_, bin)| bin)
        .ok_or_else(|| format!("no {DEBIAN_PG}/*/bin/initdb and pg_ctl: {INSTALL}"))
}

/// Whether this process runs as root (effective user 0), from `/proc/self/status`.
fn is_root() -> bool {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("Uid:"))
                .and_then(|l| l.split_whitespace().nth(2).map(|euid| euid == "0"))
        })
        .unwrap_or(false)
}

/// Runs a command to its end; `Err` with its output if it fails.
fn run(mut c: Command, what: &str) -> Result<(), String> {
    let out = c
        .stdin(Stdio::null())
        .output()
        .map_err(|e| format!("{what}: cannot run it: {e}"))?;
    if out.status.success() {
        Ok(())
    } else {
        Err(format!(
            "{what} failed ({}): {}{}",
            out.status,
            String::from_utf8_lossy(&out.stdout),
            String::from_utf8_lossy(&out.stderr)
        ))
    }
}

impl PgServer {
    /// A server program (`initdb`, `pg_ctl`), as the `postgres` user when this is root.
    fn program(&self, name: &str) -> Command {
        program(&self.bin, name, self.as_postgres)
    }

    /// Makes a cluster and starts it; see the module documentation.
    pub(crate) fn start() -> Result<PgServer, String> {
        let bin = server_bin()?;
        let as_postgres = is_root();
        // Under /tmp, not $TMPDIR: the postgres user must be able to reach it.
        let dir = tempfile::Builder::new()
            .prefix("dpsa-pg-")
            .tempdir_in("/tmp")
            .map_err(|e| format!("cannot make a directory under /tmp: {e}"))?
            .keep();
        let mut server = PgServer {
            dir,
            bin,
            port: 0,
            as_postgres,
            guardian: None,
        };
        server.guardian = Some(server.guardian()?);
        if as_postgres {
            let mut c = Command::new("chown");
            c.arg("postgres:").arg(&server.dir);
            run(c, "chown postgres: (the server runs as postgres)")?;
        }
        let data = server.dir.join("data");
        let mut c = server.program("initdb");
        c.arg("-D").arg(&data).args([
            "--auth=trust",
            "--username=postgres",
            "--encoding=UTF8",
            "--locale=C",
            "--no-sync",
            "--no-instructions",
        ]);
        run(c, "initdb")?;
        // A free port: taken and released; another program may take it first, so a failed
        // start is tried again on another.
        let mut last = String::new();
        for _ in 0..5 {
            let port = std::net::TcpListener::bind(("127.0.0.1", 0))
                .and_then(|l| l.local_addr())
                .map_err(|e| format!("no free port on 127.0.0.1: {e}"))?
                .port();
            let mut c = server.program("pg_ctl");
            c.arg("-D")
                .arg(&data)
                .arg("-l")
                .arg(server.dir.join("server.log"))
                .args(["-w", "-t", "60", "-o"])
                // Durability is of no use to a throwaway cluster, and costs time.
                .arg(format!(
                    "-c listen_addresses=127.0.0.1 -p {port} -k {} -c fsync=off \
                     -c synchronous_commit=off -c full_page_writes=off",
                    server.dir.display()
                ))
                .arg("start")
                .stdout(Stdio::null())
                .stderr(Stdio::piped());
            // Its own process group: a Ctrl-C of the tests is the guardian's to handle.
            std::os::unix::process::CommandExt::process_group(&mut c, 0);
            match run(c, "pg_ctl start") {
                Ok(()) => {
                    server.port = port;
                    return Ok(server);
                }
                Err(e) => {
                    let log =
                        std::fs::read_to_string(server.dir.join("server.log")).unwrap_or_default();
                    last = format!("{e}\n{log}");
                }
            }
        }
        Err(last)
    }

    /// Starts the guardian: it waits for EOF on its stdin, then stops the server and removes
    /// the directory.
    fn guardian(&self) -> Result<Child, String> {
        let stop = program(&self.bin, "pg_ctl", self.as_postgres);
        let mut c = Command::new("sh");
        c.arg("-c")
            .arg("cat >/dev/null; \"$@\" >/dev/null 2>&1; rm -rf -- \"$DPSA_PG_DIR\"")
            .arg("sh")
            .arg(stop.get_program())
            .args(stop.get_args())
            .arg("-D")
            .arg(self.dir.join("data"))
            .args(["-m", "immediate", "stop"])
            .env("DPSA_PG_DIR", &self.dir)
            .stdin(Stdio::piped())
            .stdout(Stdio::null())
            .stderr(Stdio::null());
        std::os::unix::process::CommandExt::process_group(&mut c, 0);
        c.spawn()
            .map_err(|e| format!("cannot start the server's guardian (sh): {e}"))
    }

    /// The URL of database `db` as the superuser.
    pub(crate) fn url(&self, db: &str) -> String {
        format!("postgres://postgres@127.0.0.1:{}/{db}", self.port)
    }

    /// A new empty database of this server; returns its name.
    pub(crate) fn create_database(&self) -> String {
        static N: AtomicUsize = AtomicUsize::new(0);
        let name = format!(
            "t{}_{}",
            std::process::id(),
            N.fetch_add(1, Ordering::Relaxed)
        );
        let mut c = postgres::Client::connect(&self.url("postgres"), postgres::NoTls)
            .unwrap_or_else(|e| panic!("the test server on port {}: {e}", self.port));
        c.batch_execute(&format!("CREATE DATABASE {name}"))
            .unwrap_or_else(|e| panic!("CREATE DATABASE {name}: {e}"));
        name
    }
}

/// `bin/name`, run as `postgres` when `as_postgres`.
fn program(bin: &Path, name: &str, as_postgres: bool) -> Command {
    if as_postgres {
        let mut c = Command::new("runuser");
        c.args(["-u", "postgres", "--"]).arg(bin.join(name));
        c
    } else {
        Command::new(bin.join(name))
    }
}

impl Drop for PgServer {
    fn drop(&mut self) {
        let mut c = self.program("pg_ctl");
        c.arg("-D")
            .arg(self.dir.join("data"))
            .args(["-m", "fast", "stop"])
            .stdout(Stdio::null())
            .stderr(Stdio::null());
        let _ = run(c, "pg_ctl stop");
        let _ = std::fs::remove_dir_all(&self.dir);
        if let Some(mut g) = self.guardian.take() {
            // Its stdin closed: it finds nothing left to stop or remove, and ends.
            drop(g.stdin.take());
            let _ = g.wait();
        }
    }
}

/// The test process's server, started by the first caller.
pub(crate) fn server() -> &'static PgServer {
    static SERVER: OnceLock<Result<PgServer, String>> = OnceLock::new();
    match SERVER.get_or_init(PgServer::start) {
        Ok(s) => s,
        Err(e) => panic!("the PostgreSQL test server did not start: {e}"),
    }
}

/// A new empty database on the test process's server.
pub(crate) fn database() -> Location {
    let s = server();
    let db = s.create_database();
    match Location::postgres(&s.url(&db)) {
        Ok(l) => l,
        Err(e) => panic!("{e}"),
    }
}

#[test]
fn the_server_starts_and_a_dropped_one_stops_and_leaves_nothing() {
    let s = PgServer::start().unwrap_or_else(|e| panic!("{e}"));
    let dir = s.dir.clone();
    let db = s.create_database();
    let mut c = postgres::Client::connect(&s.url(&db), postgres::NoTls).unwrap();
    let one: i32 = c.query_one("SELECT 1", &[]).unwrap().get(0);
    assert_eq!(one, 1);
    drop(c);
    let port = s.port;
    drop(s);
    assert!(!dir.exists(), "{} left", dir.display());
    let refused = std::net::TcpStream::connect_timeout(
        &std::net::SocketAddr::from(([127, 0, 0, 1], port)),
        Duration::from_secs(1),
    );
    assert!(refused.is_err(), "port {port} still answers");
}
