//! Exact inverses (placeholder until implemented).
use super::*;
pub fn run(_p: &Problem, _s: &mut dyn BucketSource, _k: &Control) -> Result<Reconstruction, ReconError> {
    Err(ReconError::Unsolvable("direct is not built yet".into()))
}
