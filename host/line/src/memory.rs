//! The service's memory and processor time: what it reads of its own, and glibc's malloc
//! told to keep the memory flat.
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

/// Field `n` of a `/proc/PID/stat` (or `/proc/thread-self/stat`) line, numbered from 1 as
/// `man 5 proc` numbers them (`n >= 3`; the command name, field 2, is in parentheses and may
/// hold spaces and parentheses, so the fields are counted from the last `)`).
pub fn stat_field(stat: &str, n: usize) -> Option<&str> {
    let after = stat.rsplit_once(')')?.1;
    after.split_whitespace().nth(n.checked_sub(3)?)
}

/// This process's processor time so far, user and system, all threads (those ended too), s:
/// `/proc/self/stat`'s `utime` and `stime`, in the kernel's clock ticks (100 per second on
/// Linux); `None` elsewhere or unreadable. A tick is 10 ms.
pub fn process_cpu_s() -> Option<f64> {
    cpu_of_stat(&std::fs::read_to_string("/proc/self/stat").ok()?)
}

/// `utime + stime` (fields 14 and 15) of a `/proc/PID/stat` line, s (at 100 ticks per
/// second).
fn cpu_of_stat(stat: &str) -> Option<f64> {
    let ticks = |n: usize| stat_field(stat, n)?.parse::<u64>().ok();
    Some((ticks(14)? + ticks(15)?) as f64 / 100.0)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The processor time is read from the right fields, whatever the command's name holds;
    /// a line cut short or not numbers gives none.
    #[test]
    fn processor_time_from_a_stat_line() {
        let line = "4242 (dpsa (x) y) R 1 4242 4242 0 -1 4194304 900 0 0 0 731 269 0 0 20 0 3 0 \
                    123 456 789";
        assert_eq!(cpu_of_stat(line), Some(10.0));
        assert_eq!(stat_field(line, 3), Some("R"));
        // The priority (18) and the nice value (19).
        assert_eq!(stat_field(line, 18), Some("20"));
        assert_eq!(stat_field(line, 19), Some("0"));
        assert_eq!(stat_field(line, 2), None);
        assert_eq!(cpu_of_stat("4242 (dpsa) R 1 2 3"), None);
        assert_eq!(cpu_of_stat("4242 dpsa R"), None);
        assert_eq!(cpu_of_stat("1 (a) R 1 1 1 0 -1 0 0 0 0 0 x 5 0 0"), None);
        // This process: a reading, and it does not go back.
        let a = process_cpu_s().expect("/proc/self/stat on Linux");
        let b = process_cpu_s().expect("/proc/self/stat on Linux");
        assert!(a >= 0.0 && b >= a, "{a} {b}");
    }

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
