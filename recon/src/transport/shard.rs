//! A reconstruction of `T` in shards: the model chosen once ([`super::plan_transport`]), the
//! blocks of camera pixels solved in parts anywhere ([`super::solve_transport_blocks`]), the
//! parts assembled in block order ([`super::assemble_transport`]). The model and the parts are
//! what a shared store keeps between the steps: the model as JSON (every `f64` round-trips
//! exactly), a part as bytes ([`TransportPart::encode`]).
//!
//! A part's encoding (little endian): magic `HZTP`, version (u8), first and end block (u32
//! each), rows (u32), nonzeros (u64), sigmas (u32), the counters (iterations, largest
//! iteration count, parent iterations, parent rows, refit iterations, largest read in bytes:
//! u64 each; seconds: f64), each row's nonzero count (u32 x rows), `index` (u32 x nonzeros),
//! `value` (f32 x nonzeros), the exact inverse's noise sigmas (f64 x sigmas), then a CRC-32C
//! (u32) of everything before it.

use std::ops::Range;

use helmholtz_proto::PatternSpec;
use serde::{Deserialize, Serialize};
use serde_json::{Map, Value};

use super::CameraGrid;
use crate::ReconError;
use crate::holdout::HeldOut;
use crate::transforms::TransformKind;

/// The memory plan's figures, as reported.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct MemoryFigures {
    pub budget: usize,
    pub fixed: usize,
    pub per_pixel: usize,
    pub scratch: usize,
    /// The largest block the budget allows.
    pub block_pixels: usize,
}

/// What the planning step decided, for every block of every shard: the chosen model, the
/// blocks of camera pixels, the solver's settings, and the report's figures so far.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TransportModel {
    pub version: u32,
    pub projector: (u32, u32),
    pub camera: (u32, u32),
    /// Frames used.
    pub rows: u64,
    /// A complete set, inverted exactly.
    pub exact: bool,
    pub transform: TransformKind,
    /// The l1 weight as a fraction of each row's `lambda_max` (iterative path).
    pub lambda: Option<f64>,
    /// Least-squares refit on the lasso's support.
    pub refit: bool,
    /// `L >= ||A||^2`, the step of every row's FISTA.
    pub lipschitz: f64,
    /// Coarse-to-fine used.
    pub coarse: bool,
    pub coarse_requested: bool,
    /// Rows per solver chunk.
    pub chunk: usize,
    /// The planning process's rayon threads: every part is solved on as many (sums split over
    /// threads are part of the arithmetic).
    pub threads: usize,
    pub max_iter: usize,
    pub tol: f64,
    /// The blocks of camera pixels, `[start, end)`, in order, tiling `0..m`.
    pub blocks: Vec<(usize, usize)>,
    pub memory: MemoryFigures,
    /// The request's canonical parameters.
    pub params: Value,
    /// The model choice's figures (`selection`).
    pub details: Map<String, Value>,
    pub notes: Vec<String>,
    pub held_out: Option<HeldOut>,
    pub held_out_unavailable: Option<String>,
    /// Largest read while choosing the model.
    pub largest_read_bytes: u64,
    /// Seconds the planning took.
    pub seconds: f64,
    /// Every row's l1 weight is at least its noise floor (Hadamard subsets: the universal
    /// threshold of the noise its split-pair sums show).
    #[serde(default)]
    pub noise_floor: bool,
    /// A Bernoulli session's frame noise behind the floor (the sample pixels' median estimate).
    #[serde(default)]
    pub floor_sigma: Option<f64>,
    /// The projector grid is the session's over this factor ([`super::TransportConfig`]'s
    /// `projector_binning`); `projector` is the coarse grid.
    #[serde(default = "one")]
    pub binning: u32,
    /// The Haar coefficients the subset measures completely are taken from the data and kept
    /// by the noise test of a complete set (`CoarseExact` in the module; version 2); from
    /// version 6 the model's finer coefficients are held to the same test.
    #[serde(default)]
    pub coarse_exact: bool,
    /// The rows are solved by coordinate descent on `A Psi^T` held densely (random patterns;
    /// `batch::Dense` in the module; version 3); else by FISTA on the operator. A model planned
    /// before version 3 is solved by FISTA, as it was planned.
    #[serde(default)]
    pub dense: bool,
    /// Every stored row is compacted at these shares in turn (`prune_rows` in the module: its
    /// smallest coefficients dropped within the share of its energy and of its light), each
    /// round refitted where `refit` is set and the coarse coefficients are not taken as measured
    /// (version 4).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub prune: Vec<f64>,
}

fn one() -> u32 {
    1
}

impl TransportModel {
    /// 2: `coarse_exact`; 3: `dense`; 4: `prune`; 5: the refit on the operator by CGLS
    /// (`batch::refit_rows`); 6: with `coarse_exact`, the model's finer coefficients held to
    /// the complete set's noise test (`CoarseExact` in the module). An older model is solved as
    /// it was planned; an older build refuses a newer model.
    pub const VERSION: u32 = 6;

    pub fn camera_grid(&self) -> CameraGrid {
        CameraGrid {
            width: self.camera.0,
            height: self.camera.1,
        }
    }

    /// The transform of the stored rows: Haar where the coarse coefficients are taken as
    /// measured, else the fitted one.
    pub fn stored_transform(&self) -> TransformKind {
        if self.coarse_exact {
            TransformKind::Haar
        } else {
            self.transform
        }
    }

    /// Camera pixels.
    pub fn pixels(&self) -> usize {
        self.camera.0 as usize * self.camera.1 as usize
    }

    /// Number of blocks.
    pub fn block_count(&self) -> usize {
        self.blocks.len()
    }

    /// Camera pixels of blocks `blocks`.
    pub fn block_pixels(&self, blocks: Range<usize>) -> Range<usize> {
        let start = self.blocks.get(blocks.start).map_or(0, |b| b.0);
        let end = blocks
            .end
            .checked_sub(1)
            .and_then(|i| self.blocks.get(i))
            .map_or(start, |b| b.1);
        start..end
    }

    /// Cuts the blocks to at most `max_pixels` camera pixels each (whole pairs of camera lines
    /// with coarse-to-fine, so at least two lines): before any part is solved. Every row of `T`
    /// comes out the same whatever block it is solved in; only the number of frame reads grows.
    pub fn limit_block_pixels(&mut self, max_pixels: usize) {
        let block = self.memory.block_pixels.min(max_pixels.max(1));
        let lines = self.coarse.then_some(self.camera.0 as usize);
        self.blocks = super::blocks(self.pixels(), block, lines)
            .into_iter()
            .map(|r| (r.start, r.end))
            .collect();
    }

    /// Shards of about `shard_pixels` camera pixels: consecutive runs of whole blocks (at least
    /// one each), as ranges of block indices, in order.
    pub fn shards(&self, shard_pixels: usize) -> Vec<Range<usize>> {
        let largest = self.blocks.iter().map(|(a, b)| b - a).max().unwrap_or(1);
        let per = (shard_pixels / largest.max(1)).max(1);
        (0..self.blocks.len())
            .step_by(per)
            .map(|s| s..(s + per).min(self.blocks.len()))
            .collect()
    }

    /// Refuses a spec of other dimensions than the model's.
    pub(super) fn check_spec(&self, spec: &PatternSpec) -> Result<(), ReconError> {
        if self.version == 0 || self.version > Self::VERSION {
            return Err(ReconError::Unsolvable(format!(
                "transport model version {} (this build solves version {})",
                self.version,
                Self::VERSION
            )));
        }
        let b = self.binning.max(1);
        if (spec.width() / b, spec.height() / b) != self.projector || self.rows > spec.count() {
            return Err(ReconError::Unsolvable(format!(
                "the transport model (projector {}x{} binned {b}x{b}, {} frames) does not fit the session's spec ({}x{}, {} patterns)",
                self.projector.0 * b,
                self.projector.1 * b,
                self.rows,
                spec.width(),
                spec.height(),
                spec.count()
            )));
        }
        Ok(())
    }

    pub fn to_json(&self) -> String {
        serde_json::to_string(self).expect("a transport model serializes")
    }

    pub fn from_json(json: &str) -> Result<TransportModel, serde_json::Error> {
        serde_json::from_str(json)
    }
}

/// Solved blocks of camera pixels: their rows of `T` (sparse, as the assembly appends them),
/// the exact inverse's noise sigmas and the solver's counters.
#[derive(Clone, Debug, PartialEq)]
pub struct TransportPart {
    /// Block indices of the model.
    pub blocks: Range<usize>,
    pub(super) row_ptr: Vec<u64>,
    pub(super) index: Vec<u32>,
    pub(super) value: Vec<f32>,
    pub(super) sigmas: Vec<f64>,
    pub(super) iterations: u64,
    pub(super) iterations_max: u64,
    pub(super) parent_iterations: u64,
    pub(super) parent_rows: u64,
    pub(super) refit_iterations: u64,
    pub(super) largest_read_bytes: u64,
    /// Seconds the solve took.
    pub seconds: f64,
}

const PART_MAGIC: &[u8; 4] = b"HZTP";
const PART_VERSION: u8 = 1;

/// Why bytes are not a transport part.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum PartDecodeError {
    #[error("transport part: {0} bytes is too short")]
    TooShort(usize),
    #[error("transport part: bad magic")]
    BadMagic,
    #[error(
        "transport part: version {0} is not supported (this build reads version {PART_VERSION})"
    )]
    UnsupportedVersion(u8),
    #[error(
        "transport part: checksum mismatch (stored crc32c {stored:08x}, computed {computed:08x}): the bytes are corrupt"
    )]
    Checksum { stored: u32, computed: u32 },
    #[error("transport part: inconsistent contents: {0}")]
    Inconsistent(String),
}

/// Reads little-endian values off the front of a slice.
struct Reader<'a>(&'a [u8]);

impl Reader<'_> {
    fn take(&mut self, n: usize) -> Result<&[u8], PartDecodeError> {
        if self.0.len() < n {
            return Err(PartDecodeError::Inconsistent(format!(
                "{} bytes left where {n} were due",
                self.0.len()
            )));
        }
        let (a, b) = self.0.split_at(n);
        self.0 = b;
        Ok(a)
    }
    fn u32(&mut self) -> Result<u32, PartDecodeError> {
        Ok(u32::from_le_bytes(self.take(4)?.try_into().expect("4")))
    }
    fn u64(&mut self) -> Result<u64, PartDecodeError> {
        Ok(u64::from_le_bytes(self.take(8)?.try_into().expect("8")))
    }
}

impl TransportPart {
    /// Rows of `T` (camera pixels) in this part.
    pub fn rows(&self) -> usize {
        self.row_ptr.len().saturating_sub(1)
    }

    pub fn nonzeros(&self) -> usize {
        self.value.len()
    }

    /// The part as bytes (module docs).
    pub fn encode(&self) -> Vec<u8> {
        let rows = self.rows();
        let nnz = self.value.len();
        let mut out = Vec::with_capacity(96 + 4 * rows + 8 * nnz + 8 * self.sigmas.len());
        out.extend_from_slice(PART_MAGIC);
        out.push(PART_VERSION);
        out.extend_from_slice(&(self.blocks.start as u32).to_le_bytes());
        out.extend_from_slice(&(self.blocks.end as u32).to_le_bytes());
        out.extend_from_slice(&(rows as u32).to_le_bytes());
        out.extend_from_slice(&(nnz as u64).to_le_bytes());
        out.extend_from_slice(&(self.sigmas.len() as u32).to_le_bytes());
        for v in [
            self.iterations,
            self.iterations_max,
            self.parent_iterations,
            self.parent_rows,
            self.refit_iterations,
            self.largest_read_bytes,
            self.seconds.to_bits(),
        ] {
            out.extend_from_slice(&v.to_le_bytes());
        }
        for w in self.row_ptr.windows(2) {
            out.extend_from_slice(&((w[1] - w[0]) as u32).to_le_bytes());
        }
        for i in &self.index {
            out.extend_from_slice(&i.to_le_bytes());
        }
        for v in &self.value {
            out.extend_from_slice(&v.to_le_bytes());
        }
        for s in &self.sigmas {
            out.extend_from_slice(&s.to_le_bytes());
        }
        let crc = crc32c::crc32c(&out);
        out.extend_from_slice(&crc.to_le_bytes());
        out
    }

    /// Reads [`TransportPart::encode`]'s bytes, checking the checksum and the sizes.
    pub fn decode(bytes: &[u8]) -> Result<TransportPart, PartDecodeError> {
        if bytes.len() < 9 {
            return Err(PartDecodeError::TooShort(bytes.len()));
        }
        if &bytes[..4] != PART_MAGIC {
            return Err(PartDecodeError::BadMagic);
        }
        if bytes[4] != PART_VERSION {
            return Err(PartDecodeError::UnsupportedVersion(bytes[4]));
        }
        let (body, tail) = bytes.split_at(bytes.len() - 4);
        let stored = u32::from_le_bytes(tail.try_into().expect("4"));
        let computed = crc32c::crc32c(body);
        if stored != computed {
            return Err(PartDecodeError::Checksum { stored, computed });
        }
        let mut r = Reader(&body[5..]);
        let (first, end) = (r.u32()? as usize, r.u32()? as usize);
        let rows = r.u32()? as usize;
        let nnz = r.u64()? as usize;
        let sigma_count = r.u32()? as usize;
        let iterations = r.u64()?;
        let iterations_max = r.u64()?;
        let parent_iterations = r.u64()?;
        let parent_rows = r.u64()?;
        let refit_iterations = r.u64()?;
        let largest_read_bytes = r.u64()?;
        let seconds = f64::from_bits(r.u64()?);
        let expected = rows
            .checked_mul(4)
            .and_then(|a| nnz.checked_mul(8).map(|b| a + b))
            .and_then(|a| sigma_count.checked_mul(8).map(|b| a + b));
        if expected != Some(r.0.len()) {
            return Err(PartDecodeError::Inconsistent(format!(
                "{} bytes of rows for {rows} rows, {nnz} nonzeros and {sigma_count} sigmas",
                r.0.len()
            )));
        }
        let mut row_ptr = Vec::with_capacity(rows + 1);
        row_ptr.push(0u64);
        for _ in 0..rows {
            let next = row_ptr.last().expect("one") + r.u32()? as u64;
            row_ptr.push(next);
        }
        if row_ptr.last().copied() != Some(nnz as u64) {
            return Err(PartDecodeError::Inconsistent(format!(
                "rows hold {} nonzeros, the header says {nnz}",
                row_ptr.last().copied().unwrap_or(0)
            )));
        }
        let index = r
            .take(4 * nnz)?
            .chunks_exact(4)
            .map(|b| u32::from_le_bytes(b.try_into().expect("4")))
            .collect();
        let value = r
            .take(4 * nnz)?
            .chunks_exact(4)
            .map(|b| f32::from_le_bytes(b.try_into().expect("4")))
            .collect();
        let sigmas = r
            .take(8 * sigma_count)?
            .chunks_exact(8)
            .map(|b| f64::from_le_bytes(b.try_into().expect("8")))
            .collect();
        if end <= first {
            return Err(PartDecodeError::Inconsistent(format!(
                "blocks {first}..{end}"
            )));
        }
        Ok(TransportPart {
            blocks: first..end,
            row_ptr,
            index,
            value,
            sigmas,
            iterations,
            iterations_max,
            parent_iterations,
            parent_rows,
            refit_iterations,
            largest_read_bytes,
            seconds,
        })
    }
}
