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


def _blas_threads_after(code: str, env_extra: dict[str, str]) -> str:
    import os

    env = {k: v for k, v in os.environ.items()
           if k not in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")}
    script = ("import os, sys\n" + code + "\nfrom imunoise import cli\n"
              "cli.one_blas_thread_per_process()\n"
              "print(os.environ.get('OPENBLAS_NUM_THREADS', 'unset'))")
    out = subprocess.run([sys.executable, "-c", script], env={**env, **env_extra},
                         capture_output=True, text=True, timeout=60, check=True)
    return out.stdout.strip()


def test_the_program_keeps_blas_on_one_thread_unless_the_user_sized_it():
    # worker processes do the parallel work; a BLAS pool in each would oversubscribe the CPUs
    assert _blas_threads_after("", {}) == "1"
    assert _blas_threads_after("", {"OPENBLAS_NUM_THREADS": "3"}) == "3"
    # numpy already loaded (a caller's interpreter): its pools are sized; nothing is set
    assert _blas_threads_after("import numpy", {}) == "unset"
