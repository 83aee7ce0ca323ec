"""The command line's output contract: logs go to stderr, stdout ends with one JSON line (what scripts read)."""

import json
import subprocess
import sys

from _zenoh import endpoint, free_port


def _run(*args, env=None):
    import os

    e = dict(os.environ, CRISTAL_PROGRESS="0", **(env or {}))
    return subprocess.run([sys.executable, "-m", "services.cli", *map(str, args)], capture_output=True, text=True,
                          timeout=60, env=e)


def test_logs_go_to_stderr_and_stdout_ends_with_json():
    port = free_port()
    r = _run("router", "--listen", endpoint(port), "--duration", "0.2")
    assert r.returncode == 0, r.stderr
    out = r.stdout.strip().splitlines()
    assert json.loads(out[-1])["router"]  # the last stdout line is the JSON summary
    assert out[0].startswith("router ") and len(out) == 2  # the human line, then the JSON: no log line
    assert "INFO" in r.stderr and "zenoh router" in r.stderr  # the log line went to stderr
    # non-interactive stderr: one plain line per record, never wrapped (JSON event lines stay greppable)
    log = [line for line in r.stderr.splitlines() if "zenoh router" in line]
    assert len(log) == 1 and log[0].rstrip().endswith("]")


def test_quiet_keeps_info_off_stderr():
    port = free_port()
    r = _run("-q", "router", "--listen", endpoint(port), "--duration", "0.2")
    assert r.returncode == 0 and "INFO" not in r.stderr
    assert json.loads(r.stdout.strip().splitlines()[-1])["router"]


def test_a_file_that_is_no_database_is_named_so(tmp_path):
    from services.relocalize.database import RelocDB

    ply = tmp_path / "scan.ply"  # what a user passes by mistake: the scan itself, or a text file
    ply.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 0\nend_header\n")
    try:
        RelocDB.load(ply)
    except ValueError as e:
        assert "not a relocalization database" in str(e) and "build-db" in str(e)
    else:
        raise AssertionError("a PLY loaded as a database")


def test_every_command_line_argument_says_what_it_is_for():
    import argparse

    from services.cli import build_parser

    silent = []

    def walk(p, name):
        for a in p._actions:
            if isinstance(a, argparse._SubParsersAction):
                for n, sp in a.choices.items():
                    walk(sp, f"{name} {n}")
            elif not isinstance(a, argparse._HelpAction) and not a.help:
                silent.append(f"{name} {'/'.join(a.option_strings) or a.dest}")

    walk(build_parser(), "cristal")
    assert not silent, f"arguments without a help text: {silent}"
