//! Reusable scratch buffers for operators whose `apply` takes `&self` (the trait is `Sync`, and
//! solvers may call one operator from several threads at once).
//!
//! [`Pool::take`] hands out a zeroed `Vec<f64>` of the requested length, reusing a returned one
//! when its capacity suffices; the [`Scratch`] guard gives it back on drop. After the first few
//! calls no operator allocates in its hot loop.

use std::ops::{Deref, DerefMut};
use std::sync::Mutex;

/// A free list of `f64` buffers.
#[derive(Default)]
pub struct Pool {
    free: Mutex<Vec<Vec<f64>>>,
}

impl std::fmt::Debug for Pool {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("Pool")
    }
}

impl Pool {
    pub fn new() -> Self {
        Self::default()
    }

    /// A buffer of `len` zeros (reused storage when available).
    pub fn take(&self, len: usize) -> Scratch<'_> {
        let mut buf = {
            let mut free = self.free.lock().unwrap_or_else(|e| e.into_inner());
            // Prefer a buffer that is already large enough.
            match free.iter().position(|b| b.capacity() >= len) {
                Some(i) => free.swap_remove(i),
                None => free.pop().unwrap_or_default(),
            }
        };
        buf.clear();
        buf.resize(len, 0.0);
        Scratch { pool: self, buf }
    }
}

/// A pooled buffer; returns to its pool when dropped.
pub struct Scratch<'a> {
    pool: &'a Pool,
    buf: Vec<f64>,
}

impl Deref for Scratch<'_> {
    type Target = [f64];
    fn deref(&self) -> &[f64] {
        &self.buf
    }
}

impl DerefMut for Scratch<'_> {
    fn deref_mut(&mut self) -> &mut [f64] {
        &mut self.buf
    }
}

impl Drop for Scratch<'_> {
    fn drop(&mut self) {
        let buf = std::mem::take(&mut self.buf);
        let mut free = self.pool.free.lock().unwrap_or_else(|e| e.into_inner());
        // Bounded: at most a few buffers per thread are ever live at once.
        if free.len() < 64 {
            free.push(buf);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reuses_and_zeroes() {
        let pool = Pool::new();
        let ptr = {
            let mut a = pool.take(100);
            a[3] = 7.0;
            a.as_ptr()
        };
        let b = pool.take(50);
        assert_eq!(b.as_ptr(), ptr, "storage reused");
        assert!(b.iter().all(|&v| v == 0.0));
        assert_eq!(b.len(), 50);
    }
}
