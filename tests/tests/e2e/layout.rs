//! The house's layout, checked on the real dependency graph (`cargo tree`, normal dependencies,
//! each crate's own feature resolution): the numerics know nothing of async, SQL or HTTP; the
//! service does not link the edge client, its CLI or the simulator; the benchmarks measure the
//! numerics without the service. See docs/design.md.

use std::collections::BTreeSet;
use std::process::Command;

/// Every package `package` links (transitively, normal dependencies), by name.
fn linked(package: &str) -> BTreeSet<String> {
    let root = concat!(env!("CARGO_MANIFEST_DIR"), "/..");
    let out = Command::new(env!("CARGO"))
        .current_dir(root)
        .args(["tree", "--locked", "-e", "normal", "--prefix", "none"])
        .args(["--format", "{p}", "-p", package])
        .output()
        .expect("running cargo tree");
    assert!(
        out.status.success(),
        "cargo tree -p {package} failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let names: BTreeSet<String> = String::from_utf8(out.stdout)
        .unwrap()
        .lines()
        .filter_map(|l| l.split_whitespace().next().map(str::to_string))
        .collect();
    assert!(
        names.contains(package),
        "{package} not in its own tree: {names:?}"
    );
    names
}

fn assert_links_none(package: &str, forbidden: &[&str]) {
    let names = linked(package);
    let found: Vec<&&str> = forbidden.iter().filter(|f| names.contains(**f)).collect();
    assert!(
        found.is_empty(),
        "{package} must not depend on {found:?} (it links: {names:?})"
    );
}

const ASYNC_SQL_HTTP: [&str; 10] = [
    "tokio", "sqlx", "axum", "tonic", "hyper", "h2", "tower", "reqwest", "futures", "mio",
];

#[test]
fn the_numerics_know_nothing_of_async_sql_or_http() {
    assert_links_none("helmholtz-recon", &ASYNC_SQL_HTTP);
    assert_links_none(
        "helmholtz-recon",
        &[
            "helmholtz-server",
            "helmholtz-client",
            "helmholtz-sim",
            "indicatif",
        ],
    );
    // Without its `grpc` feature the contract is messages, patterns and codecs only.
    assert_links_none("helmholtz-proto", &ASYNC_SQL_HTTP);
    assert_links_none("helmholtz-sim", &ASYNC_SQL_HTTP);
}

#[test]
fn the_service_does_not_link_the_client_or_the_simulator() {
    assert_links_none(
        "helmholtz-server",
        &[
            "helmholtz-client",
            "helmholtz-sim",
            "helmholtz-bench",
            "helmholtz-demo",
            "reqwest",
            "indicatif",
        ],
    );
    // The check sees real edges: the service does link the numerics and tokio.
    let server = linked("helmholtz-server");
    assert!(server.contains("helmholtz-recon") && server.contains("tokio"));
}

#[test]
fn the_benchmarks_measure_the_numerics_without_the_service() {
    assert_links_none(
        "helmholtz-bench",
        &["helmholtz-server", "helmholtz-client", "tokio", "sqlx"],
    );
    let bench = linked("helmholtz-bench");
    assert!(bench.contains("helmholtz-recon") && bench.contains("helmholtz-sim"));
}

#[test]
fn one_crypto_provider_and_no_second_build_of_the_databases() {
    // ring is the one TLS crypto provider (aws-lc would be a second, built from C), and the
    // migrations are embedded without sqlx's macros (which build SQLite and the PostgreSQL
    // driver again for the compiler). Build and dev dependencies included: that is where a macro's
    // second build would show.
    let root = concat!(env!("CARGO_MANIFEST_DIR"), "/..");
    let out = Command::new(env!("CARGO"))
        .current_dir(root)
        .args(["tree", "--locked", "--workspace", "-e", "normal,build,dev"])
        .args(["--prefix", "none", "--format", "{p}"])
        .output()
        .expect("running cargo tree");
    assert!(
        out.status.success(),
        "cargo tree failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let names: BTreeSet<String> = String::from_utf8(out.stdout)
        .unwrap()
        .lines()
        .filter_map(|l| l.split_whitespace().next().map(str::to_string))
        .collect();
    for forbidden in ["aws-lc-rs", "aws-lc-sys", "sqlx-macros", "sqlx-macros-core"] {
        assert!(
            !names.contains(forbidden),
            "the workspace links {forbidden}"
        );
    }
    assert!(names.contains("ring") && names.contains("libsqlite3-sys"));
}
