"""The `baton` command: every program is there, documented, and fails clearly."""

from __future__ import annotations

import argparse
import socket
import subprocess
import sys

import pytest

from baton.cli import build_parser

PROGRAMS = ["sim-vehicle", "drone", "controller", "link", "testbed", "fleet", "bench"]


def baton(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "baton.cli", *args], capture_output=True, text=True, timeout=60
    )


def test_every_program_is_listed() -> None:
    listed = baton("--help").stdout
    for program in PROGRAMS:
        assert program in listed


@pytest.mark.parametrize("program", PROGRAMS)
def test_every_option_has_help(program: str) -> None:
    result = baton(program, "--help")
    assert result.returncode == 0, result.stderr
    subparsers = next(
        a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction)
    )
    assert_documented(subparsers.choices[program], f"baton {program}")


def test_a_subcommand_that_does_not_import_is_a_clear_error_not_a_missing_command(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A broken install says which program's module failed and why, instead of
    leaving that subcommand out of `baton --help`."""
    import baton.cli

    monkeypatch.setattr(baton.cli, "PROGRAMS", {**baton.cli.PROGRAMS, "absent": "baton.absent.cli"})
    with pytest.raises(SystemExit) as exited:
        build_parser()
    message = str(exited.value.code)
    assert "baton.absent.cli" in message and "No module named 'baton.absent'" in message
    assert "reinstall" in message


def test_a_program_loads_its_own_modules_and_not_the_others() -> None:
    """A part the testbed starts (``baton link ...``) imports its program's module
    only; ``baton --help`` and a word that names no program load every one, to list
    them or to refuse the word with the list."""
    from baton.cli import PROGRAMS, program_named

    assert program_named(["--log-level", "warning", "link", "--listen", "x"]) == "link"
    assert program_named(["--die-with-parent", "7", "controller", "--help"]) == "controller"
    assert program_named(["--help"]) is None and program_named(["lnk"]) is None
    (programs,) = [a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction)]
    assert set(programs.choices) == set(PROGRAMS), "every program a module registers is named"
    others = [m for name, m in PROGRAMS.items() if name != "link" and m != "baton.link.cli"]
    probe = (
        "import sys, baton.cli\n"
        "try:\n    baton.cli.main(['--log-level', 'warning', 'link', '--help'])\n"
        "except SystemExit:\n    pass\n"
        f"print(sorted(m for m in {others!r} if m in sys.modules))"
    )
    loaded = subprocess.run(
        [sys.executable, "-c", probe], capture_output=True, text=True, timeout=60, check=True
    )
    assert loaded.stdout.strip().splitlines()[-1] == "[]", loaded.stdout


def assert_documented(parser: argparse.ArgumentParser, name: str) -> None:
    """Every option of ``parser`` and of its own subcommands has a help text."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub, subparser in action.choices.items():
                assert_documented(subparser, f"{name} {sub}")
            continue
        assert action.help, f"{name} {'/'.join(action.option_strings)} has no help text"
        for option in action.option_strings:
            assert option in parser.format_help()


def test_a_port_in_use_is_a_clear_error(tmp_path) -> None:  # type: ignore[no-untyped-def]
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        config = tmp_path / "one.yaml"
        config.write_text(f"controllers: [{{id: 0, address: 127.0.0.1:{port}}}]\n")
        result = baton("controller", "--id", "0", "--config", str(config), "--insecure")
    assert result.returncode == 1
    assert f"baton controller: cannot serve on 127.0.0.1:{port}: the address is in use" in (
        result.stderr
    )
    assert "Traceback" not in result.stderr


def test_an_unusable_controller_log_file_is_a_clear_error(tmp_path) -> None:  # type: ignore[no-untyped-def]
    config = tmp_path / "one.yaml"
    config.write_text("controllers: [{id: 0, address: 127.0.0.1:0}]\n")
    (tmp_path / "log.sqlite").write_text("not a database")
    result = baton(
        "controller",
        "--id",
        "0",
        "--config",
        str(config),
        "--log-file",
        str(tmp_path / "log.sqlite"),
        "--insecure",
    )
    assert result.returncode == 1  # as for any OSError (baton.cli): one line, no traceback
    assert "log.sqlite (--log-file)" in result.stderr and "Traceback" not in result.stderr


@pytest.mark.parametrize(
    ("program", "flag", "listen"),
    [
        ("sim-vehicle", "--effects-file", ("--port", "0")),
        ("drone", "--camera-effects-file", ("--address", "127.0.0.1:0", "--insecure")),
    ],
)
def test_an_unwritable_effects_file_is_a_clear_error_at_start(
    program: str, flag: str, listen: tuple[str, ...]
) -> None:
    result = baton(program, *listen, flag, "/proc/nope/effects.jsonl")
    assert result.returncode == 1, result.stderr
    assert f"/proc/nope/effects.jsonl ({flag})" in result.stderr
    assert "Traceback" not in result.stderr


@pytest.mark.parametrize("program", ["controller", "drone"])
def test_missing_certificates_are_a_clear_error_naming_the_file_and_the_fix(
    tmp_path,
    program: str,  # type: ignore[no-untyped-def]
) -> None:
    config = tmp_path / "one.yaml"
    config.write_text("controllers: [{id: 0, address: 127.0.0.1:0}]\ntls: {certs: keys}\n")
    args = ("--id", "0") if program == "controller" else ()
    result = baton(program, *args, "--config", str(config))
    assert result.returncode == 2, result.stderr
    name = "controller-0" if program == "controller" else "drone"
    assert f"{tmp_path / 'keys' / 'ca.crt'}: cannot read the {name} TLS files" in result.stderr
    assert f"baton certs init {tmp_path / 'keys'}" in result.stderr
    assert "Traceback" not in result.stderr


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (("testbed", "--timeout", "nan"), "--timeout must be a number > 0 and finite, got nan"),
        (("testbed", "--speedup", "1e6"), "--speedup must be at most 1000"),
        (("testbed", "--flush-limit", "1e999"), "it must be finite"),
        (("sim-vehicle", "--port", "70000"), "must be a port in 0..65535"),
        (("sim-vehicle", "--speedup", "inf"), "must be a number > 0 and finite"),
        (("link", "--latency", "1e999", "--target", "127.0.0.1:1"), "it must be finite"),
        (("drone", "--insecure", "--image", "/nonexistent"), "--image /nonexistent: cannot read"),
        (("drone", "--insecure", "--vehicle-url", "bogus://x"), "not a MAVLink URL"),
        (
            ("drone", "--insecure", "--mavlink-key", "/nonexistent.key"),
            "/nonexistent.key: no such file; make one with `baton certs mavlink-key FILE`",
        ),
        (
            ("sim-vehicle", "--mavlink-key", "/nonexistent.key"),
            "--mavlink-key: MAVLink signing key /nonexistent.key: no such file",
        ),
        (
            ("sitl", "--binary", "/bin/true", "--mavlink-key", "/nonexistent.key"),
            "--mavlink-key: MAVLink signing key /nonexistent.key: no such file",
        ),
        (
            ("drone", "--insecure", "--mavlink-key", "/dev/null", "--vehicle-url", "serial:///x"),
            "not 64 hexadecimal digits",
        ),
    ],
)
def test_bad_flags_are_one_clear_line_before_anything_starts(
    argv: tuple[str, ...], message: str
) -> None:
    """Issue 11: each was a traceback, a silent acceptance, or a run that never ends."""
    result = baton(*argv)
    assert result.returncode == 2, result.stderr
    assert message in result.stderr
    assert "Traceback" not in result.stderr


def test_an_unresolvable_host_is_named_as_such(tmp_path) -> None:  # type: ignore[no-untyped-def]
    config = tmp_path / "one.yaml"
    config.write_text("controllers: [{id: 0, address: 'no-such-host.invalid:7100'}]\n")
    result = baton("controller", "--id", "0", "--config", str(config), "--insecure")
    assert result.returncode == 1
    assert "the host 'no-such-host.invalid' does not resolve" in result.stderr
    assert "in use" not in result.stderr and "Traceback" not in result.stderr
