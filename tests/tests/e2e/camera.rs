//! Camera sessions over the real server: frames in their declared sample format, the same
//! resumable semantics as bucket rows, bad frames refused with a status naming the field and
//! nothing stored, and the frames served back byte for byte.

use helmholtz_client::auth::Grpc;
use helmholtz_proto::v1;
use helmholtz_tests::ServerProcess;
use tonic::Code;

fn spec(w: u32, h: u32, count: u64) -> v1::PatternSpec {
    v1::PatternSpec {
        family: v1::PatternFamily::Hadamard as i32,
        width: w,
        height: h,
        count,
        seed: 3,
        params: None,
    }
}

fn camera(w: u32, h: u32, format: v1::SampleFormat) -> v1::DetectorLayout {
    v1::DetectorLayout {
        camera: Some(v1::CameraLayout {
            width: w,
            height: h,
            format: format as i32,
        }),
        ..Default::default()
    }
}

fn create(
    id: &str,
    spec: v1::PatternSpec,
    detector: v1::DetectorLayout,
) -> v1::CreateSessionRequest {
    v1::CreateSessionRequest {
        session_id: id.into(),
        rig: "cam-rig".into(),
        patterns: Some(spec),
        detector: Some(detector),
        metadata: Default::default(),
        ground_truth: None,
    }
}

/// Frames `start..start+n` of a `pixels`-pixel camera as u16 counts.
fn frames_u16(start: u64, n: u64, pixels: usize) -> Vec<u8> {
    (start..start + n)
        .flat_map(|r| (0..pixels).map(move |p| ((r * 131 + p as u64 * 7) % 65536) as u16))
        .flat_map(|v| v.to_le_bytes())
        .collect()
}

fn u16_chunk(id: &str, start: u64, pixels: u32, bytes: Vec<u8>) -> v1::MeasurementChunk {
    let crc = crc32c::crc32c(&bytes);
    v1::MeasurementChunk {
        session_id: id.into(),
        start_row: start,
        channels: pixels,
        values_u16le: bytes,
        crc32c: crc,
        ..Default::default()
    }
}

async fn send(
    client: &mut Grpc,
    chunks: Vec<v1::MeasurementChunk>,
) -> Result<v1::UploadResponse, tonic::Status> {
    client
        .upload_measurements(tokio_stream::iter(chunks))
        .await
        .map(|r| r.into_inner())
}

async fn committed(client: &mut Grpc, id: &str) -> u64 {
    client
        .get_upload_status(v1::SessionRef {
            session_id: id.into(),
        })
        .await
        .unwrap()
        .into_inner()
        .committed_rows
}

fn assert_status(result: Result<impl std::fmt::Debug, tonic::Status>, code: Code, mentions: &str) {
    let status = result.expect_err("must be refused");
    assert_eq!(status.code(), code, "{status:?}");
    assert!(
        status.message().contains(mentions),
        "message {:?} should name {mentions:?}",
        status.message()
    );
}

#[tokio::test]
async fn camera_frames_upload_resume_and_come_back_byte_for_byte() {
    let dir = tempfile::tempdir().unwrap();
    let server = ServerProcess::start(dir.path(), 0, &["--max-frame-pixels", "4096"]).unwrap();
    let mut c = server.grpc().await.unwrap();
    use v1::SampleFormat::*;

    // Declarations that cannot be a camera session are refused, naming the field.
    let bad = [
        (
            create("c", spec(8, 8, 16), camera(0, 4, U16)),
            "detector.camera.width",
        ),
        (
            create("c", spec(8, 8, 16), camera(128, 64, U16)),
            "max_frame_pixels",
        ),
        (
            create("c", spec(8, 8, 16), camera(4, 4, F64)),
            "detector.camera.format",
        ),
        (
            create("c", spec(8, 8, 16), camera(4, 4, Unspecified)),
            "detector.camera.format",
        ),
        (
            create(
                "c",
                spec(8, 8, 16),
                v1::DetectorLayout {
                    channels: vec!["a".into()],
                    ..camera(4, 4, U16)
                },
            ),
            "detector.camera",
        ),
    ];
    for (req, field) in bad {
        assert_status(c.create_session(req).await, Code::InvalidArgument, field);
    }
    assert_status(
        c.get_upload_status(v1::SessionRef {
            session_id: "c".into(),
        })
        .await,
        Code::NotFound,
        "c",
    );

    // A 6x5 u16 camera under 16 Hadamard frames of 8x8.
    let (w, h) = (6u32, 5u32);
    let px = (w * h) as usize;
    let made = c
        .create_session(create("c", spec(8, 8, 16), camera(w, h, U16)))
        .await
        .unwrap()
        .into_inner();
    assert!(made.created);
    assert_eq!(
        made.session
            .unwrap()
            .detector
            .unwrap()
            .camera
            .unwrap()
            .width,
        w
    );
    // Same declaration again is idempotent; another format is a conflict.
    assert!(
        !c.create_session(create("c", spec(8, 8, 16), camera(w, h, U16)))
            .await
            .unwrap()
            .into_inner()
            .created
    );
    assert_status(
        c.create_session(create("c", spec(8, 8, 16), camera(w, h, F32)))
            .await,
        Code::AlreadyExists,
        "detector",
    );

    let all = frames_u16(0, 16, px);
    let row = px * 2;
    // Frames 0..6, then a resume that overlaps rows 4..6.
    let r = send(
        &mut c,
        vec![u16_chunk("c", 0, w * h, all[..6 * row].to_vec())],
    )
    .await
    .unwrap();
    assert_eq!((r.committed_rows, r.rows_written), (6, 6));
    let r = send(
        &mut c,
        vec![u16_chunk("c", 4, w * h, all[4 * row..10 * row].to_vec())],
    )
    .await
    .unwrap();
    assert_eq!(
        (r.committed_rows, r.rows_written, r.rows_skipped),
        (10, 4, 2)
    );

    // Bad chunks: each refused with a status naming the problem; nothing stored.
    let mut f64_chunk = u16_chunk("c", 10, w * h, Vec::new());
    f64_chunk.values_f64le = vec![0; px * 8];
    f64_chunk.crc32c = crc32c::crc32c(&f64_chunk.values_f64le);
    assert_status(
        send(&mut c, vec![f64_chunk]).await,
        Code::InvalidArgument,
        "values_f64le",
    );
    let mut both = u16_chunk("c", 10, w * h, all[10 * row..11 * row].to_vec());
    both.values_f32le = vec![0; px * 4];
    assert_status(
        send(&mut c, vec![both]).await,
        Code::InvalidArgument,
        "values_f32le",
    );
    let ragged = u16_chunk("c", 10, w * h, all[10 * row..11 * row - 2].to_vec());
    assert_status(
        send(&mut c, vec![ragged]).await,
        Code::InvalidArgument,
        "whole frames",
    );
    let mut corrupt = u16_chunk("c", 10, w * h, all[10 * row..12 * row].to_vec());
    corrupt.values_u16le[5] ^= 1;
    assert_status(send(&mut c, vec![corrupt]).await, Code::DataLoss, "crc32c");
    let wrong_size = u16_chunk("c", 10, w * h + 1, all[10 * row..11 * row].to_vec());
    assert_status(
        send(&mut c, vec![wrong_size]).await,
        Code::InvalidArgument,
        "pixels per frame",
    );
    let gap = u16_chunk("c", 11, w * h, all[11 * row..12 * row].to_vec());
    assert_status(send(&mut c, vec![gap]).await, Code::OutOfRange, "gap");
    assert_eq!(committed(&mut c, "c").await, 10);

    let r = send(
        &mut c,
        vec![u16_chunk("c", 10, w * h, all[10 * row..].to_vec())],
    )
    .await
    .unwrap();
    assert_eq!(r.committed_rows, 16);
    c.finish_session(v1::SessionRef {
        session_id: "c".into(),
    })
    .await
    .unwrap();

    // measurements.npy: uint16 frames of shape (16, 5, 6), exactly the bytes sent.
    let http = helmholtz_tests::http_client();
    let resp = http
        .get(server.url("/v1/sessions/c/measurements.npy"))
        .send()
        .await
        .unwrap();
    assert_eq!(resp.status(), 200);
    let body = resp.bytes().await.unwrap();
    let header_len = u16::from_le_bytes([body[8], body[9]]) as usize;
    let header = std::str::from_utf8(&body[10..10 + header_len]).unwrap();
    assert!(
        header.contains("'descr': '<u2'") && header.contains("'shape': (16, 5, 6)"),
        "{header}"
    );
    assert_eq!(&body[10 + header_len..], &all[..]);

    // The session document describes the camera.
    let doc: serde_json::Value = http
        .get(server.url("/v1/sessions/c"))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    assert_eq!(
        doc["camera"],
        serde_json::json!({"width": 6, "height": 5, "format": "u16"})
    );
}

#[tokio::test]
async fn f32_frames_must_be_finite_and_detector_directions_unit_vectors() {
    let dir = tempfile::tempdir().unwrap();
    let server = ServerProcess::start(dir.path(), 0, &[]).unwrap();
    let mut c = server.grpc().await.unwrap();
    c.create_session(create(
        "f",
        spec(4, 4, 4),
        camera(2, 2, v1::SampleFormat::F32),
    ))
    .await
    .unwrap();
    let mut values = [0.5f32; 8];
    values[6] = f32::NAN;
    let bytes: Vec<u8> = values.iter().flat_map(|v| v.to_le_bytes()).collect();
    let crc = crc32c::crc32c(&bytes);
    let chunk = v1::MeasurementChunk {
        session_id: "f".into(),
        start_row: 0,
        channels: 4,
        values_f32le: bytes,
        crc32c: crc,
        ..Default::default()
    };
    assert_status(
        send(&mut c, vec![chunk]).await,
        Code::InvalidArgument,
        "row 1, pixel 2",
    );
    assert_eq!(committed(&mut c, "f").await, 0);

    let dir_of = |x: f64, y: f64, z: f64| v1::Direction { x, y, z };
    let with_dirs = |dirs: Vec<v1::Direction>| v1::DetectorLayout {
        channels: vec!["n".into(), "s".into()],
        directions: dirs,
        camera: None,
    };
    let cases = [
        (
            with_dirs(vec![dir_of(0.0, -0.6, 0.8)]),
            "detector.directions",
        ),
        (
            with_dirs(vec![dir_of(0.0, -0.6, 0.8), dir_of(0.0, 0.6, 0.9)]),
            "detector.directions[1]",
        ),
        (
            with_dirs(vec![dir_of(0.0, -0.6, 0.8), dir_of(0.0, 0.6, -0.8)]),
            "z > 0",
        ),
    ];
    for (detector, field) in cases {
        assert_status(
            c.create_session(create("d", spec(4, 4, 4), detector)).await,
            Code::InvalidArgument,
            field,
        );
    }
    let ok = c
        .create_session(create(
            "d",
            spec(4, 4, 4),
            with_dirs(vec![dir_of(0.0, -0.6, 0.8), dir_of(0.0, 0.6, 0.8)]),
        ))
        .await
        .unwrap()
        .into_inner();
    assert_eq!(ok.session.unwrap().detector.unwrap().directions.len(), 2);
}
