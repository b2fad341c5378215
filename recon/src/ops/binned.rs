//! A coarser image grid seen through a measurement operator: `A U_f`, where `U_f` replicates
//! each pixel of a `ceil(W/f) x ceil(H/f)` image over an `f x f` block of the `W x H` grid
//! (edge blocks clipped). Fitting on it asks whether the rows support the full resolution or
//! only a coarser one (`auto` compares the two by held-out error).

use crate::linop::LinearOperator;

pub struct Binned<'a> {
    inner: &'a dyn LinearOperator,
    width: usize,
    height: usize,
    factor: usize,
}

impl<'a> Binned<'a> {
    /// `inner` acts on `width x height` images (row-major); `factor >= 1`.
    pub fn new(inner: &'a dyn LinearOperator, width: usize, height: usize, factor: usize) -> Self {
        assert!(factor >= 1, "binning factor must be >= 1");
        assert_eq!(
            inner.cols(),
            width * height,
            "operator columns vs image size"
        );
        Binned {
            inner,
            width,
            height,
            factor,
        }
    }

    /// The coarse grid's size.
    pub fn coarse_size(&self) -> (usize, usize) {
        (
            self.width.div_ceil(self.factor),
            self.height.div_ceil(self.factor),
        )
    }

    /// `U x`: the coarse image replicated onto the full grid.
    pub fn upsample(&self, coarse: &[f64], full: &mut [f64]) {
        let (cw, _) = self.coarse_size();
        for y in 0..self.height {
            let row = &coarse[(y / self.factor) * cw..];
            for x in 0..self.width {
                full[y * self.width + x] = row[x / self.factor];
            }
        }
    }

    /// `U^T v`: block sums.
    pub fn block_sums(&self, full: &[f64], coarse: &mut [f64]) {
        let (cw, _) = self.coarse_size();
        coarse.fill(0.0);
        for y in 0..self.height {
            let row = &mut coarse[(y / self.factor) * cw..];
            for x in 0..self.width {
                row[x / self.factor] += full[y * self.width + x];
            }
        }
    }

    /// Block means: the coarse image closest (least squares) to `full`, the adjoint of
    /// [`Self::upsample`] divided by each block's pixel count (edge blocks are smaller).
    pub fn block_means(&self, full: &[f64], coarse: &mut [f64]) {
        self.block_sums(full, coarse);
        let mut counts = vec![0.0; coarse.len()];
        self.block_sums(&vec![1.0; full.len()], &mut counts);
        for (c, n) in coarse.iter_mut().zip(&counts) {
            *c /= n;
        }
    }
}

impl LinearOperator for Binned<'_> {
    fn rows(&self) -> usize {
        self.inner.rows()
    }
    fn cols(&self) -> usize {
        let (cw, ch) = self.coarse_size();
        cw * ch
    }
    fn apply(&self, x: &[f64], y: &mut [f64]) {
        let mut full = vec![0.0; self.width * self.height];
        self.upsample(x, &mut full);
        self.inner.apply(&full, y);
    }
    fn adjoint(&self, y: &[f64], x: &mut [f64]) {
        let mut full = vec![0.0; self.width * self.height];
        self.inner.adjoint(y, &mut full);
        self.block_sums(&full, x);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::linop::{DenseOperator, adjoint_mismatch, test_vector};

    #[test]
    fn passes_the_adjoint_test_and_replicates_blocks() {
        // 7 x 5 grid, factor 2 and 3: clipped edge blocks.
        let (w, h) = (7, 5);
        let a = DenseOperator::new(11, w * h, test_vector(11 * w * h, 3));
        for f in [1, 2, 3, 8] {
            let b = Binned::new(&a, w, h, f);
            assert!(adjoint_mismatch(&b, 9) < 1e-12, "factor {f}");
        }
        let b = Binned::new(&a, w, h, 3);
        assert_eq!(b.coarse_size(), (3, 2));
        let mut full = vec![0.0; w * h];
        b.upsample(&[1.0, 2.0, 3.0, 4.0, 5.0, 6.0], &mut full);
        assert_eq!(&full[..7], &[1.0, 1.0, 1.0, 2.0, 2.0, 2.0, 3.0]);
        assert_eq!(&full[28..], &[4.0, 4.0, 4.0, 5.0, 5.0, 5.0, 6.0]);
        // Block means undo the replication, clipped edge blocks included.
        let mut back = vec![0.0; 6];
        b.block_means(&full, &mut back);
        assert_eq!(back, [1.0, 2.0, 3.0, 4.0, 5.0, 6.0]);
        // The edge block (2, 0) holds 1 x 3 pixels: x = 6, y = 0..3.
        full[6] = 7.0;
        b.block_means(&full, &mut back);
        assert!(
            (back[2] - (3.0 + 3.0 + 7.0) / 3.0).abs() < 1e-12,
            "{back:?}"
        );
    }
}
