//! A counting global allocator: live and peak heap bytes, so reconstructions and benchmarks can
//! report the memory they really used (not an estimate). The counters are process-wide: with
//! several jobs running at once a job's peak includes the others' live memory.

use std::alloc::{GlobalAlloc, Layout, System};
use std::sync::atomic::{AtomicUsize, Ordering};

static LIVE: AtomicUsize = AtomicUsize::new(0);
static PEAK: AtomicUsize = AtomicUsize::new(0);

/// Wraps the system allocator; install with `#[global_allocator]` in a binary.
pub struct CountingAlloc;

unsafe impl GlobalAlloc for CountingAlloc {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        let p = unsafe { System.alloc(layout) };
        if !p.is_null() {
            grow(layout.size());
        }
        p
    }
    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        let p = unsafe { System.alloc_zeroed(layout) };
        if !p.is_null() {
            grow(layout.size());
        }
        p
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        unsafe { System.dealloc(ptr, layout) };
        LIVE.fetch_sub(layout.size(), Ordering::Relaxed);
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        let p = unsafe { System.realloc(ptr, layout, new_size) };
        if !p.is_null() {
            if new_size >= layout.size() {
                grow(new_size - layout.size());
            } else {
                LIVE.fetch_sub(layout.size() - new_size, Ordering::Relaxed);
            }
        }
        p
    }
}

#[inline]
fn grow(bytes: usize) {
    let live = LIVE.fetch_add(bytes, Ordering::Relaxed) + bytes;
    PEAK.fetch_max(live, Ordering::Relaxed);
}

/// Heap kept for reuse instead of being returned to the kernel when freed (glibc's
/// `M_TRIM_THRESHOLD`), and the allocation size from which glibc maps pages of their own
/// (`M_MMAP_THRESHOLD`, at glibc's maximum).
const TRIM_THRESHOLD: usize = 256 << 20;
const MMAP_THRESHOLD: usize = 32 << 20;

/// Makes glibc keep freed memory for the next reconstruction (call once, at start-up).
///
/// By default glibc trims the top of the heap once 128 KiB (raised dynamically, up to 64 MiB)
/// of it are free and maps larger blocks on their own, so a process that allocates and frees the
/// same buffers job after job gives the pages back and faults them in again every time, and on
/// a multi-threaded process each trim or unmap also shoots down the other cores' TLBs. Measured
/// with three interleaved rounds of `helmholtz-bench --preset targets --methods gi,dgi --repeat
/// 15` (medians): GI and DGI on 128x128 Bernoulli at 1,638 rows 2.0-3.8 ms against 3.4-5.0 ms
/// without this, and 4.5-6.7 ms against 9.4-13.6 ms on the 256x256 sparse problem (1,000
/// rows); without it a 20-run DGI bench made 1,037 `brk` calls.
/// A no-op on other C libraries. Returns whether both settings were accepted.
pub fn retain_freed_memory() -> bool {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    {
        // SAFETY: mallopt only changes allocator parameters; it is called before any other
        // thread allocates (at start-up), and glibc takes the arena lock for it anyway.
        let trim = unsafe { libc::mallopt(libc::M_TRIM_THRESHOLD, TRIM_THRESHOLD as libc::c_int) };
        let mmap = unsafe { libc::mallopt(libc::M_MMAP_THRESHOLD, MMAP_THRESHOLD as libc::c_int) };
        trim == 1 && mmap == 1
    }
    #[cfg(not(all(target_os = "linux", target_env = "gnu")))]
    {
        false
    }
}

/// Gives freed heap pages back to the system (glibc `malloc_trim(0)`), which
/// [`retain_freed_memory`] otherwise keeps for the next job: called when the last running job of
/// the process has ended or been cancelled, so an idle server does not sit on a finished job's
/// peak. A no-op on other C libraries. Returns whether any memory was given back.
pub fn release_free_memory() -> bool {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    {
        // SAFETY: malloc_trim only returns free pages of glibc's arenas to the system; it takes
        // the arena locks itself.
        unsafe { libc::malloc_trim(0) == 1 }
    }
    #[cfg(not(all(target_os = "linux", target_env = "gnu")))]
    {
        false
    }
}

/// Heap bytes live now (0 when the counting allocator is not installed).
pub fn live_bytes() -> usize {
    LIVE.load(Ordering::Relaxed)
}

/// Highest live heap bytes since the last [`reset_peak`].
pub fn peak_bytes() -> usize {
    PEAK.load(Ordering::Relaxed)
}

/// Starts a new peak measurement from the current live bytes.
pub fn reset_peak() {
    PEAK.store(LIVE.load(Ordering::Relaxed), Ordering::Relaxed);
}

/// Whether the counting allocator is the global allocator of this process: then the live count
/// includes a probe allocation while it lives (it is 0 forever otherwise). Comparing the count
/// before and after the probe instead failed whenever another thread freed memory in between
/// (seen in CI: a server job reported no peak while its HTTP threads were busy).
pub fn installed() -> bool {
    let probe = std::hint::black_box(vec![0u8; 4096]);
    let live = live_bytes();
    drop(probe);
    live >= 4096
}

#[cfg(test)]
mod tests {
    #[test]
    fn the_library_tests_run_on_the_system_allocator() {
        // This test binary installs no counting allocator: no live bytes, so not installed
        // (the server and bench binaries do install it; their tests read the peaks it counts).
        assert!(!super::installed());
        assert_eq!(super::live_bytes(), 0);
    }

    #[test]
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    fn glibc_accepts_the_thresholds() {
        // mallopt refuses an mmap threshold above its maximum (32 MiB on 64-bit) by returning 0.
        assert!(super::retain_freed_memory());
    }
}
