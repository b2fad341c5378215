#!/usr/bin/env python3
"""Regenerates the committed gRPC stubs of the Python package from the Rust tree's .proto files.

    python client/python/tools/regenerate_stubs.py          # copy the .proto files, regenerate
    python client/python/tools/regenerate_stubs.py --check  # exit 1 if anything would change

1. Copies ``proto/proto/helmholtz/v1/*.proto`` (the contract the server is built from) to
   ``client/python/src/helmholtz/_proto/v1/``.
2. Runs ``python -m grpc_tools.protoc`` with ``client/python/src`` as the include root, so the
   generated modules import each other package-absolutely (``from helmholtz._proto.v1 import
   acquisition_pb2``): ``*_pb2.py``, ``*_pb2.pyi`` and ``*_pb2_grpc.py`` beside the copies.

Needs grpcio-tools (a test-only dependency: ``pip install 'grpcio-tools==1.85.1'``); the
pinned version is the one the committed stubs were made with (their runtime checks then require
grpcio >= 1.85.1 and protobuf >= the gencode version stated in the _pb2.py header).
The package's test ``tests/test_stubs.py`` runs :func:`generate` into a temporary directory and
requires the result to equal the committed files.
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

PACKAGE_ROOT = Path(__file__).resolve().parents[1]  # client/python
REPO_ROOT = PACKAGE_ROOT.parents[1]
RUST_PROTO_DIR = REPO_ROOT / "proto" / "proto" / "helmholtz" / "v1"
SRC = PACKAGE_ROOT / "src"
PROTO_SUBDIR = Path("helmholtz") / "_proto" / "v1"
GENERATED_SUFFIXES = ("_pb2.py", "_pb2.pyi", "_pb2_grpc.py")


def proto_names(directory: Path) -> list[str]:
    """The .proto file names in `directory`, sorted."""
    return sorted(p.name for p in directory.glob("*.proto"))


def generated_names(directory: Path) -> list[str]:
    """The generated stub file names in `directory`, sorted."""
    return sorted(
        p.name for p in directory.iterdir() if p.name.endswith(GENERATED_SUFFIXES)
    )


def generate(proto_dir: Path, out_root: Path) -> Path:
    """Copies the .proto files of `proto_dir` to `out_root`/helmholtz/_proto/v1 and generates
    the stubs there (with `out_root` as include root); returns that directory."""
    target = out_root / PROTO_SUBDIR
    target.mkdir(parents=True, exist_ok=True)
    names = proto_names(proto_dir)
    if not names:
        raise SystemExit(f"no .proto files in {proto_dir}")
    for name in names:
        if (proto_dir / name).resolve() != (target / name).resolve():
            shutil.copyfile(proto_dir / name, target / name)
    cmd = [
        sys.executable,
        "-m",
        "grpc_tools.protoc",
        f"-I{out_root}",
        f"--python_out={out_root}",
        f"--pyi_out={out_root}",
        f"--grpc_python_out={out_root}",
        *[str(PROTO_SUBDIR / name) for name in names],
    ]
    subprocess.run(cmd, check=True, cwd=out_root)
    return target


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[1])
    ap.add_argument("--check", action="store_true", help="compare only; exit 1 on a difference")
    args = ap.parse_args()
    committed = SRC / PROTO_SUBDIR
    if not args.check:
        for stale in generated_names(committed):
            (committed / stale).unlink()
        for stale in proto_names(committed):
            (committed / stale).unlink()
        generate(RUST_PROTO_DIR, SRC)
        print(f"regenerated {', '.join(generated_names(committed))} in {committed}")
        return 0
    with tempfile.TemporaryDirectory() as tmp:
        fresh = generate(RUST_PROTO_DIR, Path(tmp))
        names = proto_names(fresh) + generated_names(fresh)
        differ = [
            n
            for n in names
            if not (committed / n).exists() or (committed / n).read_bytes() != (fresh / n).read_bytes()
        ]
        extra = set(proto_names(committed) + generated_names(committed)) - set(names)
        if differ or extra:
            print(f"stubs out of date: {sorted(differ) + sorted(extra)}; run {__file__}", file=sys.stderr)
            return 1
    print("stubs up to date")
    return 0


if __name__ == "__main__":
    sys.exit(main())
