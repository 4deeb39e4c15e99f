//! The boards' thread runs below the keeper: the older board first.
//!
//! At the conveyor's rate the next board's rows come while this board is judged. The next
//! board's stitching (the boards' thread and the threads it starts: the cameras' unwrapping,
//! the resampling, the blend) and this board's inspection (the keeper's threads) then share
//! the two cores, each by its number of runnable threads, and the stitching has more. This
//! board's verdict waits for its inspection alone, the next board's for both: so the keeper
//! goes first. The boards' thread lowers its own priority (raises its nice value by
//! [`STITCH_NICE`]) once the keeper and the links' threads are started, and the threads it
//! starts afterwards inherit it. A core the keeper leaves is the stitching's, as before; the
//! links' threads, which read the frame grabbers' packets, keep the normal priority.

/// How far the boards' thread lowers its priority (its nice value's rise: at 10 a runnable
/// thread of the keeper weighs about nine times one of the stitching's in Linux's scheduler).
pub const STITCH_NICE: i32 = 10;

/// Raises the calling thread's nice value by `by` (at most to 19; the threads it starts
/// afterwards inherit it) and returns its nice value now; None where that is not supported or
/// was refused (off Linux, nothing is done).
pub fn lower_this_thread(by: i32) -> Option<i32> {
    let now = this_thread_nice()?;
    let want = (now + by.max(0)).min(19);
    #[cfg(target_os = "linux")]
    {
        // SAFETY: `gettid` and `setpriority` take and return plain integers and touch no
        // memory of ours; a thread may always raise its own nice value.
        #[allow(unsafe_code)]
        let set =
            unsafe { libc::setpriority(libc::PRIO_PROCESS, libc::gettid() as libc::id_t, want) };
        if set != 0 {
            return None;
        }
        this_thread_nice()
    }
    #[cfg(not(target_os = "linux"))]
    {
        let _ = want;
        None
    }
}

/// The calling thread's nice value: field 19 of `/proc/thread-self/stat` (None where there is
/// no such file).
pub fn this_thread_nice() -> Option<i32> {
    let stat = std::fs::read_to_string("/proc/thread-self/stat").ok()?;
    crate::memory::stat_field(&stat, 19)?.parse().ok()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// In a thread of its own (the test's thread keeps its priority): the nice value rises by
    /// the amount asked, as the kernel reports it, and a thread started afterwards has it too.
    #[test]
    fn a_lowered_thread_and_the_threads_it_starts_run_at_the_new_nice_value() {
        let own = this_thread_nice();
        std::thread::spawn(|| {
            let before = this_thread_nice().expect("/proc/thread-self/stat");
            let want = (before + 3).min(19);
            assert_eq!(lower_this_thread(3), Some(want));
            assert_eq!(this_thread_nice(), Some(want));
            let child = std::thread::spawn(this_thread_nice).join().unwrap();
            assert_eq!(child, Some(want));
            // Never above 19.
            assert_eq!(lower_this_thread(40), Some(19));
        })
        .join()
        .unwrap();
        // The test's own thread is as it was.
        assert_eq!(this_thread_nice(), own);
    }
}
