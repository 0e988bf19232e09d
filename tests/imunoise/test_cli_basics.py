import subprocess
import sys

from imunoise.cli import main
from imunoise.errors import UsageError
from imunoise.options import parse_duration


def test_parse_duration_units():
    assert parse_duration("90") == 90.0
    assert parse_duration("90s") == 90.0
    assert parse_duration("30m") == 1800.0
    assert parse_duration("8h") == 28800.0
    assert parse_duration("1.5h") == 5400.0


def test_parse_duration_rejects_garbage():
    for bad in ["", "abc", "10x", "-5s", "0"]:
        try:
            parse_duration(bad)
        except UsageError as exc:
            assert "duration" in str(exc)
        else:
            raise AssertionError(f"accepted {bad!r}")


def test_unknown_command_is_one_line_exit_2(capsys):
    assert main(["frobnicate"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "frobnicate" in err[0]


def test_module_entry_point_help():
    out = subprocess.run([sys.executable, "-m", "imunoise", "--help"], capture_output=True,
                         text=True, check=True).stdout
    assert "analyze" in out


def test_command_help_has_no_markup():
    out = subprocess.run([sys.executable, "-m", "imunoise", "fit", "--help"],
                         capture_output=True, text=True, check=True).stdout
    assert "``" not in out and "imunoise fit:" in out
