"""Generates the Python and mypy stubs of the contracts in ``protos/``.

The generated ``*_pb2.py``, ``*_pb2_grpc.py`` and their ``.pyi`` files sit
beside the ``.proto`` files (package ``baton.v1``) and are never edited by
hand: ``make proto`` rewrites them, and a test fails when they are stale.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
from importlib import resources
from pathlib import Path

PROTO_ROOT = Path(__file__).resolve().parents[2] / "protos"
PROTO_PACKAGE = Path("baton") / "v1"


def proto_files(root: Path = PROTO_ROOT) -> list[Path]:
    """The contract files, relative to ``root``."""
    return sorted(p.relative_to(root) for p in (root / PROTO_PACKAGE).glob("*.proto"))


def generate(out_dir: Path, root: Path = PROTO_ROOT) -> list[Path]:
    """Compiles every contract into ``out_dir``; returns the files written."""
    from grpc_tools import protoc  # dev dependency: only the generator needs it

    include = str(resources.files("grpc_tools") / "_proto")
    scripts = Path(sys.executable).parent  # mypy-protobuf's plugins sit beside python
    args = [
        "grpc_tools.protoc",
        f"--plugin=protoc-gen-mypy={scripts / 'protoc-gen-mypy'}",
        f"--plugin=protoc-gen-mypy_grpc={scripts / 'protoc-gen-mypy_grpc'}",
        f"-I{root}",
        f"-I{include}",
        f"--python_out={out_dir}",
        f"--grpc_python_out={out_dir}",
        f"--mypy_out=quiet:{out_dir}",
        f"--mypy_grpc_out=quiet:{out_dir}",
        *(str(p) for p in proto_files(root)),
    ]
    if protoc.main(args) != 0:
        raise RuntimeError("protoc failed: " + " ".join(args))
    return sorted(p.relative_to(out_dir) for p in (out_dir / PROTO_PACKAGE).glob("*_pb2*"))


def stale_files(root: Path = PROTO_ROOT) -> list[str]:
    """Generated files that differ from a fresh generation (or are missing)."""
    with tempfile.TemporaryDirectory() as tmp:
        fresh = generate(Path(tmp), root)
        stale = []
        for rel in fresh:
            current = root / rel
            if not current.exists() or current.read_bytes() != (Path(tmp) / rel).read_bytes():
                stale.append(str(rel))
        known = {str(p) for p in fresh}
        for existing in (root / PROTO_PACKAGE).glob("*_pb2*"):
            if str(existing.relative_to(root)) not in known:
                stale.append(str(existing.relative_to(root)))
        return stale


def main(argv: list[str] | None = None) -> int:
    """Regenerates the stubs in place, or with ``--check`` lists stale ones."""
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--check", action="store_true", help="fail if generated code is stale")
    args = parser.parse_args(argv)
    if args.check:
        stale = stale_files()
        for name in stale:
            print(f"stale: protos/{name} (run `make proto`)", file=sys.stderr)
        return 1 if stale else 0
    with tempfile.TemporaryDirectory() as tmp:
        for rel in generate(Path(tmp)):
            shutil.copyfile(Path(tmp) / rel, PROTO_ROOT / rel)
            print(f"wrote protos/{rel}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
