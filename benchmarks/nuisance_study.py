"""The robustness study of issue 48 (docs/stam_study.md): a positive control first, then every model on
each nuisance level's own data, both training protocols, n = 2..7, paired 95% intervals, the mechanism
table and accuracy against severity.

    .venv/bin/python benchmarks/nuisance_study.py --data DATA --out OUT [--gen "GELSIM GENERATE OPTIONS"]
        [--levels none handheld] [--control-levels none handheld] [--severities 0.5 2] [--frames 2 4 6] ...

Steps, in this order; each is resumable (a complete dataset, a finished backbone or cell is reused):

1. Positive control: for each --control-levels L, the dataset DATA/control-L (`gelsim generate GEN
   --nuisance L --precontact 3-6`) and `stam experiment` of the CNN and the oracle on it. Its verdict
   (does the study resolve the oracle's gain over the CNN?) is printed and written to OUT/control.md
   before anything else is run.
2. Levels: for each --levels L, DATA/L (`gelsim generate GEN --nuisance L`) and `stam experiment` of
   --models into OUT/L. Each run pretrains its own backbone on that level's training frames, all of them
   (the frames before contact too: --pretrain-frames), so no model meets features learnt on another
   level's frames; the heads are trained on them frozen (the cpu preset's economy).
3. Each level against the first (`stam compare`): OUT/L_vs_FIRST.md.
4. Severities (optional): DATA/SEVLEVEL-sS (`--nuisance-severity S`), `stam experiment` of
   --severity-models, and OUT/severity.png (benchmarks/nuisance_plot.py).
5. OUT/report.md: the control first, each level's contrasts, the mechanism table, the comparisons, the
   costs measured (also OUT/costs.json: wall seconds per step, per-cell medians).

Cuts for a CPU budget: --frames (n = 2, 4, 6 are kept: refused otherwise), --seeds, --models,
--severities, --settings; --plan prints the datasets and cells a command would run, and stops.
"""
from __future__ import annotations

import argparse
import json
import shlex
import shutil
import subprocess
import sys
import time
from pathlib import Path

from gelsim.atomic import atomic_write_json, atomic_write_text
from gelsim.errors import GelsimError

SMALL_GEN = "--fabrics 20 --sequences-per-fabric 30 --resolution 320x240 --split 10:4:16"


def _complete(d: Path) -> bool:
    try:
        return json.loads((d / "manifest.json").read_text()).get("complete") is True
    except (OSError, ValueError):
        return False


class Study:
    """The study's steps, sharing the options and the cost record (OUT/costs.json)."""

    def __init__(self, a):
        self.a = a
        self.data, self.out = Path(a.data), Path(a.out)
        self.costs_path = self.out / "costs.json"
        self.costs = json.loads(self.costs_path.read_text()) if self.costs_path.is_file() else {}

    def log(self, msg: str) -> None:
        print(msg, flush=True)

    def record(self, name: str, **values) -> None:
        self.costs.setdefault(name, {}).update(values)
        atomic_write_json(self.costs_path, self.costs)

    def dataset(self, name: str, level: str, *extra: str) -> Path:
        """DATA/name, generated (or finished) with --gen, --nuisance level and ``extra`` unless complete."""
        d = self.data / name
        if _complete(d):
            return d
        cmd = [sys.executable, "-m", "gelsim", "generate", *shlex.split(self.a.gen), "--nuisance", level, *extra,
               "--out", str(d), "--no-previews"]
        self.log(f"generate {name}: {' '.join(cmd[2:])}")
        t0 = time.perf_counter()
        r = subprocess.run(cmd)
        if r.returncode != 0:
            raise GelsimError(f"gelsim generate for {name} stopped with status {r.returncode}; fix its options "
                              "(--gen) and rerun: finished sequences are kept")
        self.record(name, generate_s=round(time.perf_counter() - t0, 1))
        return d

    def experiment(self, name: str, data: Path, models, frames=None, onset: str = "detected") -> dict:
        from stam.experiment import run_experiment
        from stam.study import cell_costs

        out = self.out / name
        before = set(out.glob("cells/*/n*/*/seed*/result.json"))
        t0 = time.perf_counter()
        frames = frames or self.a.frames
        # the clean windows one frame shorter too: a window from frame 0 one frame before contact holds the clean
        # window of n - 1 frames, against which its frame before contact is costed (the mechanism table)
        extra = sorted({n - 1 for n in frames if n > 1} - set(frames))
        res = run_experiment(str(data), out, self.a.preset, self.a.seeds, list(models), frames, self.a.settings,
                             log=(lambda m: self.log(f"  {name}: {m}")) if self.a.verbose else None,
                             note=lambda m: print(m, file=sys.stderr), overrides={"onset": onset},
                             pretrain_overrides={"contact_only": self.a.pretrain_frames == "contact"}, clean_extra=extra)
        seconds = time.perf_counter() - t0
        # Each call's wall time adds to the run's (a rerun that reused everything adds nothing).
        if not (res["pretrain"].get("reused") and before == set(out.glob("cells/*/n*/*/seed*/result.json"))):
            self.record(name, experiment_s=round(self.costs.get(name, {}).get("experiment_s", 0) + seconds, 1))
        costs = cell_costs(out)
        if self.costs.get(name, {}).get("backbone_from"):   # not pretrained here
            costs.pop("pretrain_s", None)
            costs.pop("pretrain_epochs", None)
        self.record(name, **costs)
        return res

    def share_backbone(self, source: str, name: str) -> None:
        """Pretrained on all frames, a backbone does not depend on where the onset is: the run ``name`` on the
        dataset of run ``source`` starts from its backbone.pt (stam.train.pretrain reuses one whose settings
        match, which they do) instead of pretraining the same one again."""
        src, dst = self.out / source / "pretrain" / "backbone.pt", self.out / name / "pretrain" / "backbone.pt"
        if name != source and self.a.pretrain_frames == "all" and src.is_file() and not dst.is_file():
            dst.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(src, dst)
            self.record(name, backbone_from=source)

    def plan(self) -> None:
        a = self.a
        trained = [s for s in a.settings if s != "transfer"] + (["clean"] if "transfer" in a.settings
                                                                  and "clean" not in a.settings else [])
        tested = ["transfer"] if "transfer" in a.settings else []

        def line(name, models, frames=a.frames, dataset=None):
            n = len(models) * len(frames) * a.seeds
            extra = len({k - 1 for k in frames if k > 1} - set(frames)) * len(models) * a.seeds
            done = "complete" if _complete(self.data / (dataset or name)) else "to generate"
            self.log(f"  {name:<28} dataset {done}; {n * len(trained) + extra} cells trained, {n * len(tested)} "
                     f"tested only ({len(models)} models x {len(frames)} n x {a.seeds} seeds"
                     + (f", and {extra} clean at n - 1)" if extra else ")"))

        self.log("plan (nothing is run):")
        for lv in a.control_levels:
            for onset in a.control_onset:
                line(f"control-{lv}" + ("" if onset == "detected" else f"-{onset}-onset"), a.control_models,
                     a.control_frames, f"control-{lv}")
        for lv in a.levels:
            line(lv, a.models)
        for s in a.severities:
            line(f"{a.severity_level}-s{s:g}", a.severity_models)

    def run(self) -> int:
        from stam.study import (control_markdown, control_verdict, level_markdown, load_results, mechanism_markdown,
                                mechanism_rows, mechanism_summary, onset_line)

        a = self.a
        self.out.mkdir(parents=True, exist_ok=True)
        control = {}
        texts = []
        for lv in a.control_levels:   # 1. the positive control, reported before anything else runs
            d = self.dataset(f"control-{lv}", lv, "--precontact", a.control_precontact)
            for onset in a.control_onset:
                name = f"control-{lv}" + ("" if onset == "detected" else f"-{onset}-onset")
                self.share_backbone(f"control-{lv}", name)
                self.experiment(name, d, a.control_models, a.control_frames, onset)
                res = load_results(self.out / name)
                control[name] = control_verdict(res)
                texts.append(control_markdown(f"{name}: --precontact {a.control_precontact}, {onset} onsets", control[name])
                             + "\n" + onset_line(res) + "\n")
                atomic_write_text(self.out / f"{name}.md", texts[-1])
                self.log(texts[-1])
        atomic_write_text(self.out / "control.md", "\n".join(texts))
        runs = {}
        for lv in a.levels:   # 2. every model on each level's own data
            self.experiment(lv, self.dataset(lv, lv), a.models, onset=a.onset)
            runs[lv] = load_results(self.out / lv)
            self.log(f"level {lv} done: {self.out / lv / 'differences.md'}")
        compares = self.compare(a.levels)   # 3.
        plot = self.severities()   # 4.
        rows = mechanism_rows(runs)   # 5.
        parts = ["# Nuisance robustness study (issue 48)", "",
                 f"`benchmarks/nuisance_study.py {' '.join(shlex.quote(x) for x in sys.argv[1:])}`", "",
                 "## 1. Positive control", "", open(self.out / "control.md").read(),
                 "## 2. Each level: every model against the CNN", ""]
        parts += [level_markdown(lv, res) + "\n" + onset_line(res) + "\n" for lv, res in runs.items()]
        parts += ["## 3. Mechanism table", "", mechanism_markdown(rows), *[f"- {s}" for s in mechanism_summary(rows)], ""]
        parts += ["## 4. Levels against the first (`stam compare`)", ""]
        parts += [f"- {lv}: [{p.name}]({p.name}): {summary}" for lv, (p, summary) in compares.items()]
        if plot:
            parts += ["", "## 5. Accuracy against severity", "", f"![severity]({plot.name})"]
        parts += ["", "## Cost (wall seconds on this machine)", "", costs_markdown(self.costs)]
        atomic_write_text(self.out / "report.md", "\n".join(parts) + "\n")
        atomic_write_json(self.out / "mechanism.json", rows)
        passed = [k for k, v in control.items() if v["passed"]]
        self.log(f"report: {self.out / 'report.md'} (positive control "
                 + (f"passed at {', '.join(passed)})" if passed else "failed: no oracle gain resolved)"))
        return 0

    def compare(self, levels) -> dict:
        from stam.compare import compare_runs, markdown

        out = {}
        for lv in levels[1:]:
            res = compare_runs(self.out / levels[0], self.out / lv)
            path = self.out / f"{lv}_vs_{levels[0]}.md"
            atomic_write_text(path, markdown(res))
            d = res["all_cells"]["difference"]
            out[lv] = (path, f"all {res['all_cells']['cells']} shared cells, {lv} − {levels[0]} "
                             f"{d['mean']:+.1f} [{d['ci95'][0]:+.1f}, {d['ci95'][1]:+.1f}] points")
        return out

    def severities(self) -> Path | None:
        a = self.a
        if not a.severities:
            return None
        points = []
        if "none" in a.levels:
            points.append(f"0={self.out / 'none'}")
        if a.severity_level in a.levels:
            manifest = json.loads((self.data / a.severity_level / "manifest.json").read_text())
            own = manifest.get("options", {}).get("nuisance_severity")
            # no severity given: every stage at its data file's value, severity 1 (gelsim/assets/nuisance.toml)
            points.append(f"{1.0 if own is None else float(own):g}={self.out / a.severity_level}")
        for s in a.severities:
            name = f"{a.severity_level}-s{s:g}"
            d = self.dataset(name, a.severity_level, "--nuisance-severity", f"{s:g}")
            self.experiment(name, d, a.severity_models, onset=a.onset)
            points.append(f"{s:g}={self.out / name}")
        plot = self.out / "severity.png"
        script = Path(__file__).with_name("nuisance_plot.py")
        r = subprocess.run([sys.executable, str(script), *points, "--out", str(plot),
                            "--title", f"{a.severity_level}: accuracy against severity"])
        if r.returncode != 0:
            raise GelsimError(f"{script.name} stopped with status {r.returncode}; rerun with the same options")
        return plot


def costs_markdown(costs: dict) -> str:
    lines = ["| step | generate | experiment | pretraining | trained cells: count, median, total | "
             "tested-only cells: count, median |", "|---|---|---|---|---|---|"]

    def s(v):
        return "–" if v is None else f"{v:,.0f} s" if v >= 10 else f"{v:.1f} s"

    for name, c in costs.items():
        pretrain = f"{c['backbone_from']}'s" if c.get("backbone_from") else s(c.get("pretrain_s"))
        lines.append(f"| {name} | {s(c.get('generate_s'))} | {s(c.get('experiment_s'))} | {pretrain} | "
                     f"{c.get('trained_cells', 0)}, {s(c.get('trained_cell_median_s'))}, "
                     f"{s(c.get('trained_cell_total_s'))} | {c.get('tested_cells', 0)}, "
                     f"{s(c.get('tested_cell_median_s'))} |")
    return "\n".join(lines) + "\n"


def parse(argv=None):
    from stam.config import SETTINGS
    from stam.models import MODELS
    from stam.study import CONTROL_MODELS, STUDY_MODELS, STUDY_SETTINGS, check_cuts

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__.split("\n\n", 2)[2])
    p.add_argument("--data", required=True, help="directory holding the datasets (made here when missing)")
    p.add_argument("--out", required=True, help="directory of the runs and the report")
    p.add_argument("--gen", default=SMALL_GEN,
                   help=f"gelsim generate options shared by every dataset [default: {SMALL_GEN!r}, a small "
                        "set for a first look; the study of docs/stam_study.md: '--preset cpu --resolution 960x720']")
    p.add_argument("--levels", nargs="+", default=["none", "handheld"],
                   help="nuisance levels (gelsim generate --nuisance), the first the reference [default: none handheld]")
    p.add_argument("--control-levels", nargs="+",
                   help="levels of the positive control's data [default: the last of --levels]")
    p.add_argument("--control-precontact", default="3-6",
                   help="the control's frames before contact, MIN-MAX (gelsim generate --precontact) [default: 3-6]")
    p.add_argument("--control-models", nargs="+", default=list(CONTROL_MODELS), choices=MODELS, metavar="MODEL",
                   help=f"models of the control [default: {' '.join(CONTROL_MODELS)}]")
    p.add_argument("--onset", choices=("detected", "true"), default="detected",
                   help="where the levels' clean windows start and what their oracle drops: the onset detected from "
                        "the images, as the paper (its agreement with the simulator's is in the report), or the "
                        "manifest's true one [default: detected]")
    p.add_argument("--control-onset", nargs="+", choices=("detected", "true"), default=["detected"],
                   help="where the control's clean windows start and what its oracle drops: the onset detected from "
                        "the images (the study's) and/or the manifest's true one (OUT/control-LEVEL-true-onset: the "
                        "gain with a perfect detector) [default: detected]")
    p.add_argument("--control-frames", nargs="+", type=int, default=[2, 3, 4, 5, 6, 7],
                   help="n of the control (two models: cheap; the larger n hold the contact frames that 3-6 frames "
                        "before contact leave out) [default: 2..7]")
    p.add_argument("--models", nargs="+", default=list(STUDY_MODELS), choices=MODELS, metavar="MODEL",
                   help=f"models at every level (stam experiment --models) [default: {' '.join(STUDY_MODELS)}]")
    p.add_argument("--frames", nargs="+", type=int, default=[2, 3, 4, 5, 6, 7],
                   help="n; 2, 4 and 6 are kept [default: 2..7]")
    p.add_argument("--settings", nargs="+", default=list(STUDY_SETTINGS), choices=SETTINGS,
                   help="clean, noisy (trained noisy, tested noisy), transfer (trained clean, tested noisy) "
                        "[default: all three]")
    p.add_argument("--seeds", type=int, default=3, help="seeds per cell [default: 3]")
    p.add_argument("--preset", default="cpu", help="stam preset [default: cpu]")
    p.add_argument("--pretrain-frames", choices=("all", "contact"), default="all",
                   help="frames each level's backbone is pretrained on [default: all, the frames before contact too]")
    p.add_argument("--severities", nargs="*", type=float, default=[],
                   help="extra severities of --severity-level for the plot (gelsim generate --nuisance-severity) "
                        "[default: none]")
    p.add_argument("--severity-level", help="the level whose severity is swept [default: the last of --levels]")
    p.add_argument("--severity-models", nargs="+", default=["cnn", "stam", "stam_paper", "oracle"], choices=MODELS,
                   metavar="MODEL", help="models of the severity runs [default: cnn stam stam_paper oracle]")
    p.add_argument("--threads", type=int, default=0,
                   help="torch threads for pretraining and features (the heads use the preset's) [default: torch's]")
    p.add_argument("--plan", action="store_true", help="print the datasets and cells, run nothing")
    p.add_argument("--verbose", action="store_true", help="stam experiment's progress lines")
    a = p.parse_args(argv)
    a.severity_level = a.severity_level or a.levels[-1]
    a.control_levels = a.control_levels or [a.levels[-1]]
    check_cuts(a.frames, a.levels, a.control_levels)
    for need in ("cnn",):
        if need not in a.models or need not in a.control_models:
            raise GelsimError(f"--models and --control-models must hold {need}, the baseline every contrast is against")
    if "oracle" not in a.control_models:
        raise GelsimError("--control-models must hold oracle: the control asks whether its gain over the CNN is resolved")
    if a.seeds < 1:
        raise GelsimError(f"--seeds must be at least 1, got {a.seeds}")
    return a


def main(argv=None) -> int:
    a = parse(argv)
    study = Study(a)
    if a.plan:
        study.plan()
        return 0
    if a.threads:
        import torch

        torch.set_num_threads(a.threads)
    return study.run()


if __name__ == "__main__":
    from gelsim.cli import run_script

    run_script(main)
