//! Relighting over HTTP.
//!
//! - `POST /v1/reconstructions/{id}/relight`: the dual image `p' = T^T c'` under a virtual light
//!   `c'` at the detector side: per-channel weights (bucket sessions), a camera-sized image (PNG
//!   or NPY body), or a preset (`full`, a `disc`, a `stripe`; camera sessions).
//! - `POST /v1/reconstructions/{id}/primal`: the camera image `c = T p + ambient` a projector
//!   pattern `p` would give (PNG or NPY body, or `{"pattern_index": i}` for one of the session's
//!   own patterns; then the response also carries the error against the measured frame).
//!
//! Reconstructions never change once done, so a response is a function of (reconstruction,
//! request body, format): its strong ETag is a hash of those, `If-None-Match` answers 304 without
//! computing, and recent responses are kept ([`ResponseCache`]). Decoded transport matrices stay
//! in memory ([`TransportCache`], least recently used dropped first).
//!
//! Modules by concern: [`body`] reads a request body (JSON, PNG, NPY), [`light`] turns it into
//! a virtual light and relights, [`primal`] predicts camera images, [`derived`] serves the files
//! made from a bucket session's dual images (photometric stereo, colour composite); [`cache`]
//! holds decoded transport matrices and encoded answers, [`response`] the ETag, encoding and
//! header side every answer shares.

mod body;
mod cache;
mod derived;
mod light;
mod primal;
mod response;

use super::{ApiError, AppState};
use crate::auth::Principal;
use crate::store::{ReconstructionRow, SessionRow};

pub use cache::{CachedResponse, ResponseCache, TransportCache};
pub use derived::{DERIVED_FILES, derived};
pub use light::relight;
pub use primal::primal;

/// The caller's finished reconstruction and its session.
pub(super) async fn finished(
    state: &AppState,
    caller: &Principal,
    id: i64,
) -> Result<(ReconstructionRow, SessionRow), ApiError> {
    let r = state.own_reconstruction(caller, id).await?;
    if r.state != "done" {
        return Err(ApiError::FailedPrecondition(format!(
            "reconstruction {id} is {}; relighting needs a finished reconstruction",
            r.state
        )));
    }
    let session = state.store.session(&r.session_id).await?;
    Ok((r, session))
}

/// Refuses a computed image holding inf or NaN (the input's values overflow 32-bit floats),
/// naming the input `field`.
pub(super) fn finite_result(data: &[f32], field: &str) -> Result<(), ApiError> {
    match data.iter().position(|v| !v.is_finite()) {
        None => Ok(()),
        Some(i) => Err(ApiError::invalid(
            field,
            format!(
                "the result is not finite at pixel {i} ({}): the values overflow 32-bit floats; scale them down",
                data[i]
            ),
        )),
    }
}
