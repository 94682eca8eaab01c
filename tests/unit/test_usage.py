"""services/usage.py: flags with declared ranges, and one-line errors."""

from __future__ import annotations

import argparse
import os
import re

import pytest

from vistrack.services.usage import FlagError, add_number, check_endpoint, one_line


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="vistrack test")
    add_number(p, "--fps", lo=0.1, hi=1000, or_zero=True, default=0.0, metavar="F",
               help="fps, %(allowed)s")
    add_number(p, "--in-flight", lo=1, hi=16, integer=True, default=2, metavar="N")
    add_number(p, "--timeout", lo=0, hi=3600, lo_open=True, unit="s", default=None,
               metavar="S")
    return p


@pytest.mark.parametrize(("argv", "message"), [
    (["--fps", "nan"], "--fps nan is out of range: allowed 0 or 0.1..1000"),
    (["--fps=-inf"], "--fps -inf is out of range: allowed 0 or 0.1..1000"),
    (["--fps", "1e400"], "--fps 1e400 is out of range: allowed 0 or 0.1..1000"),  # float: inf
    (["--fps", "fast"], "--fps 'fast' is not a number: allowed 0 or 0.1..1000"),
    (["--fps", "0.05"], "--fps 0.05 is out of range: allowed 0 or 0.1..1000"),  # between
    (["--fps", "-0.0001"], "--fps -0.0001 is out of range: allowed 0 or 0.1..1000"),
    (["--in-flight", "17"], "--in-flight 17 is out of range: allowed 1..16"),
    (["--in-flight", "2.0"], "--in-flight '2.0' is not an integer: allowed 1..16"),
    (["--timeout", "0"], "--timeout 0 is out of range: allowed 0 < S <= 3600 s"),
    (["--timeout=-1"], "--timeout -1 is out of range: allowed 0 < S <= 3600 s"),
])
def test_a_value_outside_its_range_names_flag_value_and_range(argv, message):
    with pytest.raises(FlagError) as e:
        parser().parse_args(argv)
    assert str(e.value) == message


def test_values_inside_the_range_are_converted_and_defaults_kept():
    args = parser().parse_args(["--fps", "1000", "--in-flight", "16", "--timeout", "0.001"])
    assert (args.fps, args.in_flight, args.timeout) == (1000.0, 16, 0.001)
    assert isinstance(args.in_flight, int)
    assert vars(parser().parse_args([])) == {"fps": 0.0, "in_flight": 2, "timeout": None}
    assert parser().parse_args(["--fps", "0"]).fps == 0.0  # the value of its own
    assert parser().parse_args(["--fps", "0.1"]).fps == 0.1


def test_help_shows_the_declared_range():
    assert "fps, 0 or 0.1..1000" in " ".join(parser().format_help().split())


def test_a_range_is_declared_once_and_checked():
    with pytest.raises(TypeError, match="no type="):
        add_number(argparse.ArgumentParser(), "--x", lo=0, hi=1, type=float)
    with pytest.raises(ValueError, match="not a finite interval"):
        add_number(argparse.ArgumentParser(), "--x", lo=1, hi=0)


@pytest.mark.parametrize(("argv", "message"), [
    (["tune", "--out", ""], "--out: empty folder name; give a folder, e.g. --out tune-report"),
    (["tune", "--out="], "--out: empty folder name; give a folder, e.g. --out tune-report"),
    (["demo", "--out", ""],
     "--out: empty folder name; give a folder, e.g. --out vistrack-demo"),
    (["certs", "ca", "--dir", ""], "--dir: empty folder name; give a folder, e.g. --dir certs"),
    (["certs", "issue", "robot", "--dir", ""],
     "--dir: empty folder name; give a folder, e.g. --dir certs"),
    (["certs", "show", "a.pem", ""],
     "FILE.pem: empty file name; give a file, e.g. certs/robot.pem"),
    (["certs", "show", "a.pem", "--ca", ""],
     "--ca: empty file name; give a file, e.g. --ca certs/ca.pem"),
    (["up", ""], "LAUNCH.yaml: empty file name; give a file, e.g. deploy/local.yaml"),
    (["camera", "--source", "sim", "--texture", ""],
     "--texture: empty file name; give a file, e.g. --texture texture.png"),
    (["record", ""], "FILE: empty file name; give a file, e.g. run.vtr"),
    (["replay", ""], "FILE: empty file name; give a file, e.g. run.vtr"),
    (["export", "", "b.mcap"], "IN: empty file name; give a file, e.g. run.vtr"),
    (["export", "a.vtr", ""], "OUT: empty file name; give a file, e.g. run.mcap"),
])
def test_an_empty_file_or_folder_name_is_refused_naming_the_flag(argv, message):
    # Path('') is the current folder: demo --out '' and certs --dir '' wrote into it, and
    # tune --out '' and certs show --ca '' took it for "not given"
    from vistrack.services import cli

    with pytest.raises(FlagError) as e:
        cli.build_parser(argv[0]).parse_args(argv)
    assert str(e.value) == message


def test_an_empty_zenoh_config_name_is_refused_before_anything_opens(tmp_path, monkeypatch,
                                                                     capsys):
    from vistrack.services import cli

    monkeypatch.chdir(tmp_path)
    assert cli.main(["echo", "estimate", "-c", ""]) == 2
    assert capsys.readouterr().err == ("vistrack echo: error: -c/--config: empty file name; "
                                       "give a file, e.g. -c zenoh.json5\n")


@pytest.mark.parametrize(("endpoint", "ok"), [
    ("tcp/127.0.0.1:7447", True), ("tcp/[::1]:7447", True), ("udp/robot.local:0", True),
    ("tls/host:7447?iface=eth0", True), ("unixsock-stream//tmp/zenoh.sock", True),
    ("nonsense", False), ("tcp/", False), ("tcp/127.0.0.1", False), ("tcp/1.2.3", False),
    ("tcp/127.0.0.1:99999", False), ("tcp/:7447", False),
])
def test_endpoints_need_a_protocol_and_for_ip_a_host_and_port(endpoint, ok):
    if ok:
        assert check_endpoint("-e", endpoint) == endpoint
    else:
        with pytest.raises(FlagError, match=r"^-e '.*' is not a Zenoh endpoint: expected"):
            check_endpoint("-e", endpoint)


@pytest.mark.parametrize(("raw", "line"), [
    ("zenoh config file c.json5:  --> 1:17\n  |\n1 | { mode: 'peer', \n  |                ^---\n"
     "  |\n  = expected identifier or string at /root/.cargo/git/x/src/lib.rs:1486.",
     "zenoh config file c.json5: line 1, column 17: expected identifier or string"),
    ('zenoh config file c.json5: JSON error: Message { msg: "invalid type: integer `42`", '
     "location: Some(Location { line: 1, column: 9 }) }",
     "zenoh config file c.json5: line 1, column 9: invalid type: integer `42`"),
    ("cannot open zenoh session: invalid port value at /root/.cargo/a/lib.rs:62.",
     "cannot open zenoh session: invalid port value"),
    ("two\nlines", "two lines"),
])
def test_one_line(raw, line):
    assert one_line(raw) == line


@pytest.mark.parametrize("value", ["0", "65", "two", ""])
def test_a_bad_numeric_thread_count_is_one_line_and_exit_2(value, monkeypatch, capsys):
    from vistrack.services import cli

    monkeypatch.setenv("VISTRACK_NUMERIC_THREADS", value)
    assert cli.main(["status", "--help"]) == 2
    assert capsys.readouterr().err == (f"vistrack: error: VISTRACK_NUMERIC_THREADS={value!r} "
                                       "is out of range: allowed 1..64\n")


def test_the_thread_pool_variables_are_set_for_every_library(monkeypatch):
    from vistrack.services import threads

    for var in threads.POOL_VARS:
        monkeypatch.setenv(var, "8")  # a shell's setting does not win
    monkeypatch.setenv("VISTRACK_NUMERIC_THREADS", "1")
    assert threads.configure() == 1
    assert {os.environ[var] for var in threads.POOL_VARS} == {"1"}


@pytest.mark.parametrize(("argv", "message"), [
    (["status", "--timeout", "-1e3"], "--timeout -1e3 is out of range: allowed 0 < S <= 3600 s"),
    (["status", "--timeout", "-0.5"], "--timeout -0.5 is out of range: allowed 0 < S <= 3600 s"),
    (["camera", "--size", "-5x5"], "--size -5x5 is out of range: width and height must be "
                                   "8..4096"),
])
def test_a_negative_value_gets_the_flags_own_range_check(argv, message, capsys):
    # argparse took "-1e3" and "-5x5" for flags and said "expected one argument"
    from vistrack.services import cli

    assert cli.main(argv) == 2
    err = capsys.readouterr().err
    assert message in err and "expected one argument" not in err


def test_a_flag_after_a_flag_that_wants_a_value_is_still_a_flag(capsys):
    from vistrack.services import cli

    with pytest.raises(SystemExit) as exit_:
        cli.main(["status", "--timeout", "--json"])
    assert exit_.value.code == 2
    assert "argument --timeout: expected one argument" in capsys.readouterr().err


@pytest.mark.parametrize(("argv", "code"), [(["--help"], 0), (["track", "--max-features", "0"],
                                                              2)])
def test_a_closed_standard_error_is_no_failure(argv, code):
    # with 2>&- Python leaves sys.stderr None: every command exited 1 without a word
    import subprocess
    import sys

    run = subprocess.run([sys.executable, "-m", "vistrack.services.cli", *argv],
                         preexec_fn=lambda: os.close(2), stdout=subprocess.PIPE, text=True,
                         timeout=60)
    assert run.returncode == code
    if code == 0:
        assert run.stdout.startswith("usage: vistrack")


def test_version_and_the_benchmarks_name_in_errors(capsys):
    import importlib.metadata

    from vistrack.services import cli

    with pytest.raises(SystemExit) as exit_:
        cli.main(["--version"])  # was: "the following arguments are required: COMMAND"
    assert exit_.value.code == 0
    assert capsys.readouterr().out == f"vistrack {importlib.metadata.version('vistrack')}\n"
    with pytest.raises(SystemExit) as exit_:
        cli.main(["bench", "nope"])
    assert exit_.value.code == 2
    # the argument's name in the error, not its internal "which"
    assert "argument BENCHMARK: invalid choice: 'nope'" in capsys.readouterr().err


@pytest.mark.parametrize(("term", "tty", "rewrites"), [
    ("xterm-256color", True, True), ("dumb", True, False), ("", True, False),
    ("xterm", False, False)])
def test_a_status_line_is_rewritten_in_place_only_on_a_terminal_that_can(term, tty, rewrites,
                                                                        monkeypatch):
    import io

    from vistrack.services.usage import rewrites_lines

    class Stream(io.StringIO):
        def isatty(self) -> bool:
            return tty

    monkeypatch.setenv("TERM", term)
    assert rewrites_lines(Stream()) is rewrites


def test_help_is_plain_text_without_the_docstrings_markup():
    # the subcommands' descriptions are their modules' docstrings, written in
    # reStructuredText for the API docs; a terminal showed ``--json`` and :mod:`.tracker`
    from vistrack.services import cli

    text = {}
    for name in cli.COMMANDS:
        sub = next(a for a in cli.build_parser(name)._actions
                   if isinstance(a, argparse._SubParsersAction))
        text[name] = sub.choices[name].format_help()
    for name, help_text in text.items():
        assert "``" not in help_text, name
        assert not re.search(r":(mod|func|meth|class|data|attr):`", help_text), name
    assert "* tracker: the SSD tracker against cv2.matchTemplate" in text["bench"]
    assert "(vistrack/<robot>/<service>/status)" in text["status"]
    assert cli.plain(":func:`~vistrack.common.vision.warm_up` and :class:`.Tracker`") == \
        "warm_up() and Tracker"
    # a module constant by its value: "up to RESENDS times" named nothing a user can read
    assert "up to 2 times" in text["camera"] and "RESENDS" not in text["camera"]
    assert cli.plain("every :data:`SCENE_SAMPLE_S` s, ``MAX_GAP`` frames, ``THRES_PERCENT``",
                     {"SCENE_SAMPLE_S": 0.2, "MAX_GAP": 8, "THRES_PERCENT": "x"}) == \
        "every 0.2 s, 8 frames, THRES_PERCENT"
