use super::*;

#[test]
fn smoke_grid_runs_and_writes_the_report() {
    let cases = Preset::Smoke.cases();
    assert!(cases.iter().any(|c| c.method == "direct") && cases.iter().any(|c| c.method == "dgi"));
    let results = run_cases(&cases, |_, _| {});
    assert_eq!(results.len(), cases.len());
    for m in &results {
        assert!(m.error.is_none(), "{}: {:?}", m.case.label(), m.error);
        assert!(m.seconds.is_finite() && m.seconds >= 0.0);
        assert!(
            m.quality_db().is_finite() || m.quality_db() == f64::INFINITY,
            "{}",
            m.case.label()
        );
    }
    // The complete noise-free Hadamard set is inverted exactly.
    let direct = results.iter().find(|m| m.case.method == "direct").unwrap();
    assert!(direct.psnr_db > 80.0, "direct: {} dB", direct.psnr_db);
    let dir = tempfile::tempdir().unwrap();
    let contention = super::machine::Contention::start().finish();
    report::write_with(dir.path(), "smoke", 1, &contention, &results).unwrap();
    let md = std::fs::read_to_string(dir.path().join("benchmarks-smoke.md")).unwrap();
    assert!(md.contains("| shapes |") && md.contains(".svg"));
    // The header says how busy the machine was (steal share from /proc/stat where it exists).
    assert!(md.contains("load average (1, 5, 15 min)"), "{md}");
    assert!(
        md.contains("taken by the hypervisor") || md.contains("steal time unknown"),
        "{md}"
    );
    let json: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(dir.path().join("benchmarks-smoke.json")).unwrap(),
    )
    .unwrap();
    assert_eq!(json["results"].as_array().unwrap().len(), results.len());
}

#[test]
fn noisy_preset_runs_and_reports_against_the_targets_and_the_truth() {
    let dir = tempfile::tempdir().unwrap();
    let opts = noisy::Options {
        out: dir.path().to_path_buf(),
        scenes: vec!["shapes".into()],
        families: vec!["hadamard".into()],
        noises: vec![Noise::Snr30],
        size: 32,
        ratio: 0.25,
        oracle: true,
    };
    let results = noisy::run(&opts).unwrap();
    assert_eq!(results.len(), 1);
    let r = &results[0];
    assert!(r.auto.error.is_none() && r.auto.psnr_db.is_finite());
    // The noise put in is known, and auto estimated it from the pair sums.
    assert!(r.true_sigma > 0.0);
    let est = r.auto_choice["noise_estimate"]["sigma"].as_f64().unwrap();
    assert!(
        (est / r.true_sigma - 1.0).abs() < 0.3,
        "{est} vs {}",
        r.true_sigma
    );
    // The oracle swept both models over the whole grid.
    assert_eq!(r.oracle.len(), 2);
    assert!(
        r.oracle
            .iter()
            .all(|s| s.points.len() == noisy::ORACLE_FRACTIONS.len())
    );
    let md = std::fs::read_to_string(dir.path().join("benchmarks-noisy.md")).unwrap();
    for want in [
        "## Summary against the targets",
        "| 30 dB | 1 |",
        "## Calibration",
        "| shapes | hadamard | 30 dB |",
    ] {
        assert!(md.contains(want), "{want:?} missing from:\n{md}");
    }
    let json: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(dir.path().join("benchmarks-noisy.json")).unwrap(),
    )
    .unwrap();
    assert_eq!(json["problems"].as_array().unwrap().len(), 1);
}

#[test]
fn env_flags_are_off_when_unset_empty_or_zero() {
    assert!(!crate::flag_is_on(None));
    for (value, on) in [
        ("", false),
        ("0", false),
        ("no", false),
        ("false", false),
        ("1", true),
        ("yes", true),
    ] {
        assert_eq!(crate::flag_is_on(Some(value)), on, "{value:?}");
    }
}

#[test]
fn the_single_frame_haar_oracle_splits_blocks_only_below_split_blocks_and_finds_the_energy() {
    use helmholtz_proto::HaarFunction;
    use helmholtz_recon::linop::LinearOperator as _;
    use helmholtz_recon::transforms::wavelet::Wavelet2d;
    // A 16x16 scene dark but for one bright pixel at (13, 2): its energy lies in the details of
    // the blocks containing it, one block per scale.
    let w = 16u32;
    let k = (w * w) as usize;
    let mut t = vec![0.0; k];
    t[2 * w as usize + 13] = 1.0;
    let mut c = vec![0.0; k];
    Wavelet2d::haar(w as usize, w as usize).apply(&t, &mut c);
    let block_of = |n: u32| {
        let f = HaarFunction::new(w, n);
        (f.scale, f.x0, f.y0)
    };
    // The whole basis in the order of the rule: every index once, index 0 first, and each
    // detail only after all three details of the block containing its block (the parent block).
    let all = adaptive::haar_block_greedy(&c, w, k);
    assert_eq!(all.len(), k);
    assert_eq!(all[0], 0);
    let mut seen = std::collections::HashSet::new();
    let mut details_taken: std::collections::HashMap<(u32, u32, u32), usize> = Default::default();
    for &n in &all {
        assert!(seen.insert(n), "index {n} twice");
        if n == 0 {
            continue;
        }
        let (s, x0, y0) = block_of(n);
        if s < w.trailing_zeros() {
            let side = 1u32 << (s + 1);
            let parent = (s + 1, x0 / side * side, y0 / side * side);
            assert_eq!(
                details_taken.get(&parent).copied().unwrap_or(0),
                3,
                "index {n} (block {:?}) before its parent block {parent:?} was split",
                (s, x0, y0)
            );
        }
        *details_taken.entry((s, x0, y0)).or_default() += 1;
    }
    // With 1 + 3 * 4 coefficients (four splits: one block per scale down to the 2x2 one) the
    // rule splits exactly the blocks containing the pixel, so it holds all the scene's energy.
    let chosen = adaptive::haar_block_greedy(&c, w, 13);
    assert_eq!(chosen.len(), 13);
    for &n in &chosen[1..] {
        let (s, x0, y0) = block_of(n);
        let side = 1u32 << s;
        assert!(
            (x0..x0 + side).contains(&13) && (y0..y0 + side).contains(&2),
            "index {n}: block {:?} does not hold the pixel",
            (s, x0, y0)
        );
    }
    let kept: f64 = chosen.iter().map(|&n| c[n as usize].powi(2)).sum();
    assert!((kept - 1.0).abs() < 1e-12, "energy kept {kept}");
}
