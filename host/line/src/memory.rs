//! The service's memory: what it reads of its own, and glibc's malloc told to keep it flat.
//!
//! The line runs all shift with a thread per frame-grabber connection, three new ones per
//! board. glibc's malloc hands threads arenas of their own (up to eight per core) and keeps
//! what was freed in each arena for that arena, so the rows a link thread allocated and the
//! board thread freed pile up across arenas: the service's RSS climbed from 45 to 78 MB over
//! 3,000 boards of the small array scene and was still climbing. With the arenas capped at
//! [`ARENAS`] it stays flat (docs/line.md, "Soak"). mimalloc as the global allocator was
//! measured too and held 140 to 180 MB on the same soak: it keeps each thread's pages.

/// The malloc arenas the service allows: one per core of the machine it was sized for, so
/// the link threads and the board thread rarely wait for each other's arena lock.
pub const ARENAS: i32 = 2;

/// Caps glibc's malloc arenas at [`ARENAS`] for the rest of the process (arenas already made
/// stay). True when the allocator took it; false off glibc, where nothing is done.
pub fn cap_arenas() -> bool {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    {
        // SAFETY: `mallopt` sets one of malloc's parameters and touches no memory of ours;
        // M_ARENA_MAX is a parameter glibc knows, and any positive value is valid for it.
        #[allow(unsafe_code)]
        let taken = unsafe { libc::mallopt(libc::M_ARENA_MAX, ARENAS) };
        taken == 1
    }
    #[cfg(not(all(target_os = "linux", target_env = "gnu")))]
    {
        false
    }
}

/// This process's `key` line of `/proc/self/status` (`VmRSS`, `VmHWM`), MB (10^6 bytes);
/// `None` off Linux.
pub fn status_mb(key: &str) -> Option<f64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status
        .lines()
        .find(|l| l.starts_with(key) && l[key.len()..].starts_with(':'))?;
    let kb: f64 = line[key.len() + 1..]
        .trim()
        .trim_end_matches("kB")
        .trim()
        .parse()
        .ok()?;
    Some(kb * 1024.0 / 1e6)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The peak is never below the current resident memory, and both are read (Linux).
    #[test]
    fn peak_memory_is_at_least_the_resident_memory() {
        let rss = status_mb("VmRSS").expect("VmRSS on Linux");
        let peak = status_mb("VmHWM").expect("VmHWM on Linux");
        assert!(rss > 0.1 && peak >= rss, "{rss} {peak}");
        assert_eq!(status_mb("NoSuchKey"), None);
    }

    /// The cap is taken where the allocator is glibc's (this crate's tests run on it).
    #[test]
    fn glibc_takes_the_arena_cap() {
        assert_eq!(
            cap_arenas(),
            cfg!(all(target_os = "linux", target_env = "gnu"))
        );
    }
}
