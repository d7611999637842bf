"""The shared command-line dispatcher (gelsim/cli/__init__.py)."""
import subprocess
import sys


def test_closed_pipe_ends_quietly():
    # `gelsim fabrics list --json | head`: the reader is gone before the command writes (closing our
    # end at once makes the first write fail: the interpreter takes a moment to start). No traceback.
    proc = subprocess.Popen([sys.executable, "-m", "gelsim", "fabrics", "list", "--json"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    proc.stdout.close()
    _, err = proc.communicate(timeout=120)
    assert err.decode() == "" and proc.returncode == 141


def test_guarded_gives_one_line_and_status_2_on_bad_input(capsys):
    from gelsim.cli import guarded
    from gelsim.errors import GelsimError

    def bad():
        raise GelsimError("x is wrong; fix it")

    assert guarded("prog", bad) == 2
    assert capsys.readouterr().err == "prog: error: x is wrong; fix it\n"
    assert guarded("prog", lambda: None) == 0 and guarded("prog", lambda: 3) == 3


def test_print_result_is_json_or_the_lines(capsys):
    import numpy as np

    from gelsim.cli import print_result

    assert print_result(True, {"n": np.int64(2)}, "not shown") == 0
    assert capsys.readouterr().out == '{\n  "n": 2\n}\n'
    assert print_result(False, {"n": 2}, "one", "two") == 0
    assert capsys.readouterr().out == "one\ntwo\n"


def test_scripts_keep_the_error_contract(tmp_path):
    # benchmarks/ and tools/ scripts end in gelsim.cli.run_script: bad input is one line and status 2.
    from pathlib import Path

    script = Path(__file__).resolve().parents[2] / "benchmarks" / "bench_convergence.py"
    proc = subprocess.run([sys.executable, str(script), "--resolution", "12", "--hires", "", "--out", str(tmp_path)],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2
    assert proc.stderr.splitlines() == ["bench_convergence.py: error: --resolution '12' is malformed; give WIDTHxHEIGHT, "
                                        "e.g. 320x240"]


def test_argparse_errors_are_one_line_and_status_2(capsys):
    """A bad int, a bad choice, a missing required option or an unknown command: one line naming it and
    where the help is, no usage block (#42)."""
    import pytest

    from gelsim.cli import main as gelsim_main
    from stam.cli import main as stam_main

    cases = [(gelsim_main, ["render", "--fabric", "abc", "--out", "x.png"], "gelsim render: error: argument --fabric: "
              "invalid int value: 'abc'; see `gelsim render --help`"),
             (gelsim_main, ["render", "--fabric", "21"], "gelsim render: error: the following arguments are required: "
              "--out; see `gelsim render --help`"),
             (gelsim_main, ["press", "--fidelity", "turbo", "--force-n", "1"], "gelsim press: error: argument "
              "--fidelity: invalid choice: 'turbo'"),
             (gelsim_main, ["rendr"], "gelsim: error: argument COMMAND: invalid choice: 'rendr'"),
             (stam_main, ["train", "--data", "d"], "stam train: error: the following arguments are required: --out; "
              "see `stam train --help`")]
    for main, argv, start in cases:
        with pytest.raises(SystemExit) as e:
            main(argv)
        err = capsys.readouterr().err
        assert e.value.code == 2 and err.count("\n") == 1 and err.startswith(start), err
