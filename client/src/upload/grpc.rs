//! The gRPC transport of an upload: the (lazily connecting) channel, writer ids, chunk messages
//! and one client stream of them.

use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Duration;

use anyhow::Context;
use helmholtz_proto::v1::{self, acquisition_client::AcquisitionClient};
use helmholtz_proto::wire;
use indicatif::ProgressBar;
use tokio_stream::wrappers::ReceiverStream;
use tonic::Status;
use tonic::transport::Endpoint;

use crate::auth::Grpc;

use super::{RowSource, SampleFormat, UploadOptions, UploadReport};

/// A lazily connecting client: no I/O happens until the first call, and a fresh one is made for
/// each attempt so a restarted server is found again.
pub fn connect(server: &str, connect_timeout: Duration) -> anyhow::Result<Grpc> {
    let (server, token) = crate::auth::split_server(server);
    let endpoint = Endpoint::from_shared(server.clone())
        .with_context(|| {
            format!(
                "invalid server address {server:?} (expected e.g. http://127.0.0.1:8080 or https://host:port)"
            )
        })?
        .connect_timeout(connect_timeout)
        .tcp_nodelay(true)
        .http2_keep_alive_interval(Duration::from_secs(10))
        .keep_alive_timeout(Duration::from_secs(20));
    // https://: verified against the system roots and the lab's CA (--ca-file, see `tls`).
    let endpoint = if crate::tls::is_https(&server) {
        endpoint
            .tls_config(crate::tls::grpc_config())
            .context("TLS settings for the gRPC channel")?
    } else {
        endpoint
    };
    let bearer = crate::auth::Bearer::new(token.as_deref())?;
    Ok(
        AcquisitionClient::with_interceptor(endpoint.connect_lazy(), bearer)
            .max_decoding_message_size(64 << 20)
            .max_encoding_message_size(usize::MAX),
    )
}

/// A fresh writer id for [`upload_rows_as`](super::upload_rows_as): 128 random bits in hex.
pub fn new_writer_id() -> String {
    format!("{:032x}", rand::random::<u128>())
}

/// The chunks of rows `from..total`: (start_row, values slice).
pub fn chunk_ranges(
    total_rows: u64,
    from: u64,
    chunk_rows: usize,
) -> impl Iterator<Item = (u64, u64)> {
    let step = chunk_rows.max(1) as u64;
    (from..total_rows)
        .step_by(step as usize)
        .map(move |s| (s, (s + step).min(total_rows)))
}

/// One chunk message carrying `payload` (rows from `start_row`, little-endian values of
/// `format`) in the field of that format, with its CRC-32C.
pub fn encode_chunk(
    session_id: &str,
    channels: u32,
    format: SampleFormat,
    start_row: u64,
    payload: Vec<u8>,
) -> v1::MeasurementChunk {
    let crc32c = crc32c::crc32c(&payload);
    let mut chunk = v1::MeasurementChunk {
        session_id: session_id.to_string(),
        start_row,
        channels,
        crc32c,
        ..Default::default()
    };
    match format {
        SampleFormat::F64 => chunk.values_f64le = payload,
        SampleFormat::F32 => chunk.values_f32le = payload,
        SampleFormat::U16 => chunk.values_u16le = payload,
    }
    chunk
}

/// The payload bytes a chunk carries (whichever field is set).
pub fn chunk_payload_len(chunk: &v1::MeasurementChunk) -> usize {
    chunk.values_f64le.len() + chunk.values_f32le.len() + chunk.values_u16le.len()
}

/// The chunk of rows `start..end` read from `source`.
pub fn read_chunk(
    session_id: &str,
    channels: u32,
    source: &dyn RowSource,
    start: u64,
    end: u64,
) -> anyhow::Result<v1::MeasurementChunk> {
    let payload = source.read_payload(start, end)?;
    let format = source.format();
    anyhow::ensure!(
        payload.len() as u64 == (end - start) * channels as u64 * format.bytes() as u64,
        "rows {start}..{end}: {} payload bytes read, not whole rows of {channels} {} values",
        payload.len(),
        format.name()
    );
    Ok(encode_chunk(session_id, channels, format, start, payload))
}

/// One chunk message for rows `start..end` of `values`.
pub fn make_chunk(
    session_id: &str,
    channels: u32,
    values: &[f64],
    start: u64,
    end: u64,
) -> v1::MeasurementChunk {
    let ch = channels as usize;
    let (bytes, crc) = wire::encode_values(&values[start as usize * ch..end as usize * ch]);
    v1::MeasurementChunk {
        session_id: session_id.to_string(),
        start_row: start,
        channels,
        values_f64le: bytes,
        crc32c: crc,
        ..Default::default()
    }
}

/// Why one stream of chunks ended early.
pub(super) enum StreamFailure {
    /// The server or the transport refused it.
    Rpc(Status),
    /// The rows could not be read locally (a damaged spool): not retried.
    Local(anyhow::Error),
}

/// One client stream of chunks from row `from` to `total`; the chunks are read and encoded as
/// the transport takes them (at most a few in flight), so memory stays bounded whatever the
/// session size.
#[allow(clippy::too_many_arguments)]
pub(super) async fn stream_rows(
    server: &str,
    session_id: &str,
    writer: &str,
    channels: u32,
    source: &dyn RowSource,
    total: u64,
    from: u64,
    chunk_rows: usize,
    opts: &UploadOptions,
    bar: &ProgressBar,
    report: &mut UploadReport,
) -> Result<v1::UploadResponse, StreamFailure> {
    let mut client = connect(server, opts.connect_timeout)
        .map_err(|e| StreamFailure::Rpc(Status::invalid_argument(e.to_string())))?;
    let (tx, rx) = tokio::sync::mpsc::channel::<v1::MeasurementChunk>(2);
    // Counters shared with the producer (atomics keep the upload future `Send`).
    let rows_sent = AtomicU64::new(0);
    let chunks_sent = AtomicU64::new(0);
    let bytes_sent = AtomicU64::new(0);
    let read_error = std::sync::Mutex::new(None::<anyhow::Error>);
    let producer = async {
        let tx = tx; // dropped when the producer ends: the end of the stream
        for (start, end) in chunk_ranges(total, from, chunk_rows) {
            let chunk = match read_chunk(session_id, channels, source, start, end) {
                Ok(c) => c,
                Err(e) => {
                    *read_error.lock().expect("not poisoned") = Some(e);
                    return;
                }
            };
            let bytes = chunk_payload_len(&chunk) as u64;
            if tx.send(chunk).await.is_err() {
                return; // the call ended; its result says why
            }
            rows_sent.fetch_add(end - start, Ordering::Relaxed);
            chunks_sent.fetch_add(1, Ordering::Relaxed);
            bytes_sent.fetch_add(bytes, Ordering::Relaxed);
            bar.set_position(end);
        }
    };
    let mut request = tonic::Request::new(ReceiverStream::new(rx));
    if let Ok(value) = writer.parse() {
        request.metadata_mut().insert("x-helmholtz-writer", value);
    }
    let call = client.upload_measurements(request);
    tokio::pin!(producer);
    tokio::pin!(call);
    let mut producing = true;
    let result = loop {
        tokio::select! {
            result = &mut call => break result,
            _ = &mut producer, if producing => producing = false,
        }
    };
    report.rows_sent += rows_sent.load(Ordering::Relaxed);
    report.chunks_sent += chunks_sent.load(Ordering::Relaxed);
    report.bytes_sent += bytes_sent.load(Ordering::Relaxed);
    if let Some(e) = read_error.lock().expect("not poisoned").take() {
        return Err(StreamFailure::Local(e));
    }
    result
        .map(tonic::Response::into_inner)
        .map_err(StreamFailure::Rpc)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn chunks_cover_rows_exactly_once_with_correct_crcs() {
        let channels = 3u32;
        let rows = 1000u64;
        let values: Vec<f64> = (0..rows * 3).map(|v| v as f64 * 0.25).collect();
        for (from, per) in [(0, 64), (7, 64), (999, 10), (0, 1000), (0, 5000), (1000, 3)] {
            let mut next = from;
            for (s, e) in chunk_ranges(rows, from, per) {
                assert_eq!(s, next);
                assert!(e > s && e - s <= per as u64);
                let chunk = make_chunk("sess", channels, &values, s, e);
                assert_eq!(chunk.start_row, s);
                assert_eq!(chunk.values_f64le.len() as u64, (e - s) * 3 * 8);
                assert_eq!(chunk.crc32c, crc32c::crc32c(&chunk.values_f64le));
                let back = wire::decode_values(&chunk.values_f64le, 3, chunk.crc32c).unwrap();
                assert_eq!(back, values[s as usize * 3..e as usize * 3]);
                next = e;
            }
            assert_eq!(next, rows.max(from));
        }
        // Default chunk size: 256 KiB of values.
        let opts = UploadOptions::default();
        assert_eq!(opts.rows_per_chunk(1), 32768);
        assert_eq!(opts.rows_per_chunk(4), 8192);
        assert_eq!(
            UploadOptions {
                chunk_rows: Some(0),
                ..opts
            }
            .rows_per_chunk(1),
            1
        );
    }
}
