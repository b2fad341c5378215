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
