"""The README's commands run as written, and its links into the repository lead somewhere.

Every line of a ```sh block in README.md is a command a newcomer types: a
``make`` target is checked with ``make -n`` (what it would run), a ``baton``
command is parsed by baton's own parser as written (so an option the README
shows exists) and its program's ``--help`` runs. Every relative link, and
every ``#anchor`` in one, names a file and a heading that exist.
"""

from __future__ import annotations

import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

from baton.cli import build_parser

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"


def shell_commands(markdown: str) -> list[list[str]]:
    """The commands of the ```sh blocks, one argv per line, comments dropped."""
    commands = []
    for block in re.findall(r"^```sh\n(.*?)^```", markdown, flags=re.M | re.S):
        for line in block.splitlines():
            argv = shlex.split(line, comments=True)
            if argv:
                commands.append(argv)
    return commands


def links(markdown: str) -> list[str]:
    """The targets of the Markdown links that are not URLs."""
    targets = re.findall(r"\]\(([^)\s]+)\)", markdown)
    return [t for t in targets if not re.match(r"[a-z]+:", t)]


def anchor(heading: str) -> str:
    """GitHub's anchor of a Markdown heading."""
    text = heading.strip().lower()
    text = re.sub(r"[^\w\- ]", "", text)
    return text.replace(" ", "-")


def anchors(markdown: str) -> set[str]:
    return {anchor(h) for h in re.findall(r"^#+ (.*)$", markdown, flags=re.M)}


COMMANDS = shell_commands(README.read_text())


def test_the_readme_shows_the_two_commands() -> None:
    assert ["make", "demo"] in [c[:2] for c in COMMANDS]
    assert ["make", "test"] in [c[:2] for c in COMMANDS]


def test_ci_runs_the_readmes_test_command() -> None:
    assert re.search(r"^make test\b", (ROOT / ".ci/run").read_text(), flags=re.M)


@pytest.mark.parametrize("argv", COMMANDS, ids=[" ".join(c) for c in COMMANDS])
def test_a_readme_command_runs_as_written(argv: list[str]) -> None:
    if argv[0] == "make":
        done = subprocess.run(
            ["make", "-n", *argv[1:]], cwd=ROOT, capture_output=True, text=True, timeout=60
        )
        assert done.returncode == 0, done.stderr
        return
    assert argv[0] in {".venv/bin/baton", "baton"}, f"the README runs {argv[0]}: check it here"
    args = argv[1:]
    try:
        parsed = build_parser().parse_args(args)
    except SystemExit as exc:  # argparse's error
        pytest.fail(f"baton {' '.join(args)}: {exc}")
    program = [parsed.program]
    if getattr(parsed, "action", None) and parsed.program == "bench":
        program.append(parsed.action)
    done = subprocess.run(
        [sys.executable, "-m", "baton.cli", *program, "--help"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 0, done.stderr


def test_every_link_in_the_readme_leads_somewhere() -> None:
    missing = []
    for target in links(README.read_text()):
        path, _, fragment = target.partition("#")
        file = ROOT / path
        if not file.exists():
            missing.append(target)
        elif fragment and fragment not in anchors(file.read_text()):
            missing.append(target)
    assert not missing, f"README.md links to what is not there: {missing}"


def test_the_docs_map_covers_docs() -> None:
    """Every page in docs/ is in the README's map."""
    shown = {Path(t).name for t in links(README.read_text()) if t.startswith("docs/")}
    pages = {p.name for p in (ROOT / "docs").glob("*.md")}
    assert pages <= shown, f"docs/ pages the README does not map: {sorted(pages - shown)}"


@pytest.mark.parametrize("page", sorted((ROOT / "docs").glob("*.md")), ids=lambda p: p.name)
def test_links_between_the_docs_lead_somewhere(page: Path) -> None:
    missing = []
    for target in links(page.read_text()):
        path, _, fragment = target.partition("#")
        file = (page.parent / path) if path else page
        if not file.exists():
            missing.append(target)
        elif fragment and file.suffix == ".md" and fragment not in anchors(file.read_text()):
            missing.append(target)
    assert not missing, f"{page.name} links to what is not there: {missing}"


def test_the_readmes_mission_loads() -> None:
    """The mission shown imports what the SDK has and defines ``mission``."""
    (source,) = re.findall(r"^```python\n(.*?)^```", README.read_text(), flags=re.M | re.S)
    scope: dict[str, object] = {}
    exec(compile(source, "README.md", "exec"), scope)
    assert callable(scope["mission"])


def test_the_excerpt_of_make_test_shows_the_commands_it_runs() -> None:
    """The README's excerpt of `make test`'s output names the commands the Makefile
    runs, in order (``make -n test``)."""
    blocks = re.findall(r"^```text\n(.*?)^```", README.read_text(), flags=re.M | re.S)
    (excerpt,) = [b for b in blocks if ".venv/bin/mypy" in b]
    shown = [line for line in excerpt.splitlines() if line.startswith(".venv/bin/")]
    done = subprocess.run(["make", "-n", "test"], cwd=ROOT, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    run = [line.strip() for line in done.stdout.splitlines() if line.startswith(".venv/bin/")]
    # The test recipe's own commands come last (a stale .venv's set-up may come first).
    assert len(shown) == 4 and run[-len(shown) :] == shown, run
