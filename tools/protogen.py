"""Generates the Python and mypy stubs of the contracts (``make proto``).

A development tool, not part of the ``baton`` package: it runs in a checkout,
where the ``.proto`` files are, with the dev dependencies (grpcio-tools and
mypy-protobuf, pinned in pyproject.toml). Its settings are the
``[tool.baton.protogen]`` table of the checkout's pyproject.toml: ``root``, the
folder the ``.proto`` files are imported from (``-I``), and ``package``, the
folder under it that holds them. The generated ``*_pb2.py``,
``*_pb2_grpc.py`` and their ``.pyi`` files sit beside the ``.proto`` files and
are never edited by hand: ``make proto`` (``python tools/protogen.py``)
rewrites them, and ``--check`` (run by tests/test_contracts.py) fails when
they are stale.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import tomllib
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

CHECKOUT = Path(__file__).resolve().parents[1]


@dataclass(frozen=True)
class Settings:
    """Where the contracts are: ``root`` (the include path) and ``package`` under it."""

    root: Path
    package: Path

    def proto_files(self) -> list[Path]:
        """The contract files, relative to ``root``."""
        return sorted(p.relative_to(self.root) for p in (self.root / self.package).glob("*.proto"))


def load_settings(pyproject: Path = CHECKOUT / "pyproject.toml") -> Settings:
    """The ``[tool.baton.protogen]`` table of ``pyproject``, paths resolved beside it."""
    with pyproject.open("rb") as f:
        table = tomllib.load(f).get("tool", {}).get("baton", {}).get("protogen")
    if not isinstance(table, dict) or not {"root", "package"} <= table.keys():
        raise SystemExit(
            f"{pyproject}: no [tool.baton.protogen] table with `root` and `package` "
            '(e.g. root = "protos", package = "baton/v1")'
        )
    return Settings(root=pyproject.parent / table["root"], package=Path(table["package"]))


def generate(out_dir: Path, settings: Settings) -> list[Path]:
    """Compiles every contract into ``out_dir``; returns the files written."""
    from grpc_tools import protoc  # dev dependency: only the generator needs it

    include = str(resources.files("grpc_tools") / "_proto")
    scripts = Path(sys.executable).parent  # mypy-protobuf's plugins sit beside python
    args = [
        "grpc_tools.protoc",
        f"--plugin=protoc-gen-mypy={scripts / 'protoc-gen-mypy'}",
        f"--plugin=protoc-gen-mypy_grpc={scripts / 'protoc-gen-mypy_grpc'}",
        f"-I{settings.root}",
        f"-I{include}",
        f"--python_out={out_dir}",
        f"--grpc_python_out={out_dir}",
        f"--mypy_out=quiet:{out_dir}",
        f"--mypy_grpc_out=quiet:{out_dir}",
        *(str(p) for p in settings.proto_files()),
    ]
    if protoc.main(args) != 0:
        raise RuntimeError("protoc failed: " + " ".join(args))
    return sorted(p.relative_to(out_dir) for p in (out_dir / settings.package).glob("*_pb2*"))


def stale_files(settings: Settings) -> list[str]:
    """Generated files that differ from a fresh generation (or are missing, or left over)."""
    root = settings.root
    with tempfile.TemporaryDirectory() as tmp:
        fresh = generate(Path(tmp), settings)
        stale = []
        for rel in fresh:
            current = root / rel
            if not current.exists() or current.read_bytes() != (Path(tmp) / rel).read_bytes():
                stale.append(str(rel))
        known = {str(p) for p in fresh}
        for existing in (root / settings.package).glob("*_pb2*"):
            if str(existing.relative_to(root)) not in known:
                stale.append(str(existing.relative_to(root)))
        return stale


def main(argv: list[str] | None = None) -> int:
    """Regenerates the stubs in place, or with ``--check`` lists stale ones."""
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--check", action="store_true", help="fail if generated code is stale")
    args = parser.parse_args(argv)
    settings = load_settings()
    shown = settings.root.relative_to(CHECKOUT)
    if args.check:
        stale = stale_files(settings)
        for name in stale:
            print(f"stale: {shown}/{name} (run `make proto`)", file=sys.stderr)
        return 1 if stale else 0
    with tempfile.TemporaryDirectory() as tmp:
        for rel in generate(Path(tmp), settings):
            shutil.copyfile(Path(tmp) / rel, settings.root / rel)
            print(f"wrote {shown}/{rel}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
