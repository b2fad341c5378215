//! The basis functions of the adaptive families (`proto/PATTERNS.md`, adaptive_haar and
//! adaptive_hadamard): which function an index names, and its sign on each pixel.
//!
//! Both families live on a square `W x W` grid, `W = 2^m`. Index `n` is in `0..W^2`.
//!
//! - adaptive_hadamard: `n = u W + v` is the natural Walsh-Hadamard index of the hadamard family,
//!   `w_n(x, y) = (-1)^(popcount(u & y) + popcount(v & x))`.
//! - adaptive_haar: `n = r W + c` is the position of the coefficient in the Mallat layout of the
//!   `W x W` orthonormal 2D Haar transform (`m` levels, rows first, approximation first, detail =
//!   left/top half minus right/bottom half). `n = 0` is the scaling function (all +1). Otherwise
//!   the ring `max(r, c) in [2^(m-s), 2^(m-s+1))` holds the details of support side `2^s`, with
//!   `h = W >> s`, band offsets `pr = r mod h`, `pc = c mod h`: the function is `+-1` on the
//!   `2^s x 2^s` block at `(pc 2^s, pr 2^s)` and 0 elsewhere; its sign is `-1` on the right half
//!   of the block if `c >= h`, times `-1` on the bottom half if `r >= h`. The orthonormal
//!   function is this sign pattern over `2^s` (the scaling function's over `W`).

/// One 2D Haar function on a `W x W` grid (see the module docs), as a sign pattern.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct HaarFunction {
    /// log2 of the support side: `m` for the scaling function, `s` in `1..=m` for a detail.
    pub scale: u32,
    /// Top-left pixel of the support.
    pub x0: u32,
    pub y0: u32,
    /// Sign flips between the left and right halves of the support (a detail along x).
    pub split_x: bool,
    /// Sign flips between the top and bottom halves (a detail along y).
    pub split_y: bool,
}

impl HaarFunction {
    /// The function with Mallat index `n` on a `width x width` grid (`width` a power of two,
    /// `n < width^2`).
    pub fn new(width: u32, n: u32) -> HaarFunction {
        debug_assert!(width.is_power_of_two());
        let m = width.trailing_zeros();
        let (r, c) = (n / width, n % width);
        assert!(r < width, "haar index {n} out of range for width {width}");
        if n == 0 {
            return HaarFunction {
                scale: m,
                x0: 0,
                y0: 0,
                split_x: false,
                split_y: false,
            };
        }
        // max(r, c) in [2^(m-s), 2^(m-s+1)).
        let s = m - (31 - r.max(c).leading_zeros());
        let h = width >> s;
        HaarFunction {
            scale: s,
            x0: (c % h) << s,
            y0: (r % h) << s,
            split_x: c >= h,
            split_y: r >= h,
        }
    }

    /// Side of the square support, `2^scale`.
    pub fn side(&self) -> u32 {
        1 << self.scale
    }

    /// `+1`, `-1` or `0` at pixel `(x, y)`.
    pub fn sign(&self, x: u32, y: u32) -> i8 {
        let side = self.side();
        let (dx, dy) = (x.wrapping_sub(self.x0), y.wrapping_sub(self.y0));
        if dx >= side || dy >= side {
            return 0;
        }
        let half = side / 2;
        let negative = (self.split_x && dx >= half) != (self.split_y && dy >= half);
        if negative { -1 } else { 1 }
    }
}

/// `+1` or `-1`: the Walsh-Hadamard function with natural index `n = u W + v` at `(x, y)`.
pub fn walsh_sign(width: u32, n: u32, x: u32, y: u32) -> i8 {
    let (u, v) = (n / width, n % width);
    if ((u & y).count_ones() + (v & x).count_ones()) & 1 == 0 {
        1
    } else {
        -1
    }
}
