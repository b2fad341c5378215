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
}
