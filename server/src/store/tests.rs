use std::collections::BTreeMap;

use helmholtz_proto::{Family, PatternSpec};

use super::*;

async fn store() -> (tempfile::TempDir, Store) {
    let dir = tempfile::tempdir().unwrap();
    let store = Store::open(dir.path()).await.unwrap();
    (dir, store)
}

fn new_session(id: &str, count: u64) -> NewSession {
    NewSession {
        id: id.into(),
        rig: "bench".into(),
        spec: PatternSpec::new(Family::Bernoulli { fill: 0.5 }, 4, 4, count, 1).unwrap(),
        channels: vec!["a".into(), "b".into()],
        metadata: BTreeMap::from([("lab".into(), "optics".into())]),
        ground_truth: None,
    }
}

fn rows(start: u64, n: u64) -> Vec<f64> {
    (start..start + n).flat_map(|r| [r as f64, -(r as f64)]).collect()
}

#[tokio::test]
async fn create_is_idempotent_and_conflicts_name_the_field() {
    let (_d, s) = store().await;
    let (a, created) = s.create_session(&new_session("s1", 10)).await.unwrap();
    assert!(created);
    let (b, created) = s.create_session(&new_session("s1", 10)).await.unwrap();
    assert!(!created);
    assert_eq!(a, b);
    let err = s.create_session(&new_session("s1", 11)).await.unwrap_err();
    assert!(matches!(err, StoreError::SessionConflict(_, "patterns")), "{err}");
    let mut other_rig = new_session("s1", 10);
    other_rig.rig = "other".into();
    assert!(matches!(s.create_session(&other_rig).await, Err(StoreError::SessionConflict(_, "rig"))));
}

#[tokio::test]
async fn appends_skip_overlap_reject_gaps_and_read_back_exactly() {
    let (_d, s) = store().await;
    s.create_session(&new_session("s", 10)).await.unwrap();
    let out = s.append_rows("s", 0, 2, &rows(0, 4)).await.unwrap();
    assert_eq!(out, AppendOutcome { committed_rows: 4, written: 4, skipped: 0 });
    // Overlap: rows 2..6, of which 2 and 3 are already there.
    let out = s.append_rows("s", 2, 2, &rows(2, 4)).await.unwrap();
    assert_eq!(out, AppendOutcome { committed_rows: 6, written: 2, skipped: 2 });
    // Entirely old.
    let out = s.append_rows("s", 0, 2, &rows(0, 3)).await.unwrap();
    assert_eq!(out, AppendOutcome { committed_rows: 6, written: 0, skipped: 3 });
    // Gap.
    assert!(matches!(s.append_rows("s", 7, 2, &rows(7, 1)).await, Err(StoreError::Gap { committed: 6, start: 7 })));
    // Past the spec's count.
    assert!(matches!(s.append_rows("s", 6, 2, &rows(6, 5)).await, Err(StoreError::PastEnd { end: 11, expected: 10 })));
    assert!(matches!(s.finish_session("s").await, Err(StoreError::Incomplete { committed: 6, .. })));
    s.append_rows("s", 6, 2, &rows(6, 4)).await.unwrap();
    let chunks = s.read_chunks("s", 0, 100).await.unwrap();
    let all: Vec<f64> = chunks.iter().flat_map(|(_, v)| v.clone()).collect();
    assert_eq!(all, rows(0, 10));
    assert_eq!(chunks.iter().map(|c| c.0).collect::<Vec<_>>(), vec![0, 4, 6]);
    // Paged reads continue at chunk boundaries.
    let page = s.read_chunks("s", 4, 1).await.unwrap();
    assert_eq!(page.len(), 1);
    assert_eq!(page[0].0, 4);
    let finished = s.finish_session("s").await.unwrap();
    assert_eq!(finished.state, SessionState::Finished);
    assert_eq!(s.finish_session("s").await.unwrap(), finished);
    assert!(matches!(s.append_rows("nope", 0, 2, &rows(0, 1)).await, Err(StoreError::SessionNotFound(_))));
}

#[tokio::test]
async fn leases_expire_and_fencing_stops_stale_workers() {
    let (_d, s) = store().await;
    s.create_session(&new_session("s", 10)).await.unwrap();
    let r = s.enqueue_reconstruction("s", "gi", "{}", 10, 3).await.unwrap();
    assert_eq!(r.state, "queued");
    let first = s.claim_job("w1", 200).await.unwrap().unwrap();
    assert_eq!((first.id, first.attempt), (r.id, 1));
    // While the lease holds, nobody else gets the job.
    assert!(s.claim_job("w2", 60_000).await.unwrap().is_none());
    tokio::time::sleep(std::time::Duration::from_millis(250)).await;
    // The lease has expired (the worker died or stalled): another worker takes the job over.
    let second = s.claim_job("w2", 60_000).await.unwrap().unwrap();
    assert_eq!((second.id, second.attempt), (r.id, 2));
    // The stale worker can neither heartbeat nor complete.
    assert!(!s.heartbeat(r.id, 1, 60_000, 0.5).await.unwrap());
    let image = StoredImage { channel_index: 0, channel_name: "a".into(), width: 1, height: 1, data: vec![1.0] };
    assert!(!s.complete_reconstruction(r.id, 1, std::slice::from_ref(&image), "{}", 0.1).await.unwrap());
    assert!(s.heartbeat(r.id, 2, 60_000, 0.5).await.unwrap());
    assert!(s.complete_reconstruction(r.id, 2, std::slice::from_ref(&image), "{\"ok\":1}", 0.1).await.unwrap());
    let done = s.reconstruction(r.id).await.unwrap();
    assert_eq!((done.state.as_str(), done.attempt), ("done", 2));
    assert_eq!(s.dual_images(r.id).await.unwrap(), vec![image]);
    assert_eq!(s.latest_done("s").await.unwrap(), Some(r.id));
    assert!(s.claim_job("w3", 60_000).await.unwrap().is_none());
}

#[tokio::test]
async fn failures_retry_then_give_up() {
    let (_d, s) = store().await;
    s.create_session(&new_session("s", 10)).await.unwrap();
    let r = s.enqueue_reconstruction("s", "gi", "{}", 10, 2).await.unwrap();
    let c = s.claim_job("w", 60_000).await.unwrap().unwrap();
    assert!(s.fail_job(r.id, c.attempt, "disk hiccup", true).await.unwrap());
    assert_eq!(s.reconstruction(r.id).await.unwrap().state, "queued");
    // Retries wait a little (run_at in the future), so nothing is claimable right now.
    assert!(s.claim_job("w", 60_000).await.unwrap().is_none());
    let r2 = s.enqueue_reconstruction("s", "dgi", "{}", 10, 1).await.unwrap();
    let c2 = s.claim_job("w", 60_000).await.unwrap().unwrap();
    assert_eq!(c2.id, r2.id);
    assert!(s.fail_job(r2.id, c2.attempt, "unsolvable", false).await.unwrap());
    let failed = s.reconstruction(r2.id).await.unwrap();
    assert_eq!((failed.state.as_str(), failed.last_error.as_deref()), ("failed", Some("unsolvable")));
    assert!(s.cancel_job(r.id).await.unwrap());
    assert_eq!(s.reconstruction(r.id).await.unwrap().state, "cancelled");
}
