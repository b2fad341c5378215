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
