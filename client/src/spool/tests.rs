use super::*;
use helmholtz_proto::PatternSpec;

fn session(id: &str, count: u64, channels: usize) -> NewSession {
    let spec: PatternSpec = serde_json::from_str(&format!(
        r#"{{"family":"bernoulli","width":8,"height":8,"count":{count},"seed":3}}"#
    ))
    .unwrap();
    let names = (0..channels).map(|c| format!("ch{c}")).collect();
    NewSession::new(id, spec, names)
}

fn rows(start: u64, n: u64, channels: usize) -> Vec<f64> {
    (start..start + n)
        .flat_map(|r| (0..channels).map(move |c| r as f64 * 10.0 + c as f64 + 0.125))
        .collect()
}

/// A way a crash can leave the end of a segment.
type Damage = Box<dyn Fn(&mut Vec<u8>)>;

fn segments(dir: &Path) -> Vec<PathBuf> {
    let mut v: Vec<PathBuf> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| {
            p.file_name()
                .and_then(|n| n.to_str())
                .and_then(parse_segment_name)
                .is_some()
        })
        .collect();
    v.sort();
    v
}

#[test]
fn appended_rows_read_back_exactly_across_frames_and_segments() {
    let tmp = tempfile::tempdir().unwrap();
    // Tiny segments: every append of 40 rows x 2 channels (640 bytes + header) fills one.
    let spools = SpoolDir::new(tmp.path()).with_segment_bytes(500);
    let spool = spools
        .create_or_open(&session("s1", 1000, 2), true)
        .unwrap();
    assert_eq!(spool.rows(), 0);
    for i in 0..10 {
        assert_eq!(spool.append(&rows(i * 40, 40, 2)).unwrap(), (i + 1) * 40);
    }
    assert_eq!(spool.segment_count(), 10);
    assert_eq!(spool.read(0, 400).unwrap(), rows(0, 400, 2));
    assert_eq!(spool.read(37, 123).unwrap(), rows(37, 86, 2));
    assert_eq!(spool.read(399, 400).unwrap(), rows(399, 1, 2));
    assert!(spool.read(10, 10).unwrap().is_empty());
    assert!(spool.read(0, 401).is_err());
    drop(spool);

    // Reopened: the same rows, nothing torn.
    let spool = spools.open("s1").unwrap();
    assert_eq!(spool.rows(), 400);
    assert_eq!(spool.read(0, 400).unwrap(), rows(0, 400, 2));
    let info = spools.inspect("s1").unwrap();
    assert_eq!(
        (info.spooled_rows, info.torn_bytes, info.segments),
        (400, 0, 10)
    );
    assert!(info.busy, "this process holds the lock");
    assert!(info.finish && !info.sealed);
    assert_eq!(spools.sessions().unwrap(), ["s1"]);
}

#[test]
fn a_torn_tail_is_truncated_on_open_and_earlier_rows_survive() {
    let tmp = tempfile::tempdir().unwrap();
    let spools = SpoolDir::new(tmp.path());
    let dir = spools.session_dir("t");
    {
        let spool = spools.create_or_open(&session("t", 100, 1), false).unwrap();
        spool.append(&rows(0, 10, 1)).unwrap();
        spool.append(&rows(10, 5, 1)).unwrap();
    }
    let seg = segments(&dir).pop().unwrap();
    let good_len = std::fs::metadata(&seg).unwrap().len();
    let cases: Vec<(&str, Damage)> = vec![
        // A crash after part of a header reached the disk.
        (
            "half a header",
            Box::new(|b: &mut Vec<u8>| b.extend_from_slice(&[7, 0, 0])),
        ),
        // A whole header, a cut payload.
        (
            "a cut payload",
            Box::new(|b: &mut Vec<u8>| {
                b.extend_from_slice(&16u32.to_le_bytes());
                b.extend_from_slice(&0u32.to_le_bytes());
                b.extend_from_slice(&15u64.to_le_bytes());
                b.extend_from_slice(&[1, 2, 3]);
            }),
        ),
        // Zeros where the file grew but the data never came (len 0 is never written).
        (
            "zeros",
            Box::new(|b: &mut Vec<u8>| b.extend_from_slice(&[0; 64])),
        ),
        // A complete frame whose bytes are wrong.
        (
            "a bad checksum",
            Box::new(|b: &mut Vec<u8>| {
                let payload = 1.5f64.to_le_bytes();
                b.extend_from_slice(&8u32.to_le_bytes());
                b.extend_from_slice(&12345u32.to_le_bytes());
                b.extend_from_slice(&15u64.to_le_bytes());
                b.extend_from_slice(&payload);
            }),
        ),
    ];
    for (what, damage) in cases {
        let mut bytes = std::fs::read(&seg).unwrap();
        bytes.truncate(good_len as usize);
        damage(&mut bytes);
        std::fs::write(&seg, &bytes).unwrap();
        let info = spools.inspect("t").unwrap();
        assert_eq!(info.spooled_rows, 15, "{what}");
        assert!(info.torn_bytes > 0, "{what}");
        assert_eq!(
            std::fs::metadata(&seg).unwrap().len(),
            bytes.len() as u64,
            "inspect changes nothing ({what})"
        );
        let spool = spools.open("t").unwrap();
        assert_eq!(spool.rows(), 15, "{what}");
        assert_eq!(std::fs::metadata(&seg).unwrap().len(), good_len, "{what}");
        // Appending after the repair continues the row sequence.
        spool.append(&rows(15, 3, 1)).unwrap();
        assert_eq!(spool.read(0, 18).unwrap(), rows(0, 18, 1), "{what}");
        drop(spool);
        let bytes = std::fs::read(&seg).unwrap();
        std::fs::write(&seg, &bytes[..good_len as usize]).unwrap();
    }
}

#[test]
fn damage_before_the_last_segment_is_an_error_not_a_silent_loss() {
    let tmp = tempfile::tempdir().unwrap();
    let spools = SpoolDir::new(tmp.path()).with_segment_bytes(90);
    {
        let spool = spools.create_or_open(&session("d", 100, 1), false).unwrap();
        for i in 0..3 {
            spool.append(&rows(i * 10, 10, 1)).unwrap();
        }
        assert_eq!(spool.segment_count(), 3);
    }
    let first = segments(&spools.session_dir("d")).remove(0);
    let mut bytes = std::fs::read(&first).unwrap();
    bytes[20] ^= 0x01;
    std::fs::write(&first, &bytes).unwrap();
    let e = format!("{:#}", spools.open("d").unwrap_err());
    assert!(e.contains("damaged") && e.contains("not the last"), "{e}");
    let e = format!("{:#}", spools.inspect("d").unwrap_err());
    assert!(e.contains("damaged"), "{e}");
}

#[test]
fn bad_rows_are_refused_and_spool_nothing() {
    let tmp = tempfile::tempdir().unwrap();
    let spools = SpoolDir::new(tmp.path());
    let spool = spools.create_or_open(&session("b", 20, 2), false).unwrap();
    spool.append(&rows(0, 5, 2)).unwrap();
    let mut nan = rows(5, 3, 2);
    nan[3] = f64::NAN;
    let e = spool.append(&nan).unwrap_err().to_string();
    assert!(
        e.contains("row 6, channel 1") && e.contains("not finite"),
        "{e}"
    );
    let e = spool.append(&[1.0, 2.0, 3.0]).unwrap_err().to_string();
    assert!(e.contains("whole"), "{e}");
    let e = spool.append(&rows(5, 16, 2)).unwrap_err().to_string();
    assert!(e.contains("declares 20"), "{e}");
    assert_eq!(spool.rows(), 5);
    spool.seal().unwrap();
    assert!(
        spool
            .append(&rows(5, 1, 2))
            .unwrap_err()
            .to_string()
            .contains("sealed")
    );
    drop(spool);
    let spool = spools.open("b").unwrap();
    assert_eq!(spool.rows(), 5);
    assert!(spool.is_sealed());
    assert_eq!(spool.read(0, 5).unwrap(), rows(0, 5, 2));
    spool.unseal().unwrap();
    spool.append(&rows(5, 15, 2)).unwrap();
    assert_eq!(spool.read(0, 20).unwrap(), rows(0, 20, 2));
}

#[test]
fn one_process_at_a_time_and_one_declaration_per_session() {
    let tmp = tempfile::tempdir().unwrap();
    let spools = SpoolDir::new(tmp.path());
    let spool = spools.create_or_open(&session("x", 20, 1), false).unwrap();
    // flock is per open file description: a second open in this process is refused like another
    // process would be.
    let e = format!("{:#}", spools.open("x").unwrap_err());
    assert!(e.contains("busy"), "{e}");
    drop(spool);
    let e = format!(
        "{:#}",
        spools
            .create_or_open(&session("x", 21, 1), false)
            .unwrap_err()
    );
    assert!(e.contains("different declaration"), "{e}");
    assert_eq!(spools.open("x").unwrap().manifest().expected_rows, 20);
    // Asking to finish later turns the flag on.
    let again = spools.create_or_open(&session("x", 20, 1), true).unwrap();
    assert!(again.manifest().finish);
    drop(again);
    assert!(spools.inspect("x").unwrap().finish);
    for bad in ["..", ".", "a/b", ""] {
        assert!(
            spools.create_or_open(&session(bad, 20, 1), false).is_err(),
            "{bad:?}"
        );
    }
    assert!(
        spools
            .open("missing")
            .unwrap_err()
            .to_string()
            .contains("no spool")
    );
}

#[test]
fn compaction_deletes_only_committed_segments_and_never_the_last() {
    let tmp = tempfile::tempdir().unwrap();
    let spools = SpoolDir::new(tmp.path()).with_segment_bytes(90);
    let spool = spools.create_or_open(&session("c", 100, 1), false).unwrap();
    for i in 0..5 {
        spool.append(&rows(i * 10, 10, 1)).unwrap();
    }
    assert_eq!(spool.segment_count(), 5);
    assert_eq!(spool.compact(25).unwrap(), 2); // rows 0..20 gone, 20..30 stays
    assert_eq!(spool.base_row(), 20);
    assert_eq!(spool.read(20, 50).unwrap(), rows(20, 30, 1));
    let e = spool.read(10, 30).unwrap_err().to_string();
    assert!(e.contains("lost rows it acknowledged"), "{e}");
    assert_eq!(spool.compact(1000).unwrap(), 2);
    assert_eq!(spool.segment_count(), 1);
    assert_eq!(spool.base_row(), 40);
    drop(spool);
    let spool = spools.open("c").unwrap();
    assert_eq!((spool.base_row(), spool.rows()), (40, 50));
    spool.append(&rows(50, 10, 1)).unwrap();
    assert_eq!(spool.read(40, 60).unwrap(), rows(40, 20, 1));
}

#[test]
fn the_declaration_survives_in_the_manifest() {
    let tmp = tempfile::tempdir().unwrap();
    let spools = SpoolDir::new(tmp.path());
    let s = session("m", 64, 3)
        .with_metadata("lens", "50mm")
        .with_ground_truth(8, 8, vec![0.25; 64]);
    drop(spools.create_or_open(&s, true).unwrap());
    let spool = spools.open("m").unwrap();
    assert_eq!(spool.request(), &s.to_request());
    assert_eq!(spool.manifest().channels, 3);
    // A damaged declaration is reported, not used.
    drop(spool);
    let pb = spools.session_dir("m").join(SESSION_PB);
    let mut bytes = std::fs::read(&pb).unwrap();
    bytes[5] ^= 0xff;
    std::fs::write(&pb, bytes).unwrap();
    let e = format!("{:#}", spools.open("m").unwrap_err());
    assert!(e.contains("checksum"), "{e}");
}

#[test]
fn default_root_follows_the_environment_conventions() {
    let root = default_root();
    assert!(
        root.ends_with("helmholtz/spool") || root.ends_with("helmholtz-spool"),
        "{root:?}"
    );
}

// ---- camera sessions: f32 and u16 frames, stored as they are ----

fn camera_session(id: &str, count: u64, w: u32, h: u32, format: SampleFormat) -> NewSession {
    let spec: PatternSpec = serde_json::from_str(&format!(
        r#"{{"family":"bernoulli","width":8,"height":8,"count":{count},"seed":3}}"#
    ))
    .unwrap();
    NewSession::camera(id, spec, w, h, format)
}

/// `n` frames of `pixels` values from frame `start`, in `format`.
fn frames(start: u64, n: u64, pixels: usize, format: SampleFormat) -> crate::upload::SampleBuf {
    use crate::upload::SampleBuf;
    let values =
        (start..start + n).flat_map(|r| (0..pixels).map(move |p| (r * 7 + p as u64 * 3) % 60_000));
    match format {
        SampleFormat::F64 => SampleBuf::F64(values.map(|v| v as f64 * 0.5).collect()),
        SampleFormat::F32 => SampleBuf::F32(values.map(|v| v as f32 * 0.25 + 0.125).collect()),
        SampleFormat::U16 => SampleBuf::U16(values.map(|v| v as u16).collect()),
    }
}

#[test]
fn frames_round_trip_in_their_own_format_across_frames_and_segments() {
    for format in [SampleFormat::F32, SampleFormat::U16] {
        let tmp = tempfile::tempdir().unwrap();
        let (w, h) = (6u32, 5u32);
        let px = (w * h) as usize;
        let row_bytes = px * format.bytes();
        // Segments of about 3 appends of 4 frames.
        let spools = SpoolDir::new(tmp.path()).with_segment_bytes((12 * row_bytes) as u64);
        let spool = spools
            .create_or_open(&camera_session("cam", 200, w, h, format), true)
            .unwrap();
        assert_eq!(spool.manifest().channels, 30);
        assert_eq!(spool.manifest().sample(), format);
        assert_eq!(spool.manifest().format, 2);
        for i in 0..10 {
            let f = frames(i * 4, 4, px, format);
            assert_eq!(spool.append_samples(f.as_samples()).unwrap(), (i + 1) * 4);
        }
        assert!(spool.segment_count() >= 3, "{format:?}");
        let all = frames(0, 40, px, format);
        assert_eq!(spool.read_bytes(0, 40).unwrap(), all.as_samples().encode());
        assert_eq!(
            spool.read_bytes(5, 23).unwrap(),
            frames(5, 18, px, format).as_samples().encode()
        );
        let widened: Vec<f64> = (0..all.as_samples().len())
            .map(|i| all.as_samples().get_f64(i))
            .collect();
        assert_eq!(spool.read(0, 40).unwrap(), widened);
        // Not widened on disk: 40 frames of `row_bytes` plus one header per append.
        let on_disk: u64 = segments(spool.dir())
            .iter()
            .map(|p| std::fs::metadata(p).unwrap().len())
            .sum();
        assert_eq!(
            on_disk,
            (40 * row_bytes + 10 * FRAME_HEADER) as u64,
            "{format:?}"
        );
        drop(spool);

        let spool = spools.open("cam").unwrap();
        assert_eq!(spool.rows(), 40);
        assert_eq!(spool.read_bytes(0, 40).unwrap(), all.as_samples().encode());
        let info = spools.inspect("cam").unwrap();
        assert_eq!(
            (info.sample_format, info.channels, info.torn_bytes),
            (format, 30, 0)
        );
        // The wire request declares the camera.
        let camera = spool.request().detector.clone().unwrap().camera.unwrap();
        assert_eq!(
            (camera.width, camera.height, camera.format),
            (w, h, format.to_proto() as i32)
        );
    }
}

#[test]
fn frame_spools_refuse_other_formats_bad_values_and_partial_frames() {
    let tmp = tempfile::tempdir().unwrap();
    let spools = SpoolDir::new(tmp.path());
    let spool = spools
        .create_or_open(&camera_session("f", 10, 4, 4, SampleFormat::F32), false)
        .unwrap();
    let e = spool.append(&[1.0; 16]).unwrap_err().to_string();
    assert!(e.contains("stores f32 values, not f64"), "{e}");
    let e = spool
        .append_samples(Samples::U16(&[1; 16]))
        .unwrap_err()
        .to_string();
    assert!(e.contains("not u16"), "{e}");
    let mut bad = vec![0.5f32; 32];
    bad[21] = f32::INFINITY;
    let e = spool
        .append_samples(Samples::F32(&bad))
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("row 1, channel 5") && e.contains("not finite"),
        "{e}"
    );
    let e = spool
        .append_samples(Samples::F32(&[0.5; 20]))
        .unwrap_err()
        .to_string();
    assert!(e.contains("whole"), "{e}");
    assert_eq!(spool.rows(), 0);
    // A camera layout the server would refuse never makes a spool.
    for (w, h, f) in [
        (257, 256, SampleFormat::U16),
        (0, 4, SampleFormat::F32),
        (4, 4, SampleFormat::F64),
    ] {
        assert!(
            spools
                .create_or_open(&camera_session("g", 10, w, h, f), false)
                .is_err(),
            "{w}x{h} {f:?}"
        );
    }
    assert!(!spools.session_dir("g").join(MANIFEST).exists());
}

#[test]
fn a_torn_frame_tail_is_truncated_and_frames_continue() {
    for format in [SampleFormat::F32, SampleFormat::U16] {
        let tmp = tempfile::tempdir().unwrap();
        let spools = SpoolDir::new(tmp.path());
        let px = 12;
        let dir = spools.session_dir("t");
        {
            let spool = spools
                .create_or_open(&camera_session("t", 50, 4, 3, format), false)
                .unwrap();
            spool
                .append_samples(frames(0, 3, px, format).as_samples())
                .unwrap();
            spool
                .append_samples(frames(3, 2, px, format).as_samples())
                .unwrap();
        }
        let seg = segments(&dir).pop().unwrap();
        let good_len = std::fs::metadata(&seg).unwrap().len();
        let row_bytes = px * format.bytes();
        let damages: Vec<(&str, Damage)> = vec![
            (
                "half a header",
                Box::new(|b: &mut Vec<u8>| b.extend_from_slice(&[9, 0])),
            ),
            (
                "a cut frame",
                Box::new(move |b: &mut Vec<u8>| {
                    b.extend_from_slice(&(row_bytes as u32).to_le_bytes());
                    b.extend_from_slice(&0u32.to_le_bytes());
                    b.extend_from_slice(&5u64.to_le_bytes());
                    b.extend_from_slice(&vec![1; row_bytes / 2]);
                }),
            ),
            (
                "a bad checksum",
                Box::new(move |b: &mut Vec<u8>| {
                    b.extend_from_slice(&(row_bytes as u32).to_le_bytes());
                    b.extend_from_slice(&777u32.to_le_bytes());
                    b.extend_from_slice(&5u64.to_le_bytes());
                    b.extend_from_slice(&vec![1; row_bytes]);
                }),
            ),
            // Not a whole frame of this session's row size (an f64-sized row would not fit).
            (
                "a partial-row length",
                Box::new(move |b: &mut Vec<u8>| {
                    b.extend_from_slice(&(row_bytes as u32 + 2).to_le_bytes());
                    b.extend_from_slice(&0u32.to_le_bytes());
                    b.extend_from_slice(&5u64.to_le_bytes());
                    b.extend_from_slice(&vec![1; row_bytes + 2]);
                }),
            ),
        ];
        for (what, damage) in damages {
            let mut bytes = std::fs::read(&seg).unwrap();
            bytes.truncate(good_len as usize);
            damage(&mut bytes);
            std::fs::write(&seg, &bytes).unwrap();
            let info = spools.inspect("t").unwrap();
            assert_eq!(info.spooled_rows, 5, "{what} {format:?}");
            assert!(info.torn_bytes > 0, "{what} {format:?}");
            let spool = spools.open("t").unwrap();
            assert_eq!(spool.rows(), 5, "{what}");
            assert_eq!(std::fs::metadata(&seg).unwrap().len(), good_len, "{what}");
            spool
                .append_samples(frames(5, 1, px, format).as_samples())
                .unwrap();
            assert_eq!(
                spool.read_bytes(0, 6).unwrap(),
                frames(0, 6, px, format).as_samples().encode(),
                "{what} {format:?}"
            );
            drop(spool);
            let bytes = std::fs::read(&seg).unwrap();
            std::fs::write(&seg, &bytes[..good_len as usize]).unwrap();
        }
    }
}

#[test]
fn an_old_manifest_without_a_sample_format_reads_as_f64() {
    let tmp = tempfile::tempdir().unwrap();
    let spools = SpoolDir::new(tmp.path());
    {
        let spool = spools.create_or_open(&session("old", 40, 2), true).unwrap();
        spool.append(&rows(0, 7, 2)).unwrap();
    }
    // Rewrite the manifest exactly as clients before camera sessions wrote it.
    let dir = spools.session_dir("old");
    let mut manifest: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.join(MANIFEST)).unwrap()).unwrap();
    assert_eq!(manifest["format"], 1, "f64 spools keep layout 1");
    assert_eq!(manifest["sample_format"], "f64");
    manifest.as_object_mut().unwrap().remove("sample_format");
    std::fs::write(
        dir.join(MANIFEST),
        serde_json::to_vec_pretty(&manifest).unwrap(),
    )
    .unwrap();
    let spool = spools.open("old").unwrap();
    assert_eq!(spool.manifest().sample_format, None);
    assert_eq!(spool.manifest().sample(), SampleFormat::F64);
    assert_eq!(spool.read(0, 7).unwrap(), rows(0, 7, 2));
    spool.append(&rows(7, 3, 2)).unwrap();
    assert_eq!(spool.read(0, 10).unwrap(), rows(0, 10, 2));
    assert_eq!(
        spools.inspect("old").unwrap().sample_format,
        SampleFormat::F64
    );
}

#[test]
fn camera_chunks_carry_whole_frames_in_their_own_field_under_the_byte_cap() {
    use crate::upload::{MAX_CHUNK_BYTES, chunk_payload_len, chunk_ranges, read_chunk};
    for (format, w, h) in [
        (SampleFormat::F32, 256u32, 256u32),
        (SampleFormat::U16, 256, 256),
        (SampleFormat::U16, 16, 8),
    ] {
        let tmp = tempfile::tempdir().unwrap();
        let spools = SpoolDir::new(tmp.path());
        let px = (w * h) as usize;
        let n = 40u64;
        let spool = spools
            .create_or_open(&camera_session("c", n, w, h, format), false)
            .unwrap();
        spool
            .append_samples(frames(0, n, px, format).as_samples())
            .unwrap();
        let source = SpoolRows {
            spool: &spool,
            upto: n,
        };
        let row_bytes = px * format.bytes();
        for chunk_rows in [None, Some(1000)] {
            let opts = UploadOptions {
                chunk_rows,
                ..UploadOptions::default()
            };
            let per = opts.rows_per_chunk_of(px, format);
            assert!(
                per * row_bytes <= MAX_CHUNK_BYTES,
                "{format:?} {w}x{h} {chunk_rows:?}"
            );
            let mut covered = 0;
            for (s, e) in chunk_ranges(n, 0, per) {
                let c = read_chunk("c", px as u32, &source, s, e).unwrap();
                let (set, unset) = match format {
                    SampleFormat::F32 => (&c.values_f32le, [&c.values_f64le, &c.values_u16le]),
                    SampleFormat::U16 => (&c.values_u16le, [&c.values_f64le, &c.values_f32le]),
                    SampleFormat::F64 => unreachable!(),
                };
                assert!(unset.iter().all(|u| u.is_empty()), "exactly one payload");
                assert_eq!(set.len(), (e - s) as usize * row_bytes, "whole frames");
                assert_eq!(chunk_payload_len(&c), set.len());
                assert!(set.len() <= MAX_CHUNK_BYTES);
                assert_eq!(c.crc32c, crc32c::crc32c(set));
                assert_eq!((c.start_row, c.channels), (s, px as u32));
                assert_eq!(*set, frames(s, e - s, px, format).as_samples().encode());
                covered += e - s;
            }
            assert_eq!(covered, n);
        }
    }
}

#[test]
fn frame_damage_before_the_last_segment_is_an_error() {
    for format in [SampleFormat::F32, SampleFormat::U16] {
        let tmp = tempfile::tempdir().unwrap();
        let px = 16;
        let spools = SpoolDir::new(tmp.path()).with_segment_bytes((2 * px * format.bytes()) as u64);
        {
            let spool = spools
                .create_or_open(&camera_session("d", 30, 4, 4, format), false)
                .unwrap();
            for i in 0..3 {
                spool
                    .append_samples(frames(i * 2, 2, px, format).as_samples())
                    .unwrap();
            }
            assert_eq!(spool.segment_count(), 3);
        }
        let first = segments(&spools.session_dir("d")).remove(0);
        let mut bytes = std::fs::read(&first).unwrap();
        bytes[FRAME_HEADER + 3] ^= 0x10;
        std::fs::write(&first, &bytes).unwrap();
        let e = format!("{:#}", spools.open("d").unwrap_err());
        assert!(
            e.contains("damaged") && e.contains("not the last"),
            "{format:?}: {e}"
        );
    }
}

#[cfg(unix)]
#[test]
fn the_spool_is_its_owners_only() {
    use std::os::unix::fs::PermissionsExt;
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path().join("spool");
    // An existing root with wide permissions is narrowed.
    std::fs::create_dir_all(&root).unwrap();
    std::fs::set_permissions(&root, std::fs::Permissions::from_mode(0o755)).unwrap();
    let spools = SpoolDir::new(&root);
    let spool = spools
        .create_or_open(&session("perm", 10, 3), false)
        .unwrap();
    spool.append(&[1.0, 2.0, 3.0]).unwrap();
    spool.save_state(&UploadState::default());
    let mode = |p: &std::path::Path| std::fs::metadata(p).unwrap().permissions().mode() & 0o777;
    assert_eq!(mode(&root), 0o700);
    assert_eq!(mode(spool.dir()), 0o700);
    let mut files = 0;
    for entry in std::fs::read_dir(spool.dir()).unwrap() {
        let path = entry.unwrap().path();
        assert_eq!(mode(&path), 0o600, "{}", path.display());
        files += 1;
    }
    assert!(
        files >= 5,
        "manifest, session.pb, lock, a segment, state.json: {files}"
    );
}

#[test]
fn an_empty_spool_starts_where_the_session_continues() {
    let dir = tempfile::tempdir().unwrap();
    let spools = SpoolDir::new(dir.path());
    let spool = spools
        .create_or_open(&session("cont", 10, 2), false)
        .unwrap();
    assert!(spool.is_empty());
    spool.start_at(6).unwrap();
    assert_eq!((spool.base_row(), spool.rows()), (6, 6));
    assert!(spool.start_at(11).is_err(), "past the spec's 10 rows");
    spool.append(&rows(6, 2, 2)).unwrap();
    assert_eq!(spool.read(6, 8).unwrap(), rows(6, 2, 2));
    let err = spool.start_at(0).unwrap_err().to_string();
    assert!(err.contains("its next row is 8"), "{err}");
    drop(spool);
    // Durable: a reopened spool continues at row 8.
    let spool = spools.open("cont").unwrap();
    assert_eq!((spool.base_row(), spool.rows()), (6, 8));
    assert_eq!(
        spool.confirmed_rows(),
        6,
        "rows below the start are on the server"
    );
    spool.save_state(&UploadState {
        confirmed_rows: Some(7),
        ..Default::default()
    });
    assert_eq!(spool.confirmed_rows(), 7);
    spool.save_state(&UploadState {
        confirmed_rows: Some(99),
        ..Default::default()
    });
    assert_eq!(spool.confirmed_rows(), 8, "never past the spooled rows");
}
