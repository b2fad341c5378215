//! The Python package (`client/python`, importable as `helmholtz`): its own pytest suite against
//! the real `helmholtz-server` binary, run from `cargo test`.
//!
//! 1. A venv under the cargo target directory (`target/python-venv`), made with `python3 -m
//!    venv` and reused while its marker file records the same requirements (the pins below,
//!    the package's pyproject.toml and the interpreter's version); made again otherwise.
//! 2. The package installed into it with pip from `client/python` (a real, non-editable
//!    install, so the packaging is tested too; offline once the venv exists).
//! 3. pytest run on `client/python/tests` with `HELMHOLTZ_SERVER_BIN` = this build's server
//!    and, on the PostgreSQL backend (`HELMHOLTZ_TEST_BACKEND=postgres`), a fresh database of
//!    the harness (`HELMHOLTZ_PYTEST_DATABASE_URL`).
//!
//! Without python3, its venv module or pip this test fails, saying how to provide them; it
//! never skips. The first run needs network to PyPI (pytest, grpcio-tools, hatchling, and the
//! package's grpcio, protobuf and numpy).

use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::time::Instant;

use helmholtz_tests::{Backend, backend, binary, pg::TestDatabase};

/// What the venv holds besides the package: the test runner, the stub generator the stubs test
/// runs, and the build backend (so reinstalling the package needs no network).
const REQUIREMENTS: &[&str] = &["pytest>=9,<10", "grpcio-tools==1.85.1", "hatchling>=1.25"];

const HOW: &str = "the Python package's tests need python3 (3.10 or later) with the venv module \
and pip (Debian/Ubuntu: `apt-get install python3 python3-venv python3-pip`), and network to \
PyPI the first time; set HELMHOLTZ_PYTHON to use another interpreter";

fn repo_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .expect("tests/ is inside the repository")
        .to_path_buf()
}

/// The cargo target directory: the server binary is `<target>/<profile>/helmholtz-server`.
fn target_dir() -> PathBuf {
    binary("helmholtz-server")
        .parent()
        .and_then(Path::parent)
        .expect("target/<profile>/helmholtz-server")
        .to_path_buf()
}

fn run(what: &str, command: &mut Command) -> Output {
    let out = command
        .output()
        .unwrap_or_else(|e| panic!("{what}: cannot run {command:?} ({e}); {HOW}"));
    if !out.status.success() {
        panic!(
            "{what} failed ({}):\n{}\n{}\n{HOW}",
            out.status,
            String::from_utf8_lossy(&out.stdout),
            String::from_utf8_lossy(&out.stderr)
        );
    }
    out
}

/// The venv, made (or made again) unless its marker records these requirements.
fn venv(python: &str, package: &Path) -> PathBuf {
    let dir = target_dir().join("python-venv");
    let version = run(
        "python3 --version",
        Command::new(python).args(["-c", "import sys; print(sys.version)"]),
    );
    let pyproject = std::fs::read_to_string(package.join("pyproject.toml"))
        .expect("client/python/pyproject.toml");
    let marker_text = format!(
        "python {}requirements {}\n{pyproject}",
        String::from_utf8_lossy(&version.stdout),
        REQUIREMENTS.join(" ")
    );
    let marker = dir.join("helmholtz-requirements.txt");
    let bin = dir.join("bin");
    if std::fs::read_to_string(&marker).ok().as_deref() == Some(marker_text.as_str())
        && bin.join("python").exists()
    {
        return dir;
    }
    let _ = std::fs::remove_dir_all(&dir);
    run(
        "python3 -m venv",
        Command::new(python).arg("-m").arg("venv").arg(&dir),
    );
    // The package with its dependencies (grpcio, protobuf, numpy) and the test requirements.
    run(
        "pip install (first run: from PyPI)",
        Command::new(bin.join("python"))
            .args(["-m", "pip", "install", "--disable-pip-version-check", "-q"])
            .arg(package)
            .args(REQUIREMENTS),
    );
    std::fs::write(&marker, marker_text).expect("writing the venv's marker");
    dir
}

#[test]
fn the_python_package_passes_its_pytest_suite_against_the_real_server() {
    let started = Instant::now();
    let python = std::env::var("HELMHOLTZ_PYTHON").unwrap_or_else(|_| "python3".into());
    let root = repo_root();
    let package = root.join("client").join("python");
    let venv = venv(&python, &package);
    let venv_python = venv.join("bin").join("python");
    let made = started.elapsed();

    // This tree's package, installed for real (a wheel built by hatchling), every run.
    run(
        "pip install client/python",
        Command::new(&venv_python)
            .args([
                "-m",
                "pip",
                "install",
                "--disable-pip-version-check",
                "-q",
                "--no-deps",
                "--no-index",
                "--no-build-isolation",
                "--force-reinstall",
            ])
            .arg(&package),
    );
    let installed = started.elapsed();

    // On PostgreSQL: a fresh database for the suite's server, dropped when this test ends.
    let database = (backend() == Backend::Postgres).then(TestDatabase::create);
    let mut pytest = Command::new(&venv_python);
    pytest
        .args(["-m", "pytest", "-p", "no:cacheprovider", "-q", "tests"])
        .current_dir(&package)
        .env("HELMHOLTZ_SERVER_BIN", binary("helmholtz-server"))
        .env("HELMHOLTZ_PYTEST_REQUIRE_INSTALLED", "1")
        .env("PYTHONDONTWRITEBYTECODE", "1")
        .env_remove("HELMHOLTZ_PYTEST_DATABASE_URL")
        .env_remove("HELMHOLTZ_TOKEN")
        .env_remove("HELMHOLTZ_SERVER");
    if let Some(db) = &database {
        pytest.env("HELMHOLTZ_PYTEST_DATABASE_URL", db.url());
    }
    let out = pytest
        .output()
        .unwrap_or_else(|e| panic!("running pytest in {}: {e}", venv.display()));
    let stdout = String::from_utf8_lossy(&out.stdout);
    let stderr = String::from_utf8_lossy(&out.stderr);
    println!("{stdout}\n{stderr}");
    println!(
        "python tests on {:?}: venv {:.1} s, install {:.1} s, pytest {:.1} s",
        backend(),
        made.as_secs_f64(),
        (installed - made).as_secs_f64(),
        (started.elapsed() - installed).as_secs_f64()
    );
    assert!(
        out.status.success(),
        "pytest failed ({}):\n{stdout}\n{stderr}",
        out.status
    );
    assert!(
        stdout.contains(" passed") && !stdout.contains(" failed"),
        "pytest ran no tests or reported failures:\n{stdout}"
    );
    // Inside this wrapper every test runs: a skip would hide one silently.
    assert!(
        !stdout.contains("skipped"),
        "pytest skipped tests under cargo test:\n{stdout}"
    );
}
