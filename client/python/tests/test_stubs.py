"""The committed gRPC stubs are what the .proto gives, and the .proto is the server's."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

from conftest import PACKAGE_ROOT, REPO_ROOT

PROTO = REPO_ROOT / "proto" / "proto" / "helmholtz" / "v1"
COMMITTED = PACKAGE_ROOT / "src" / "helmholtz" / "_proto" / "v1"


def _tool():  # type: ignore[no-untyped-def]
    path = PACKAGE_ROOT / "tools" / "regenerate_stubs.py"
    spec = importlib.util.spec_from_file_location("regenerate_stubs", path)
    assert spec and spec.loader
    module = importlib.util.module_from_spec(spec)
    sys.modules["regenerate_stubs"] = module
    spec.loader.exec_module(module)
    return module


def test_committed_proto_is_the_rust_trees() -> None:
    tool = _tool()
    names = tool.proto_names(PROTO)
    assert names, f"no .proto files in {PROTO}"
    assert tool.proto_names(COMMITTED) == names
    for name in names:
        assert (COMMITTED / name).read_bytes() == (PROTO / name).read_bytes(), (
            f"{name} differs from {PROTO / name}: run tools/regenerate_stubs.py"
        )


def test_regenerating_the_stubs_gives_no_diff(tmp_path: Path) -> None:
    tool = _tool()
    fresh = tool.generate(PROTO, tmp_path)
    generated = tool.generated_names(fresh)
    assert len(generated) == 3 * len(tool.proto_names(PROTO)), generated
    assert tool.generated_names(COMMITTED) == generated
    for name in generated:
        assert (COMMITTED / name).read_bytes() == (fresh / name).read_bytes(), (
            f"{name} is out of date: run tools/regenerate_stubs.py"
        )


def test_installed_package_carries_the_stubs() -> None:
    import helmholtz
    from helmholtz._proto.v1 import acquisition_pb2, acquisition_pb2_grpc

    installed = Path(helmholtz.__file__).parent / "_proto" / "v1"
    for name in ("acquisition.proto", "acquisition_pb2.pyi"):
        assert (installed / name).read_bytes() == (COMMITTED / name).read_bytes()
    assert acquisition_pb2.DESCRIPTOR.package == "helmholtz.v1"
    assert hasattr(acquisition_pb2_grpc, "AcquisitionStub")
    assert (Path(helmholtz.__file__).parent / "py.typed").exists()
