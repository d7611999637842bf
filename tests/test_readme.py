"""The README as a newcomer follows it: at most 250 lines, every link resolves, every python quick start runs
as written, and no command needs an activated virtualenv (#42). The MuJoCo quick start also runs from an
installed wheel (tests/test_install.py)."""
from __future__ import annotations

import importlib.util
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
MOVED = ["architecture", "dataset", "performance", "physics", "realism_summary", "stam_results", "texture_budget"]


def _blocks(lang: str) -> list[str]:
    return re.findall(rf"```{lang}\n(.*?)```", README.read_text(), flags=re.S)


def test_readme_is_short():
    assert len(README.read_text().splitlines()) <= 250


@pytest.mark.parametrize("doc", [README] + [ROOT / "docs" / f"{m}.md" for m in MOVED], ids=lambda p: p.name)
def test_every_relative_link_resolves(doc):
    for target in re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", doc.read_text()):
        if "://" in target:
            continue
        assert (doc.parent / target).exists(), f"{doc.name} links to {target}, which does not exist"


def test_no_command_needs_an_activated_virtualenv():
    """`torchrun` is on the PATH only with .venv activated: the README names .venv/bin/torchrun."""
    for block in _blocks("bash"):
        for line in block.splitlines():
            assert not line.startswith("torchrun"), line


@pytest.mark.parametrize("i", range(len(_blocks("python"))))
def test_each_python_quick_start_runs_as_written(i, tmp_path, monkeypatch):
    code = _blocks("python")[i]
    if "gymnasium" in code and importlib.util.find_spec("gymnasium") is None:
        pytest.skip("gymnasium is an optional extra (make gym)")
    monkeypatch.chdir(tmp_path)
    exec(compile(code, f"README.md python block {i}", "exec"), {"__name__": "__readme__"})
    written = sorted(p.name for p in tmp_path.glob("*.png"))
    if "write_png(" in code:
        assert written, "the quick start says it writes a PNG"
