//! Raster / block scan: pattern i lights block `i % blocks` (PATTERNS.md "raster"), so
//! `y_i = sum of x over that block` and the adjoint spreads each row's value over its block
//! (repeated scans add up). With block 1 and one full scan this is the identity; with fewer rows a
//! subsampled identity. O(k + n) per product.

use helmholtz_proto::{Family, PatternSpec};

use super::OpError;
use super::scratch::Pool;
use crate::linop::LinearOperator;

#[derive(Debug)]
pub struct RasterOperator {
    width: u32,
    height: u32,
    block: u32,
    rows: usize,
    blocks: usize,
    /// Block index of every pixel.
    pixel_block: Vec<u32>,
    pool: Pool,
}

impl RasterOperator {
    /// `rows` patterns of a `width x height` raster scan with `block x block` blocks.
    pub fn new(width: u32, height: u32, block: u32, rows: usize) -> Self {
        assert!(
            width > 0 && height > 0 && block > 0,
            "raster needs positive sizes"
        );
        let bx = width.div_ceil(block) as usize;
        let by = height.div_ceil(block) as usize;
        let b = block as usize;
        let mut pixel_block = Vec::with_capacity(width as usize * height as usize);
        for y in 0..height as usize {
            for x in 0..width as usize {
                pixel_block.push(((y / b) * bx + x / b) as u32);
            }
        }
        RasterOperator {
            width,
            height,
            block,
            rows,
            blocks: bx * by,
            pixel_block,
            pool: Pool::new(),
        }
    }

    pub fn from_spec(spec: &PatternSpec, rows: u64) -> Result<Self, OpError> {
        let Family::Raster { block, .. } = *spec.family() else {
            return Err(OpError::WrongFamily {
                want: "raster",
                got: spec.family().name(),
            });
        };
        super::check_rows(spec, rows)?;
        Ok(Self::new(spec.width(), spec.height(), block, rows as usize))
    }

    pub fn width(&self) -> u32 {
        self.width
    }
    pub fn height(&self) -> u32 {
        self.height
    }
    pub fn block(&self) -> u32 {
        self.block
    }
    /// Number of distinct blocks (the scan period).
    pub fn blocks(&self) -> usize {
        self.blocks
    }
    /// Block lit by row i.
    pub fn row_block(&self, i: usize) -> usize {
        i % self.blocks
    }
}

impl LinearOperator for RasterOperator {
    fn rows(&self) -> usize {
        self.rows
    }
    fn cols(&self) -> usize {
        self.pixel_block.len()
    }
    fn apply(&self, x: &[f64], y: &mut [f64]) {
        assert_eq!(x.len(), self.pixel_block.len());
        assert_eq!(y.len(), self.rows);
        if self.block == 1 {
            for (i, yi) in y.iter_mut().enumerate() {
                *yi = x[i % self.blocks];
            }
            return;
        }
        let mut sums = self.pool.take(self.blocks);
        for (&b, &v) in self.pixel_block.iter().zip(x) {
            sums[b as usize] += v;
        }
        for (i, yi) in y.iter_mut().enumerate() {
            *yi = sums[i % self.blocks];
        }
    }
    fn adjoint(&self, y: &[f64], x: &mut [f64]) {
        assert_eq!(y.len(), self.rows);
        assert_eq!(x.len(), self.pixel_block.len());
        if self.block == 1 && self.rows <= self.blocks {
            x[..self.rows].copy_from_slice(y);
            x[self.rows..].fill(0.0);
            return;
        }
        let mut sums = self.pool.take(self.blocks);
        for (i, &v) in y.iter().enumerate() {
            sums[i % self.blocks] += v;
        }
        for (xj, &b) in x.iter_mut().zip(&self.pixel_block) {
            *xj = sums[b as usize];
        }
    }
}
