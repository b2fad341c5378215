"""The README's walkthrough and the example script run as written against the real server."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from conftest import PACKAGE_ROOT


def test_the_readme_walkthrough_runs_as_written(server, monkeypatch, capsys) -> None:  # type: ignore[no-untyped-def]
    text = (PACKAGE_ROOT / "README.md").read_text()
    blocks = re.findall(r"```python\n(.*?)```", text, flags=re.S)
    assert len(blocks) >= 5, "the walkthrough's code blocks are missing"
    monkeypatch.setenv("HELMHOLTZ_SERVER", server.address)
    monkeypatch.setenv("HELMHOLTZ_TOKEN", server.token)
    ns: dict = {}
    for block in blocks:
        exec(compile(block, "README.md", "exec"), ns)  # noqa: S102 - our own documentation
    # What the walkthrough says it gets.
    assert ns["session"].expected_rows == 512
    assert (ns["report"]["details"]["auto"][0]["model"]) == "direct"
    assert float(np.abs(ns["image"] - ns["scene"]).max()) < 1e-6
    T, light = ns["T"], ns["light"]
    want = T.T @ light.reshape(-1)
    assert float(np.abs(ns["relit"].reshape(-1) - want).max() / ns["relit"].max()) < 1e-5
    assert np.array_equal(ns["stripe"], ns["relit"])
    assert ns["predicted"].shape == (8, 8)
    assert "400 light.radius" in capsys.readouterr().out
    run, scene = ns["run"], ns["scene"]
    assert (run.reason, run.rows, run.batches) == ("target_error", 224, 7), run
    assert run.indices == ns["client"].adaptive_sequence("walkthrough-adaptive-1")["indices"]
    error = np.linalg.norm(ns["adaptive_image"] - scene) / np.linalg.norm(scene)
    # Within the target asked for: the planner's (measured) estimate does not read below the
    # truth here. (The prediction-only estimate of sessions stored before 2026-11-29 stopped this
    # session at 0.02 with 0.024.)
    assert error < 0.03 and run.estimated_error >= error, (error, run.estimated_error)
    print(f"adaptive walkthrough: error {error:.4f}, estimated {run.estimated_error:.4f}")
    ns["client"].close()


def test_the_example_script_runs(server, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    out = tmp_path / "dual.npy"
    env = {k: v for k, v in os.environ.items() if not k.startswith("HELMHOLTZ_")}
    result = subprocess.run(
        [sys.executable, str(PACKAGE_ROOT / "examples" / "ghost_imaging.py"),
         "--server", server.address, "--token", server.token, "--side", "8", "--count", "200",
         "--out", str(out)],
        capture_output=True, text=True, timeout=120, env=env,
    )
    assert result.returncode == 0, result.stdout + result.stderr
    assert "auto chose" in result.stdout and "saved to" in result.stdout, result.stdout
    image = np.load(out)
    assert image.shape == (8, 8) and image.dtype == np.float32


def test_the_package_under_test_is_the_installed_one() -> None:
    if not os.environ.get("HELMHOLTZ_PYTEST_REQUIRE_INSTALLED"):
        pytest.skip("run from a checkout (the cargo wrapper sets HELMHOLTZ_PYTEST_REQUIRE_INSTALLED)")
    import helmholtz

    where = Path(helmholtz.__file__).resolve()
    assert "site-packages" in where.parts, where
    assert PACKAGE_ROOT not in where.parents, f"imported from the source tree: {where}"
