//! Run-time choice of instruction set for the hot loops.
//!
//! The crate is built for baseline x86-64 (SSE2), so one binary runs on any x86-64 machine. The
//! few loops that carry the solvers (the TV prox, the Walsh-Hadamard butterflies, the packed-bit
//! products) are written once as plain Rust and compiled twice by [`avx2_dispatch!`]: as is, and
//! inside a `#[target_feature(enable = "avx2,fma")]` function that LLVM vectorises 4 doubles
//! wide. The AVX2 copy runs when the CPU has the features (checked once at run time;
//! `HELMHOLTZ_SIMD=baseline` forces the baseline copies, to measure one against the other).
//! Results are bit-for-bit those of the baseline copy: without fast-math LLVM neither fuses
//! multiply-adds nor reorders sums, so only the vector width changes.
//!
//! The packed-bit product has a kernel of its own for AVX-512F ([`avx512`]; written with
//! intrinsics, it adds in another order than the portable kernel, so its results differ by
//! rounding); `HELMHOLTZ_SIMD=avx2` or `baseline` turns it off.

use std::sync::atomic::{AtomicU8, Ordering};

/// 0: not decided yet; 1: AVX2 copies; 2: baseline copies.
static CHOICE: AtomicU8 = AtomicU8::new(0);

/// Whether the AVX2 + FMA copies run: the CPU has the features and `HELMHOLTZ_SIMD` is not
/// `baseline` (read once; for measuring one build against the other).
#[inline]
pub fn avx2() -> bool {
    cached(&CHOICE, || {
        cpu_has_avx2() && std::env::var("HELMHOLTZ_SIMD").map_or(true, |v| v != "baseline")
    })
}

/// A run-time choice decided once: `decide` on the first call, the stored answer after.
#[inline]
fn cached(choice: &AtomicU8, decide: impl FnOnce() -> bool) -> bool {
    match choice.load(Ordering::Relaxed) {
        1 => true,
        2 => false,
        _ => {
            let yes = decide();
            choice.store(if yes { 1 } else { 2 }, Ordering::Relaxed);
            yes
        }
    }
}

/// Makes every dispatched loop run its baseline copy (`true`) or, CPU permitting, its AVX2
/// copy (`false`). Both give the same bits, so flipping this under running work is harmless;
/// tests use it to check exactly that.
#[cfg(test)]
pub(crate) fn force_baseline(baseline: bool) {
    let wide = !baseline && cpu_has_avx2();
    CHOICE.store(if wide { 1 } else { 2 }, Ordering::Relaxed);
}

/// 0: not decided yet; 1: AVX-512 kernels; 2: not.
static CHOICE512: AtomicU8 = AtomicU8::new(0);

/// Whether the AVX-512 kernels run (the packed-bit products, [`crate::ops::BitMatrix`]):
/// the CPU has AVX-512F and `HELMHOLTZ_SIMD` is neither `baseline` nor `avx2` (read once).
/// Unlike the AVX2 copies, these kernels add in another order than the portable ones: their
/// results differ by rounding.
#[inline]
pub fn avx512() -> bool {
    cached(&CHOICE512, || {
        cpu_has_avx512()
            && std::env::var("HELMHOLTZ_SIMD").map_or(true, |v| v != "baseline" && v != "avx2")
    })
}

fn cpu_has_avx512() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::arch::is_x86_feature_detected!("avx512f")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

fn cpu_has_avx2() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

/// `avx2_dispatch!(fn name(args) -> Ret { body })` defines `name`, which runs `body` compiled
/// for AVX2 + FMA when [`avx2`] says the CPU has them, and the baseline build otherwise.
macro_rules! avx2_dispatch {
    ($(#[$m:meta])* $vis:vis fn $name:ident($($arg:ident: $ty:ty),* $(,)?) $(-> $ret:ty)? $body:block) => {
        $(#[$m])*
        $vis fn $name($($arg: $ty),*) $(-> $ret)? {
            #[inline(always)]
            fn body($($arg: $ty),*) $(-> $ret)? $body
            #[cfg(target_arch = "x86_64")]
            {
                #[target_feature(enable = "avx2,fma")]
                unsafe fn wide($($arg: $ty),*) $(-> $ret)? {
                    body($($arg),*)
                }
                if $crate::simd::avx2() {
                    // SAFETY: the CPU has AVX2 and FMA (checked just above); `wide` is `body`.
                    return unsafe { wide($($arg),*) };
                }
            }
            body($($arg),*)
        }
    };
}
pub(crate) use avx2_dispatch;
