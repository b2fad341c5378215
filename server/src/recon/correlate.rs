//! Streaming correlators (placeholder until implemented).
use super::*;
pub fn run(_p: &Problem, _c: &MethodConfig, _s: &mut dyn BucketSource, _k: &Control) -> Result<Reconstruction, ReconError> {
    Err(ReconError::Unsolvable("correlators are not built yet".into()))
}
