"""No module reaches into another's private names (issue 49), read from the source (nothing is imported).

In gelsim/, stam/, tools/ and benchmarks/ (but benchmarks/peers/, which drive other people's simulators through their
internals by design): no ``from X import _name`` of another module, no read of ``something._name`` but on the
object itself (``self``, ``cls``, ``super()``), and no write of ``something._name = ...`` but its own. What two
modules share is public (and tested where it is defined); an object's state that another object sets is a public
object of its own (the MuJoCo pad's :class:`gelsim.mujoco.stickslip.StickSlip`)."""
from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
TREES = ("gelsim", "stam", "tools", "benchmarks")
EXEMPT = ("benchmarks/peers",)
#: Reaches into a third-party library that has no public way to the same thing: file -> (name, why).
THIRD_PARTY = {"stam/ranks.py": ("_get_default_store",
                                 "torch has no public accessor for the default process group's store")}
OWN = ("self", "cls")


def private(name: str) -> bool:
    return name.startswith("_") and not (name.startswith("__") and name.endswith("__"))


def own_object(node: ast.expr) -> bool:
    """``self``, ``cls`` or ``super()``: the object whose class the code belongs to."""
    if isinstance(node, ast.Name):
        return node.id in OWN
    return isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id == "super"


def reaches(source: str, where: str) -> list[str]:
    """Each place in ``source`` that imports, reads or writes another module's or object's private name."""
    out = []
    for node in sorted(ast.walk(ast.parse(source, where)), key=lambda n: getattr(n, "lineno", 0)):
        if isinstance(node, ast.ImportFrom):
            out += [f"{where}:{node.lineno}: imports {a.name} from {'.' * node.level}{node.module or ''}"
                    for a in node.names if private(a.name)]
        elif isinstance(node, ast.Attribute) and private(node.attr) and not own_object(node.value):
            what = "writes" if isinstance(node.ctx, (ast.Store, ast.Del)) else "reads"
            out.append(f"{where}:{node.lineno}: {what} {ast.unparse(node)}")
    return out


def test_the_check_sees_each_kind_of_reach():
    code = ("from .twoscale import _widen\nimport gelsim.gel.twoscale as ts\nts._widen(1, 2, 3)\n"
            "host._anchor = None\nself._ok = 1\nsuper()._ok()\nclass A:\n    def f(self, other):\n        return other._x\n")
    found = reaches(code, "x.py")
    assert [f.split(": ", 1)[1] for f in found] == ["imports _widen from .twoscale", "reads ts._widen",
                                                     "writes host._anchor", "reads other._x"]


def test_no_module_reaches_into_another_modules_private_names():
    files = [p for t in TREES for p in sorted((ROOT / t).rglob("*.py"))
             if not any(p.relative_to(ROOT).as_posix().startswith(e) for e in EXEMPT)]
    assert any(p.name == "batch.py" for p in files) and len(files) > 100
    found = [f for p in files for f in reaches(p.read_text(), p.relative_to(ROOT).as_posix())
             if not (f.split(":")[0] in THIRD_PARTY and f" {THIRD_PARTY[f.split(':')[0]][0]} " in f"{f} ")]
    assert not found, "private names reached from outside:\n" + "\n".join(found)
