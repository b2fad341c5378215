//! The reconstructed transport matrix `T` (m camera pixels x k projector pixels), stored sparse:
//! row `j` is `t_j = Psi^T s_j` with `s_j` the row's coefficients in one orthonormal transform
//! `Psi` (the same for every row), of which only the nonzero ones are kept (CSR: row offsets,
//! coefficient indices, f32 values).
//!
//! - `relight(c')` = `T^T c'` = `Psi^T (sum_j c'_j s_j)`: the sparse rows are accumulated in the
//!   coefficient domain (rayon, one accumulator per split of the rows), then one inverse
//!   transform.
//! - `primal(p)` = `T p`: one forward transform `Psi p`, then a sparse dot product per row
//!   (`t_j . p = s_j . Psi p`, `Psi` orthonormal).
//!
//! Encoding (little endian): magic `HZTRANSP`, format version (u16), header length (u32), a JSON
//! header naming the sizes, transform, counts and layout, then `row_ptr` (u64 x (m + 1)),
//! `index` (u32 x nnz), `value` (f32 x nnz), and a CRC-32C (u32) of everything before it.

use rayon::prelude::*;
use serde_json::json;

use crate::transforms::{Transform, TransformKind};

const MAGIC: &[u8; 8] = b"HZTRANSP";
const VERSION: u16 = 1;

/// Why bytes are not a transport matrix.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum TransportDecodeError {
    #[error("transport matrix: {0} bytes is too short for the header")]
    TooShort(usize),
    #[error("transport matrix: bad magic (not a Helmholtz transport matrix)")]
    BadMagic,
    #[error(
        "transport matrix: format version {0} is not supported (this build reads version {VERSION})"
    )]
    UnsupportedVersion(u16),
    #[error(
        "transport matrix: checksum mismatch (stored crc32c {stored:08x}, computed {computed:08x}): the bytes are corrupt"
    )]
    Checksum { stored: u32, computed: u32 },
    #[error("transport matrix: bad header: {0}")]
    BadHeader(String),
    #[error("transport matrix: inconsistent contents: {0}")]
    Inconsistent(String),
}

/// `T`, sparse in an orthonormal transform (module docs).
pub struct TransportMatrix {
    projector: (u32, u32),
    camera: (u32, u32),
    transform: TransformKind,
    row_ptr: Vec<u64>,
    index: Vec<u32>,
    value: Vec<f32>,
    psi: Box<dyn Transform>,
}

impl std::fmt::Debug for TransportMatrix {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("TransportMatrix")
            .field("projector", &self.projector)
            .field("camera", &self.camera)
            .field("transform", &self.transform)
            .field("nonzeros", &self.value.len())
            .finish()
    }
}

impl PartialEq for TransportMatrix {
    fn eq(&self, other: &Self) -> bool {
        self.projector == other.projector
            && self.camera == other.camera
            && self.transform == other.transform
            && self.row_ptr == other.row_ptr
            && self.index == other.index
            && self
                .value
                .iter()
                .map(|v| v.to_bits())
                .eq(other.value.iter().map(|v| v.to_bits()))
    }
}

impl Clone for TransportMatrix {
    fn clone(&self) -> Self {
        TransportMatrix {
            projector: self.projector,
            camera: self.camera,
            transform: self.transform,
            row_ptr: self.row_ptr.clone(),
            index: self.index.clone(),
            value: self.value.clone(),
            psi: self
                .transform
                .build(self.projector.0 as usize, self.projector.1 as usize),
        }
    }
}

/// Rows appended one at a time (the reconstruction's output, block by block).
pub(crate) struct Builder {
    projector: (u32, u32),
    camera: (u32, u32),
    transform: TransformKind,
    row_ptr: Vec<u64>,
    index: Vec<u32>,
    value: Vec<f32>,
}

impl Builder {
    pub fn new(projector: (u32, u32), camera: (u32, u32), transform: TransformKind) -> Self {
        let m = camera.0 as usize * camera.1 as usize;
        let mut row_ptr = Vec::with_capacity(m + 1);
        row_ptr.push(0);
        Builder {
            projector,
            camera,
            transform,
            row_ptr,
            index: Vec::new(),
            value: Vec::new(),
        }
    }

    /// Appends the next row from its coefficients, keeping those with `|s| > threshold` that
    /// are nonzero in f32.
    pub fn push_row(&mut self, coefficients: &[f64], threshold: f64) {
        for (i, &s) in coefficients.iter().enumerate() {
            let v = s as f32;
            if s.abs() > threshold && v != 0.0 {
                self.index.push(i as u32);
                self.value.push(v);
            }
        }
        self.row_ptr.push(self.value.len() as u64);
    }

    /// Appends the next row from its coefficients, keeping those marked in `keep` that are
    /// nonzero in f32.
    pub fn push_kept(&mut self, coefficients: &[f64], keep: &[bool]) {
        for (i, (&s, &kept)) in coefficients.iter().zip(keep).enumerate() {
            let v = s as f32;
            if kept && v != 0.0 {
                self.index.push(i as u32);
                self.value.push(v);
            }
        }
        self.row_ptr.push(self.value.len() as u64);
    }

    pub fn rows(&self) -> usize {
        self.row_ptr.len() - 1
    }

    /// The rows so far as CSR (`row_ptr` from 0, `index`, `value`): a part of `T`.
    pub fn into_rows(self) -> (Vec<u64>, Vec<u32>, Vec<f32>) {
        (self.row_ptr, self.index, self.value)
    }

    /// Appends rows as [`Builder::into_rows`] gave them (every row kept as it is).
    pub fn append_rows(&mut self, row_ptr: &[u64], index: &[u32], value: &[f32]) {
        let base = self.value.len() as u64;
        let first = row_ptr.first().copied().unwrap_or(0);
        self.row_ptr
            .extend(row_ptr.iter().skip(1).map(|p| base + p - first));
        let (a, b) = (
            first as usize,
            row_ptr.last().copied().unwrap_or(0) as usize,
        );
        self.index.extend_from_slice(&index[a..b]);
        self.value.extend_from_slice(&value[a..b]);
    }

    pub fn finish(self) -> TransportMatrix {
        let m = self.camera.0 as usize * self.camera.1 as usize;
        assert_eq!(self.rows(), m, "every camera pixel needs a row");
        TransportMatrix::from_parts(
            self.projector,
            self.camera,
            self.transform,
            self.row_ptr,
            self.index,
            self.value,
        )
    }
}

impl TransportMatrix {
    fn from_parts(
        projector: (u32, u32),
        camera: (u32, u32),
        transform: TransformKind,
        row_ptr: Vec<u64>,
        index: Vec<u32>,
        value: Vec<f32>,
    ) -> Self {
        let psi = transform.build(projector.0 as usize, projector.1 as usize);
        TransportMatrix {
            projector,
            camera,
            transform,
            row_ptr,
            index,
            value,
            psi,
        }
    }

    /// A dense `m x k` matrix (row-major) stored sparse in `transform`, keeping every
    /// coefficient with `|s| > threshold` (tests, benchmarks).
    pub fn from_dense(
        projector: (u32, u32),
        camera: (u32, u32),
        transform: TransformKind,
        dense: &[f32],
        threshold: f64,
    ) -> Self {
        let k = projector.0 as usize * projector.1 as usize;
        let m = camera.0 as usize * camera.1 as usize;
        assert_eq!(dense.len(), m * k, "dense T must be m x k");
        let psi = transform.build(projector.0 as usize, projector.1 as usize);
        let mut b = Builder::new(projector, camera, transform);
        let (mut t, mut s) = (vec![0.0; k], vec![0.0; k]);
        for row in dense.chunks_exact(k) {
            t.iter_mut().zip(row).for_each(|(a, &b)| *a = b as f64);
            psi.apply(&t, &mut s);
            b.push_row(&s, threshold);
        }
        b.finish()
    }

    /// Rows given one at a time (f64, k values each, `m` of them), stored sparse in `transform`,
    /// keeping in each row the coefficients with `|s| > relative * max |s|` (benchmarks: a
    /// reference matrix from a scene's exact rows).
    pub fn from_rows(
        projector: (u32, u32),
        camera: (u32, u32),
        transform: TransformKind,
        rows: impl Iterator<Item = Vec<f64>>,
        relative: f64,
    ) -> Self {
        let k = projector.0 as usize * projector.1 as usize;
        let psi = transform.build(projector.0 as usize, projector.1 as usize);
        let mut b = Builder::new(projector, camera, transform);
        let mut s = vec![0.0; k];
        for t in rows {
            assert_eq!(t.len(), k, "a row has k values");
            psi.apply(&t, &mut s);
            let max = s.iter().fold(0.0f64, |m, v| m.max(v.abs()));
            b.push_row(&s, relative * max);
        }
        b.finish()
    }

    /// Projector grid `(width, height)`: `k = width * height` columns.
    pub fn projector(&self) -> (u32, u32) {
        self.projector
    }

    /// Camera grid `(width, height)`: `m = width * height` rows.
    pub fn camera(&self) -> (u32, u32) {
        self.camera
    }

    /// The transform the rows are stored in.
    pub fn transform(&self) -> TransformKind {
        self.transform
    }

    fn k(&self) -> usize {
        self.projector.0 as usize * self.projector.1 as usize
    }

    fn m(&self) -> usize {
        self.camera.0 as usize * self.camera.1 as usize
    }

    fn row_range(&self, j: usize) -> std::ops::Range<usize> {
        self.row_ptr[j] as usize..self.row_ptr[j + 1] as usize
    }

    /// Nonzero coefficients of row `j`: `(index, value)`.
    pub fn row_coefficients(&self, j: usize) -> (&[u32], &[f32]) {
        let r = self.row_range(j);
        (&self.index[r.clone()], &self.value[r])
    }

    /// `p' = T^T c'`: the projector-side image lit by camera-side light `c'` (m values; the
    /// dual image when `c'` is a camera pixel's indicator). Returns k values.
    pub fn relight(&self, light: &[f32]) -> Vec<f32> {
        let (m, k) = (self.m(), self.k());
        assert_eq!(
            light.len(),
            m,
            "relight takes one value per camera pixel ({m})"
        );
        let threads = rayon::current_num_threads().max(1);
        let min_len = m.div_ceil(threads).max(64);
        let acc = (0..m)
            .into_par_iter()
            .with_min_len(min_len)
            .fold(
                || vec![0f32; k],
                |mut acc, j| {
                    let c = light[j];
                    if c != 0.0 {
                        let r = self.row_range(j);
                        for (&i, &v) in self.index[r.clone()].iter().zip(&self.value[r]) {
                            acc[i as usize] += c * v;
                        }
                    }
                    acc
                },
            )
            .reduce_with(|mut a, b| {
                a.iter_mut().zip(&b).for_each(|(x, y)| *x += y);
                a
            })
            .unwrap_or_else(|| vec![0f32; k]);
        self.synthesise(&acc)
    }

    /// `Psi^T s` for coefficients `s` (f32 in, f32 out).
    fn synthesise(&self, s: &[f32]) -> Vec<f32> {
        if self.transform == TransformKind::Identity {
            return s.to_vec();
        }
        let s64: Vec<f64> = s.iter().map(|&v| v as f64).collect();
        let mut t = vec![0.0; s.len()];
        self.psi.adjoint(&s64, &mut t);
        t.into_iter().map(|v| v as f32).collect()
    }

    /// `c = T p`: the camera frame a projector pattern `p` (k values) gives. Returns m values.
    pub fn primal(&self, pattern: &[f32]) -> Vec<f32> {
        let k = self.k();
        assert_eq!(
            pattern.len(),
            k,
            "primal takes one value per projector pixel ({k})"
        );
        let sp: Vec<f32> = if self.transform == TransformKind::Identity {
            pattern.to_vec()
        } else {
            let p: Vec<f64> = pattern.iter().map(|&v| v as f64).collect();
            let mut s = vec![0.0; k];
            self.psi.apply(&p, &mut s);
            s.into_iter().map(|v| v as f32).collect()
        };
        let m = self.m();
        let threads = rayon::current_num_threads().max(1);
        let mut out = vec![0f32; m];
        out.par_iter_mut()
            .with_min_len(m.div_ceil(threads).max(64))
            .enumerate()
            .for_each(|(j, o)| {
                let r = self.row_range(j);
                *o = self.index[r.clone()]
                    .iter()
                    .zip(&self.value[r])
                    .map(|(&i, &v)| v * sp[i as usize])
                    .sum();
            });
        out
    }

    /// Dense row `j` (the dual image of camera pixel `j`, k values).
    pub fn row(&self, j: usize) -> Vec<f32> {
        assert!(j < self.m(), "row {j} of {}", self.m());
        let mut s = vec![0f32; self.k()];
        let (idx, val) = self.row_coefficients(j);
        for (&i, &v) in idx.iter().zip(val) {
            s[i as usize] = v;
        }
        self.synthesise(&s)
    }

    /// Stored coefficients (all rows).
    pub fn nonzeros(&self) -> usize {
        self.value.len()
    }

    fn header_json(&self) -> Vec<u8> {
        serde_json::to_vec(&json!({
            "kind": "helmholtz transport matrix",
            "projector": [self.projector.0, self.projector.1],
            "camera": [self.camera.0, self.camera.1],
            "transform": self.transform.name(),
            "rows": self.m(),
            "nonzeros": self.value.len(),
            "layout": "row t_j = Psi^T s_j (Psi orthonormal); CSR of s: row_ptr u64 LE (rows + 1), index u32 LE (nonzeros), value f32 LE (nonzeros); then crc32c u32 LE of all preceding bytes",
        }))
        .expect("a JSON object serialises")
    }

    /// Size of [`TransportMatrix::encode`] in bytes.
    pub fn stored_bytes(&self) -> usize {
        8 + 2 + 4 + self.header_json().len() + 8 * self.row_ptr.len() + 8 * self.value.len() + 4
    }

    /// The versioned, self-describing, checksummed encoding (module docs).
    pub fn encode(&self) -> Vec<u8> {
        let header = self.header_json();
        let mut out = Vec::with_capacity(self.stored_bytes());
        out.extend_from_slice(MAGIC);
        out.extend_from_slice(&VERSION.to_le_bytes());
        out.extend_from_slice(&(header.len() as u32).to_le_bytes());
        out.extend_from_slice(&header);
        for p in &self.row_ptr {
            out.extend_from_slice(&p.to_le_bytes());
        }
        for i in &self.index {
            out.extend_from_slice(&i.to_le_bytes());
        }
        for v in &self.value {
            out.extend_from_slice(&v.to_le_bytes());
        }
        let crc = crc32c::crc32c(&out);
        out.extend_from_slice(&crc.to_le_bytes());
        out
    }

    /// Reads [`TransportMatrix::encode`]'s bytes, checking the checksum and every count.
    pub fn decode(bytes: &[u8]) -> Result<TransportMatrix, TransportDecodeError> {
        use TransportDecodeError as E;
        if bytes.len() < 8 + 2 + 4 + 4 {
            return Err(E::TooShort(bytes.len()));
        }
        if &bytes[..8] != MAGIC {
            return Err(E::BadMagic);
        }
        let (body, tail) = bytes.split_at(bytes.len() - 4);
        let stored = u32::from_le_bytes(tail.try_into().expect("4 bytes"));
        let computed = crc32c::crc32c(body);
        if stored != computed {
            return Err(E::Checksum { stored, computed });
        }
        let version = u16::from_le_bytes([body[8], body[9]]);
        if version != VERSION {
            return Err(E::UnsupportedVersion(version));
        }
        let header_len = u32::from_le_bytes(body[10..14].try_into().expect("4 bytes")) as usize;
        let header_end = 14usize
            .checked_add(header_len)
            .filter(|&e| e <= body.len())
            .ok_or_else(|| E::BadHeader(format!("header length {header_len} runs past the end")))?;
        let header: serde_json::Value = serde_json::from_slice(&body[14..header_end])
            .map_err(|e| E::BadHeader(e.to_string()))?;
        let pair = |key: &str| -> Result<(u32, u32), E> {
            let a = header
                .get(key)
                .and_then(|v| v.as_array())
                .filter(|a| a.len() == 2)
                .ok_or_else(|| E::BadHeader(format!("{key} must be [width, height]")))?;
            let side = |v: &serde_json::Value| {
                v.as_u64()
                    .filter(|&s| (1..=u32::MAX as u64).contains(&s))
                    .map(|s| s as u32)
            };
            match (side(&a[0]), side(&a[1])) {
                (Some(w), Some(h)) => Ok((w, h)),
                _ => Err(E::BadHeader(format!("{key} must be two positive integers"))),
            }
        };
        let projector = pair("projector")?;
        let camera = pair("camera")?;
        let name = header
            .get("transform")
            .and_then(|v| v.as_str())
            .ok_or_else(|| E::BadHeader("transform missing".into()))?;
        let transform = TransformKind::ALL
            .into_iter()
            .find(|t| t.name() == name)
            .ok_or_else(|| E::BadHeader(format!("unknown transform {name:?}")))?;
        let m = camera.0 as u64 * camera.1 as u64;
        let k = projector.0 as u64 * projector.1 as u64;
        if header.get("rows").and_then(|v| v.as_u64()) != Some(m) {
            return Err(E::BadHeader(format!(
                "rows must equal the camera's {m} pixels"
            )));
        }
        let nnz = header
            .get("nonzeros")
            .and_then(|v| v.as_u64())
            .ok_or_else(|| E::BadHeader("nonzeros missing".into()))?;
        let payload = &body[header_end..];
        let want = (m + 1)
            .checked_mul(8)
            .and_then(|a| nnz.checked_mul(8).and_then(|b| a.checked_add(b)));
        if want != Some(payload.len() as u64) {
            return Err(E::Inconsistent(format!(
                "{} payload bytes for {m} rows and {nnz} nonzeros",
                payload.len()
            )));
        }
        let (ptr_bytes, rest) = payload.split_at((m as usize + 1) * 8);
        let (idx_bytes, val_bytes) = rest.split_at(nnz as usize * 4);
        let row_ptr: Vec<u64> = ptr_bytes
            .chunks_exact(8)
            .map(|c| u64::from_le_bytes(c.try_into().expect("8")))
            .collect();
        let index: Vec<u32> = idx_bytes
            .chunks_exact(4)
            .map(|c| u32::from_le_bytes(c.try_into().expect("4")))
            .collect();
        let value: Vec<f32> = val_bytes
            .chunks_exact(4)
            .map(|c| f32::from_le_bytes(c.try_into().expect("4")))
            .collect();
        if row_ptr[0] != 0 || row_ptr[m as usize] != nnz || row_ptr.windows(2).any(|w| w[0] > w[1])
        {
            return Err(E::Inconsistent(
                "row offsets must rise from 0 to the nonzero count".into(),
            ));
        }
        if let Some(i) = index.iter().find(|&&i| i as u64 >= k) {
            return Err(E::Inconsistent(format!(
                "coefficient index {i} outside the {k} projector pixels"
            )));
        }
        if value.iter().any(|v| !v.is_finite()) {
            return Err(E::Inconsistent("non-finite coefficient".into()));
        }
        Ok(TransportMatrix::from_parts(
            projector, camera, transform, row_ptr, index, value,
        ))
    }
}
