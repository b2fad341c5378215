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
