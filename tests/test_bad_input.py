"""Bad input, command by command: one line on stderr naming the problem and the fix, exit status 2, no
traceback, and nothing written where the command was run or into the dataset it was given (#42, #50).

TABLE lists bad inputs per command. Every option that takes a value, and every positional argument, of
every `gelsim` and `stam` command must appear in at least one of its command's cases
(:func:`test_every_option_has_a_bad_input`), so that a new option or command gets the same treatment.
Placeholders: ``{data}`` a small finished dataset, ``{file}`` an existing regular file (not a folder),
``{bad_npz}`` a file that is no data pack, ``{missing}`` a path that does not exist.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import pytest

from gelsim.cli import build_parser as gelsim_parser
from gelsim.cli import main as gelsim_main

stam_cli = pytest.importorskip("stam.cli", reason="stam needs torch")

MAINS = {"gelsim": gelsim_main, "stam": stam_cli.main}

#: command -> [(arguments, a fragment the one line must hold)]
TABLE: dict[str, list[tuple[list[str], str]]] = {
    "gelsim render": [
        (["--fabric", "21", "--out", "x.txt"], "must be a .png"),
        (["--fabric", "999", "--out", "x.png"], "999"),
        (["--fabric", "21", "--depth-mm", "-1", "--out", "x.png"], "--depth-mm"),
        (["--force-n", "nan", "--out", "x.png"], "--force-n"),
        (["--indenter", "cube", "--out", "x.png"], "unknown indenter"),
        (["--indenter", "{bad_npz}.stl", "--out", "x.png"], "not found"),
        (["--diameter-mm", "0", "--out", "x.png"], "diameter_mm"),
        (["--diameter-mm", "1e9", "--out", "x.png"], "diameter up to"),
        (["--fabric", "21", "--diameter-mm", "6", "--out", "x.png"], "would change nothing"),  # an option doing nothing
        (["--profile", "nosuch", "--out", "x.png"], "unknown sensor profile"),
        (["--backend", "opengl", "--out", "x.png"], "--backend"),
        (["--device", "cuda", "--out", "x.png"], "--device"),
        (["--fidelity", "ultra", "--out", "x.png"], "--fidelity"),
        (["--seed", "-1", "--out", "x.png"], "--seed"),
        (["--out", "{file}/x.png"], "is a file, not a folder"),
        (["--out", "{missing}/x.png"], "does not exist"),
    ],
    "gelsim press": [
        (["--force-n", "0"], "--force-n"),
        (["--force-n", "1e20"], "more than the vitac gel can carry"),
        (["--force-n", "0.05", "--diameter-mm", "1e9"], "diameter up to"),
        (["--force-n", "1", "--indenter", "{bad_npz}"], "unknown indenter"),
        (["--force-n", "1", "--indenter", "cylinder", "--length-mm", "-2"], "length_mm"),
        (["--force-n", "1", "--indenter", "cylinder", "--angle-deg", "inf"], "angle_deg"),
        (["--force-n", "1", "--length-mm", "3"], "not for --indenter sphere"),     # an option doing nothing
        (["--force-n", "1", "--profile", "{missing}.toml"], "not found"),
        (["--force-n", "1", "--fidelity", "ultra"], "--fidelity"),
        (["--force-n", "1", "--resolution-px", "4"], "out of range for vitac"),
    ],
    "gelsim generate": [
        (["--out", "{file}", "--preset", "quick"], "is a file"),
        (["--out", "o", "--preset", "huge"], "--preset"),
        (["--out", "o", "--fabrics", "0"], "--fabrics"),
        (["--out", "o", "--sequences-per-fabric", "0"], "--sequences-per-fabric"),
        (["--out", "o", "--actions", "1:2"], "--actions"),
        (["--out", "o", "--split", "1:x:1"], "--split"),
        (["--out", "o", "--frames", "0"], "--frames"),
        (["--out", "o", "--precontact", "5-2"], "--precontact"),
        (["--out", "o", "--nuisance", "storm"], "unknown nuisance level"),
        (["--out", "o", "--nuisance-severity", "2"], "add --nuisance camera or handheld"),
        (["--out", "o", "--nuisance", "none", "--nuisance-severity", "3"], "add --nuisance camera or handheld"),
        (["--out", "o", "--nuisance", "camera", "--nuisance-severity", "9"], "--nuisance-severity"),
        (["--out", "o", "--profile", "nosuch"], "unknown sensor profile"),
        (["--out", "o", "--resolution", "0x0"], "--resolution"),
        (["--out", "o", "--resolution", "16x16"], "give 19x16 to"),
        (["--out", "o", "--fidelity", "ultra"], "--fidelity"),
        (["--out", "o", "--backend", "gl"], "--backend"),
        (["--out", "o", "--stages", "all"], "--backend torch"),
        (["--out", "o", "--device", "cuda"], "--backend torch"),
        (["--out", "o", "--batch", "8"], "--backend torch"),
        (["--out", "o", "--seed", "x"], "--seed"),
        (["--out", "o", "--workers", "100000", "--dry-run"], "--workers 100000"),
        (["--out", "o", "--workers", "0"], "--workers 0"),
        (["--out", "o", "--ray", "127.0.0.1:1", "--workers", "2"], "Ray"),
        (["--out", "o", "--format", "gif"], "--format"),
        (["--out", "o", "--units", "-1"], "--units"),
    ],
    "gelsim verify": [
        (["{missing}"], "does not exist"),
        (["{file}"], "is a file, not a dataset directory"),
        (["{data}", "--stats-out", "s"], "add --stats"),
        (["{data}", "--stats", "--crop", "2"], "crop"),
    ],
    "gelsim show": [
        (["{missing}"], "does not exist"),
        (["{data}", "f999-s0000"], "not in its manifest"),
        (["{data}", "--frames", "0"], "--frames"),
        (["{data}", "--out", "{file}"], "is a file, not a folder"),
    ],
    "gelsim fabrics list": [
        (["--catalog", "{missing}"], "not found"),
    ],
    "gelsim fabrics show": [
        (["999", "--out", "x.png"], "999"),
        (["1", "--out", "x.txt"], ".png"),
        (["1", "--out", "x.png", "--catalog", "{missing}"], "not found"),
        (["1", "--out", "x.png", "--size-mm", "-3"], "size"),
        (["1", "--out", "x.png", "--mm-per-px", "0"], "mm"),
        (["1", "--out", "x.png", "--seed", "-5"], "seed"),
        (["1", "--out", "x.png", "--rotation-deg", "nan"], "rotation"),
    ],
    "gelsim fabrics sheet": [
        (["--out", "x.txt"], ".png"),
        (["--out", "x.png", "--catalog", "{missing}"], "not found"),
        (["--out", "x.png", "--tile-mm", "0"], "positive"),
        (["--out", "x.png", "--mm-per-px", "-1"], "positive"),
        (["--out", "x.png", "--columns", "0"], "--columns"),
        (["--out", "x.png", "--seed", "-5"], "seed"),
    ],
    "gelsim sensors show": [
        (["nosuch"], "unknown sensor profile"),
    ],
    "gelsim bench": [
        (["--out", "b", "--resolution", "10x10"], "out of range for vitac"),
        (["--out", "b", "--frames", "3", "--precontact", "2"], "frames"),
        (["--out", "b", "--fabrics", "1,x"], "--fabrics"),
        (["--out", "b", "--actions", "jump"], "action"),
        (["--out", "b", "--levels", "ultra", "--quick"], "unknown fidelity"),
        (["--out", "b", "--reference", "ultra", "--quick"], "fidelity"),
        (["--out", "b", "--profile", "nosuch", "--quick"], "unknown sensor profile"),
        (["--out", "b", "--seed", "-1", "--quick"], "seed"),
        (["--out", "b", "--format", "gif", "--quick"], "--format"),
        (["--out", "b", "--cache", "{file}", "--quick"], "cache"),
        (["--out", "b", "--convergence", "--knobs", "colour"], "--knobs"),
        (["--out", "{file}", "--quick"], "is a file"),
    ],
    "gelsim texture": [
        (["--fabric", "999"], "999"),
        (["--fabrics", "5-2"], "--fabrics"),
        (["--fabric", "1", "--force-n", "-1"], "force"),
        (["--fabric", "1", "--forces", "1,x"], "--forces"),
        (["--fabric", "1", "--profile", "nosuch"], "unknown sensor profile"),
        (["--fabric", "1", "--fidelity", "ultra"], "--fidelity"),
        (["--fabric", "1", "--resolution", "4x3"], "out of range for vitac"),
        (["--fabric", "1", "--seed", "-1"], "seed"),
        (["--fabric", "1", "--out", "{file}"], "is not a directory"),
        (["--fabric", "1", "--sheet", "x.txt"], ".png"),
        (["--fabric", "1", "--sheet", "x.png", "--crop", "0x0"], "--crop"),
    ],
    "gelsim realism": [
        (["--datapack", "{bad_npz}"], "data pack bad.npz cannot be read"),
        (["--profile", "nosuch", "--datapack", "{bad_npz}"], "unknown sensor profile"),
        (["--datapack", "{bad_npz}", "--frames", "most"], "--frames"),
        (["--datapack", "{bad_npz}", "--mm-per-px", "-1"], "mm"),
        (["--datapack", "{bad_npz}", "--ball-diameter-mm", "0"], "diameter"),
        (["--datapack", "{bad_npz}", "--channel-order", "gbr"], "--channel-order"),
        (["--datapack", "{bad_npz}", "--centres", "guess"], "--centres"),
        (["--datapack", "{bad_npz}", "--out", "x.txt"], ".png"),
    ],
    "gelsim calibrate": [
        (["{bad_npz}", "--out", "p.toml"], "data pack bad.npz cannot be read"),
        (["{bad_npz}", "--out", "p.txt"], ".toml"),
        (["{bad_npz}", "--out", "p.toml", "--frames", "most"], "--frames"),
        (["{bad_npz}", "--out", "p.toml", "--mm-per-px", "-1"], "mm"),
        (["{bad_npz}", "--out", "p.toml", "--ball-diameter-mm", "0"], "diameter"),
        (["{bad_npz}", "--out", "p.toml", "--base-profile", "nosuch"], "unknown sensor profile"),
        (["{bad_npz}", "--out", "p.toml", "--channel-order", "gbr"], "--channel-order"),
    ],
    "stam info": [
        (["--model", "rnn"], "--model"),
        (["--model", "stam", "--frames", "0"], "n_frames must be at least 1"),
        (["--model", "stam", "--width", "0"], "--width"),
        (["--model", "stam", "--image-size", "8"], "--image-size"),
        (["--model", "stam", "--classes", "0"], "--classes"),
    ],
    "stam onsets": [
        (["--data", "{missing}"], "does not exist"),
        (["--data", "{data}", "--threshold", "-1"], "--threshold -1"),
        (["--data", "{data}", "--image-size", "0"], "--image-size"),
    ],
    "stam pretrain": [
        (["--data", "{missing}", "--out", "p"], "does not exist"),
        (["--data", "{data}", "--out", "{file}"], "is a file, not a folder"),
        (["--data", "{data}", "--out", "p", "--width", "0"], "--width"),
        (["--data", "{data}", "--out", "p", "--image-size", "8"], "--image-size"),
        (["--data", "{data}", "--out", "p", "--crop", "0"], "crop"),
        (["--data", "{data}", "--out", "p", "--epochs", "0"], "--epochs"),
        (["--data", "{data}", "--out", "p", "--batch-size", "0"], "--batch-size"),
        (["--data", "{data}", "--out", "p", "--lr", "0"], "--lr"),
        (["--data", "{data}", "--out", "p", "--optimizer", "lbfgs"], "--optimizer"),
        (["--data", "{data}", "--out", "p", "--seed", "-1"], "--seed"),
        (["--data", "{data}", "--out", "p", "--device", "tpu"], "--device"),
    ],
    "stam train": [
        (["--data", "{data}", "--out", "{file}"], "is a file, not a folder"),
        (["--data", "{missing}", "--out", "r"], "does not exist"),
        (["--data", "{data}", "--out", "r", "--config", "huge"], "unknown config 'huge'"),
        (["--data", "{data}", "--out", "r", "--model", "rnn"], "--model"),
        (["--data", "{data}", "--out", "r", "--frames", "0"], "--frames"),
        (["--data", "{data}", "--out", "r", "--start", "end"], "--start"),
        (["--data", "{data}", "--out", "r", "--epochs", "0"], "--epochs"),
        (["--data", "{data}", "--out", "r", "--seed", "-1"], "--seed"),
        (["--data", "{data}", "--out", "r", "--pretrained", "{missing}.pt"], "not found"),
        (["--data", "{data}", "--out", "r", "--set", "lr"], "key=value"),
        (["--data", "{data}", "--out", "r", "--set", "lr=-1"], "--set lr"),
        (["--data", "{data}", "--out", "r", "--resume"], "nothing to resume"),
    ],
    "stam evaluate": [
        (["--checkpoint", "{missing}.pt"], "not found"),
        (["--checkpoint", "{file}"], "cannot load checkpoint"),
        (["--checkpoint", "{file}", "--data", "{missing}"], "checkpoint"),
        (["--checkpoint", "{file}", "--split", "dev"], "--split"),
        (["--checkpoint", "{file}", "--out", "{file}"], "is a file, not a folder"),
        (["--checkpoint", "{file}", "--device", "tpu"], "--device"),
    ],
    "stam experiment": [
        (["--data", "{data}", "--out", "e"], "no 'test' sequences"),
        (["--data", "{data}", "--out", "{file}"], "is a file, not a folder"),
        (["--data", "{data}", "--out", "e", "--config", "gpu9"], "unknown config"),
        (["--data", "{data}", "--out", "e", "--seeds", "0"], "--seeds 0"),
        (["--data", "{data}", "--out", "e", "--models", "rnn"], "--models"),
        (["--data", "{data}", "--out", "e", "--frames", "0"], "--frames 0"),
        (["--data", "{data}", "--out", "e", "--settings", "dirty"], "--settings"),
        (["--data", "{data}", "--out", "e", "--attention-at", "fc6"], "--attention-at"),
        (["--data", "{data}", "--out", "e", "--clean-frames", "x"], "--clean-frames"),
        (["--data", "{data}", "--out", "e", "--pretrain-frames", "some"], "--pretrain-frames"),
        (["--data", "{data}", "--out", "e", "--ray", "127.0.0.1:1"], "ray"),
    ],
    "stam compare": [
        (["{missing}", "{missing}"], "no finished cells"),
        (["{file}", "{file}"], "no finished cells"),
        (["{missing}", "{missing}", "--out", "x.md"], "no finished cells"),
    ],
    "stam explain": [
        (["--checkpoint", "{missing}.pt"], "not found"),
        (["--checkpoint", "{file}", "--data", "{data}"], "cannot load checkpoint"),
        (["--checkpoint", "{file}", "--sequence", "f999-s0000"], "checkpoint"),
        (["--checkpoint", "{file}", "--split", "dev"], "--split"),
        (["--checkpoint", "{file}", "--out", "{file}"], "is a file, not a folder"),
    ],
}

#: Commands that take no option with a value (besides --json): nothing to list.
NO_VALUES = {"gelsim sensors list"}
#: Options that take any text: no value of theirs is bad input.
FREE_TEXT = {"gelsim calibrate": {"--description"}}


def _commands() -> dict[str, set[str]]:
    """Every leaf command of both CLIs -> its options that take a value and its positional arguments."""
    out: dict[str, set[str]] = {}

    def walk(parser: argparse.ArgumentParser, name: str) -> None:
        subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
        if subs:
            for sub, p in subs[0].choices.items():
                walk(p, f"{name} {sub}")
            return
        names = set()
        for a in parser._actions:
            if isinstance(a, (argparse._HelpAction, argparse._VersionAction)) or a.nargs == 0:
                continue
            if a.help == argparse.SUPPRESS:
                continue   # an old spelling, kept working
            names.add(a.option_strings[0] if a.option_strings else a.dest)
        out[name] = names

    walk(gelsim_parser(), "gelsim")
    walk(stam_cli.build_parser(), "stam")
    return out


def test_every_option_has_a_bad_input():
    for command, names in _commands().items():
        if command in NO_VALUES:
            assert not names, f"{command} now takes {names}: give it cases in TABLE"
            continue
        assert command in TABLE, f"{command} has no bad inputs in TABLE"
        used = {tok for argv, _ in TABLE[command] for tok in argv}
        positional = {n for n in names if not n.startswith("-")}
        missing = {n for n in names - positional - FREE_TEXT.get(command, set()) if n not in used}
        assert not missing, f"{command}: no bad input uses {sorted(missing)}"
        if positional:
            assert TABLE[command], command
    assert set(TABLE) <= set(_commands()), set(TABLE) - set(_commands())


def _listing(*roots: Path) -> dict[str, int]:
    return {str(p): p.stat().st_size for r in roots for p in sorted(r.rglob("*"))}


@pytest.fixture(scope="module")
def data(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("bad") / "ds"
    assert gelsim_main(["generate", "--out", str(out), "--fabrics", "2", "--sequences-per-fabric", "2",
                        "--resolution", "96x72", "--fidelity", "fast", "--frames", "8-10", "--no-previews",
                        "--workers", "1", "--json"]) == 0
    return out


CASES = [(command, argv, fragment) for command, rows in TABLE.items() for argv, fragment in rows]


@pytest.mark.parametrize("command, argv, fragment", CASES,
                         ids=[f"{c}:{' '.join(a)}" for c, a, _ in CASES])
def test_bad_input_is_one_line_and_status_2(command, argv, fragment, data, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("GELSIM_CACHE", str(tmp_path / ".cache"))   # nothing fetched, nothing kept
    (tmp_path / "afile").write_text("not a folder, not a checkpoint\n")
    (tmp_path / "bad.npz").write_text("not a data pack\n")
    subs = {"{data}": str(data), "{file}": "afile", "{bad_npz}": "bad.npz", "{missing}": "nothere"}
    args = []
    for tok in argv:
        for key, value in subs.items():
            tok = tok.replace(key, value)
        args.append(tok)
    prog, *sub = command.split()
    before = _listing(tmp_path, data)
    try:
        code = MAINS[prog]([*sub, *args])
    except SystemExit as e:          # argparse's own errors
        code = e.code
    cap = capsys.readouterr()
    assert code == 2, f"exit {code}; stderr: {cap.err[-500:]}"
    assert cap.err.count("\n") == 1 and cap.err.startswith(f"{prog}"), cap.err
    assert fragment in cap.err, cap.err
    assert " error: " in cap.err and "Traceback" not in cap.err
    assert _listing(tmp_path, data) == before, "the bad input left files behind"
