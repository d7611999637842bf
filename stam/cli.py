"""The ``stam`` command line: a thin layer over stam's Python API.

Commands: info, onsets, pretrain, train, evaluate, experiment, compare, explain. Bad input prints
one line ``stam: error: <problem>; <fix>`` and exits with status 2.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from gelsim.atomic import out_folder
from gelsim.cli import ArgumentParser, HelpFormatter, dispatch, print_json, print_result, seed_arg

from . import __version__

#: ``--device``: auto (a CUDA device when there is one), cpu or cuda.
DEVICES = ("auto", "cpu", "cuda")


def _info(args) -> int:
    from . import models
    from .config import PretrainConfig, build_options

    build_options(PretrainConfig, {"width": args.width, "image_size": args.image_size})   # their ranges
    if args.classes < 1:
        from .errors import StamError

        raise StamError(f"--classes {args.classes} is out of range; give 1 or more fabric classes (the paper's 100)")
    opts = {"width": args.width, "image_size": args.image_size}
    n = models.parameter_count(args.model, args.frames, args.classes, **opts)
    paper_setting = args.width == 1.0 and args.image_size == 224 and args.classes == 100
    paper = models.PAPER_PARAMS.get(args.model) if paper_setting and (args.model == "cnn" or args.frames == 2) else None
    res = {"model": args.model, "frames": args.frames, "width": args.width, "image_size_px": args.image_size,
           "num_classes": args.classes, "params": n, "params_m": round(n / 1e6, 2),
           "paper_params_m": None if paper is None else paper / 1e6}
    if args.readings:
        res["paper_readings"] = models.paper_readings()
    if args.json:
        print_json(res)
    else:
        print(f"{args.model}, n={args.frames}, width {args.width}, {args.image_size} px, {args.classes} classes: "
              f"{n:,} parameters ({n / 1e6:.2f} M)"
              + (f"; paper: {paper / 1e6:.1f} M" if paper else ""))
        for r in res.get("paper_readings", []):
            print(f"  {r['params_m']:7.2f} M  {r['reading']}")
    return 0


def _onsets(args) -> int:
    from .config import TrainConfig, build_options
    from .data import DEFAULT_ONSET_THRESHOLD, TactileDataset

    build_options(TrainConfig, {"image_size": args.image_size})   # its range
    if not args.threshold > 0:
        from .errors import StamError

        raise StamError(f"--threshold {args.threshold:g} is out of range; give a change in DN > 0 (default "
                        f"{DEFAULT_ONSET_THRESHOLD:g})")

    res = TactileDataset(args.data).onset_agreement(args.image_size, args.threshold)
    if args.json:
        print_json(res)
        return 0
    n = res["sequences"]
    if not n:
        print("no sequence in the manifest has a contact_onset; nothing to compare")
        return 0

    def rate(k, ci):
        return f"{k}/{n} ({100 * k / n:.1f}%, 95% CI {100 * ci[0]:.1f}-{100 * ci[1]:.1f}%)"

    print(f"onset detection (threshold {res['threshold_dn']:g} DN) against the manifest's contact_onset, {n} sequences:")
    print(f"  exact          {rate(res['exact'], res['exact_ci95'])}")
    print(f"  within 1 frame {rate(res['within_1'], res['within_1_ci95'])}")
    print(f"  not detected   {res['not_detected']}")
    print("  detected - true (frames): " + ", ".join(f"{e}: {c}" for e, c in res["error_histogram"].items()))
    labels = {"true_onset_0": "true onset at frame 0 (detectable at 1 at the earliest)",
              "true_onset_1_plus": "true onset at frame 1 or later"}
    for name, g in res["by_true_onset"].items():
        if g["sequences"]:
            print(f"  {labels[name]}: {g['sequences']} sequences, exact {g['exact']}, within 1 {g['within_1']}")
    print("  confusion (true onset: detected onset x count):")
    for t, row in res["confusion"].items():
        print(f"    {t:>3}: " + " ".join(f"{d}x{c}" for d, c in row.items()))
    return 0


def _pretrain(args) -> int:
    from .config import PretrainConfig, build_options
    from .data import load_manifest
    from .train import pretrain

    build_options(PretrainConfig, {"width": args.width, "image_size": args.image_size, "epochs": args.epochs,
                                   "batch_size": args.batch_size, "lr": args.lr, "optimizer": args.optimizer,
                                   "seed": args.seed})
    load_manifest(args.data)        # before anything is written

    with out_folder(args.out):
        res = pretrain(args.data, args.out, width=args.width, image_size=args.image_size, epochs=args.epochs,
                       batch_size=args.batch_size, lr=args.lr, optimizer=args.optimizer, seed=args.seed,
                       contact_only=not args.all_frames, device=args.device, progress=not args.quiet, crop=args.crop,
                       log=None if args.json or args.quiet else print)
    return print_result(args.json, res, f"backbone: {res['path']} (validation frame accuracy {res['val_acc']:.3f})")


def _train(args) -> int:
    from .ranks import one_line_per_rank
    from .train import run_train

    from .data import load_manifest
    from .errors import StamError

    load_manifest(args.data)        # a bad --data is said before anything else (the config's note)
    if args.pretrained and args.pretrained != "none" and not args.dry_run and not Path(args.pretrained).is_file():
        raise StamError(f"--pretrained {args.pretrained} not found; give the backbone.pt of `stam pretrain`, or none")
    overrides = {"model": args.model, "frames": args.frames, "start": args.start, "epochs": args.epochs,
                 "seed": args.seed}
    if args.quiet or args.json:
        overrides["progress"] = False
    with one_line_per_rank(), out_folder(args.out):   # under torchrun: every rank's stop is one line
        res = run_train(args.data, args.out, preset=args.preset, overrides=overrides, sets=args.set,
                        pretrained=args.pretrained, resume=args.resume, dry_run=args.dry_run,
                        log=None if args.json or args.quiet else print,
                        note=None if args.quiet else (lambda m: print(m, file=sys.stderr)))
    if res.get("rank", 0):
        return 0  # under torchrun, rank 0 reports for the job
    if args.json:
        print_json(res)
    elif args.dry_run:
        print(f"config {res['preset']}" + (" (chosen by default)" if res["preset_chosen_by_default"] else ""))
        if res["pretrain"]:
            print("pretrain: " + ", ".join(f"{k}={v}" for k, v in res["pretrain"].items()))
        print("train: " + ", ".join(f"{k}={v}" for k, v in res["config"].items()))
    else:
        print(f"best validation accuracy {res['best_val_acc']:.3f} at epoch {res['best_epoch']}: {res['best']}")
    return 0


def _evaluate(args) -> int:
    from .evaluate import evaluate

    with out_folder(args.out or "."):
        res = evaluate(args.checkpoint, args.data, args.split, out=args.out, device=args.device)
    return print_result(args.json, res, f"{res['split']} accuracy {res['accuracy']:.4f} ({res['count']} windows), "
                        f"mean per-class {res['mean_class_accuracy']:.4f}; confusion matrix: {res['confusion_png']}")


def _experiment(args) -> int:
    from .experiment import run_experiment

    if args.ray is not None:
        from gelsim.cluster import import_ray

        import_ray()  # not installed: one line, before anything is written
    from .errors import StamError

    if args.seeds is not None and args.seeds < 1:
        raise StamError(f"--seeds {args.seeds} is out of range; give 1 or more seeds per cell")
    if args.frames and min(args.frames) < 1:
        raise StamError(f"--frames {' '.join(map(str, args.frames))}: n must be at least 1; give e.g. 2 3 4")
    stdout = sys.stdout  # progress lines stay on stdout while Ray's own messages go to stderr (gelsim.cluster)
    overrides = {"attention_at": args.attention_at} if args.attention_at else None
    pretrain = None if args.pretrain_frames is None else {"contact_only": args.pretrain_frames == "contact"}
    with out_folder(args.out):
        res = run_experiment(args.data, args.out, args.preset, args.seeds, args.models, args.frames, args.settings,
                             overrides=overrides, log=None if args.json else (lambda m: print(m, file=stdout)),
                             note=lambda m: print(m, file=sys.stderr), ray=args.ray, pretrain_overrides=pretrain,
                             clean_extra=args.clean_frames)
    if args.json:
        print_json({k: v for k, v in res.items() if k != "cells"} | {"cells": len(res["cells"])})
    else:
        for k in ("table1", "table2", "table2_transfer", "differences_table"):
            if k in res:
                print(open(res[k]).read())
        print(f"plot: {res['plot']}")
    return 0


def _compare(args) -> int:
    from gelsim.atomic import atomic_write_text

    from .compare import compare_runs, markdown

    res = compare_runs(args.run_a, args.run_b)
    text = markdown(res)
    if args.out:
        atomic_write_text(args.out, text)
        res["markdown"] = str(args.out)
    return print_result(args.json, res, text.rstrip("\n"))


def _explain(args) -> int:
    from .explain import explain

    with out_folder(args.out):
        res = explain(args.checkpoint, args.sequence, args.out, args.data, args.split)
    return print_result(args.json, res, "\n".join(res["files"]))


MODEL_HELP = ("cnn, cnn_sa, stam (the paper's three), or a named variant: cnn_mean_features, cnn_max_features "
              "(the baseline's fusions), cnn_flatten (one FC on the flattened window, no per-frame head), "
              "cnn_joint (per-frame head + FC on the flattened window: STAM-paper's head without attention), "
              "stam_paper (full-width q, k, v and that head: 68.88 M parameters at the paper's size), oracle "
              "(the CNN on the frames from the detected onset on only)")

TRAIN_HELP = """train one model (writes config.json, log.csv, last.pt, best.pt)

The configuration is --config (a TOML file of stam/configs/ or a path: [pretrain] and [train]),
then --model/--frames/--start/--epochs/--seed, then --set KEY=VALUE. --config quick trains a first
model on `gelsim generate --preset quick`'s dataset in minutes (docs/quickstart.md). Without --config:
  * no CUDA device: the cpu config. AlexNet at width 0.5 on the central half of each frame at
    128 px; its backbone is pretrained once on single training frames (16 epochs) and then
    frozen, so only the attention modules and the head are trained. Measured on the 2,000
    sequences of `gelsim generate --preset cpu` on 2 cores: pretraining took 28 min and reached
    36.3% single-frame validation accuracy (100 classes, chance 1%); a model then trains in
    8-70 s (STAM: 24.5% test accuracy at n = 2, 49.1% at n = 7).
    Reruns and --resume reuse the backbone. The library's own defaults (full AlexNet from
    scratch at 224 px, 58 M parameters) took 3-4 min per epoch there and were still at chance
    (1%) after 2 of their 30 epochs.
  * a CUDA device: the paper config (full AlexNet at 224 px, pretrained, fine-tuned end to end).
One line on stderr says which was chosen. The resolved configuration is saved in OUT/config.json;
--resume continues with it."""


def experiment_help() -> str:
    from . import stats

    need = ", ".join(f"{d} point{'s' * (d != 1)}: {stats.required_test_size(d / 100):,}" for d in (5, 3, 2, 1))
    return f"""the Tables I/II sweep: 3 models x n = 2..7 x clean/noisy x seeds, with 95% CIs (resumable)

Writes OUT/table1.md and OUT/table2.md (test accuracy, mean over seeds [95% CI], beside the
paper's figure), OUT/differences.md (the paper's comparisons STAM - CNN, CNN+SA - CNN and
noisy - clean as paired differences with 95% CIs, bold where the CI excludes 0; noisy/clean
ratios; what the frames before contact cost once the contact frames are matched: noisy n
against clean n - onset, the same contact frames; the resolution reached), OUT/tables.png
(CIs as error bars) and OUT/results.json.

Intervals: percentile bootstrap over the test sequences ({stats.BOOTSTRAP_RESAMPLES:,} resamples, fixed seed).
Each sequence's correctness is averaged over the seeds first, so its seed-to-seed flips are
inside the interval; every statistic uses the same resamples, so differences between models,
n and settings are paired. A seed can also move a whole cell; that shift's variance, measured
across the seeds and pooled over the cells, is added to each interval.

Test size: an observed difference of d points is resolved (its CI excludes 0) when the CI's
half-width, 1.96 sqrt(v / N) on N test sequences, is below d: N >= (1.96 / d)^2 v; finding a
true difference of d with 80% power takes about twice that. Here v is the variance over
sequences of the per-sequence difference in correctness: {stats.PLANNING_DIFFERENCE_VARIANCE} for two models
whose correctness differs on a quarter of the sequences (less after averaging over seeds).
Then {need} test sequences.
`gelsim generate --preset cpu` has 1,100 (11 per fabric, --split 7:2:11).
With fewer than {stats.MIN_TEST_SEQUENCES} test sequences it warns; differences.md states the half-width reached."""


def build_parser() -> argparse.ArgumentParser:
    from .config import SETTINGS
    from .data import DEFAULT_ONSET_THRESHOLD
    from .models import MODELS

    p = ArgumentParser(prog="stam", formatter_class=HelpFormatter,
                                description="STAM tactile texture recognition (Cao et al., IROS 2020) on gelsim datasets.")
    p.add_argument("--version", action="version", version=f"stam {__version__}")
    sub = p.add_subparsers(dest="command", metavar="COMMAND")

    def cmd(name, handler, help_, description=None):
        # argparse %-formats the help of the command list (not descriptions): "95%" must be escaped there.
        s = sub.add_parser(name, help=help_.replace("%", "%%"), description=description or help_,
                           formatter_class=HelpFormatter)
        s.set_defaults(handler=handler)
        s.add_argument("--json", action="store_true", help="print one JSON document on stdout")
        return s

    s = cmd("info", _info, "parameter count of a model (beside the paper's figure at its setting)")
    s.add_argument("--model", choices=MODELS, required=True, help=MODEL_HELP)
    s.add_argument("--frames", type=int, default=2, help="n, frames per window")
    s.add_argument("--width", type=float, default=1.0, help="AlexNet channel multiplier (1.0 = full)")
    s.add_argument("--image-size", type=int, default=224, help="input side in px")
    s.add_argument("--classes", type=int, default=100, help="number of fabric classes")
    s.add_argument("--readings", action="store_true", help="also list the counts of several readings of the paper")

    s = cmd("onsets", _onsets, "how often the contact onset detected from the images matches the manifest's "
            "contact_onset: exact and within-one-frame rates with 95% intervals, error histogram, confusion")
    s.add_argument("--data", required=True, help="dataset directory (gelsim generate --out)")
    s.add_argument("--threshold", type=float, default=DEFAULT_ONSET_THRESHOLD, help="contact score threshold, DN (0-255) of RGB change per frame (from frame 0: twice that)")
    s.add_argument("--image-size", type=int, default=128, help="px, size of the frame cache filled on the way")

    s = cmd("pretrain", _pretrain, "pretrain the AlexNet backbone on single training frames (stand-in for ImageNet)")
    s.add_argument("--data", required=True, help="dataset directory")
    s.add_argument("--out", required=True, help="output directory (writes backbone.pt)")
    s.add_argument("--width", type=float, default=1.0, help="AlexNet channel multiplier")
    s.add_argument("--image-size", type=int, default=224, help="input side in px")
    s.add_argument("--crop", type=float, default=1.0,
                   help="keep a centred square of this fraction of the frame's shorter side before resizing")
    s.add_argument("--epochs", type=int, default=10, help="epochs")
    s.add_argument("--batch-size", type=int, default=64, help="frames per step")
    s.add_argument("--lr", type=float, default=0.001, help="learning rate (cosine decay); the cpu config uses 3e-4, at which 3 of 3 seeds took off "
                        "(1e-3 stalled at chance on 2 of 3; a stalled run is told so after epoch 3)")
    s.add_argument("--optimizer", choices=("adam", "sgd"), default="adam", help="optimizer (sgd: momentum 0.9)")
    s.add_argument("--seed", type=seed_arg, default=0, help="random seed")
    s.add_argument("--all-frames", action="store_true", help="also use frames before the detected contact")
    s.add_argument("--device", default="auto", choices=DEVICES, help="where to train")
    s.add_argument("--quiet", action="store_true", help="no progress output")

    s = cmd("train", _train, TRAIN_HELP)
    s.add_argument("--config", dest="preset", metavar="NAME|PATH",
                   help="quick, cpu, paper, or a .toml file with [pretrain]/[train] sections (stam/configs/); "
                        "default: paper with a CUDA device, cpu without (see above)")
    s.add_argument("--preset", dest="preset", help=argparse.SUPPRESS)   # the old spelling of --config
    s.add_argument("--data", required=True, help="dataset directory")
    s.add_argument("--out", required=True, help="run directory")
    s.add_argument("--model", choices=MODELS, help=MODEL_HELP + " (default: the config's, stam)")
    s.add_argument("--frames", type=int, help="n, frames per window (default: the config's, 2)")
    s.add_argument("--start", choices=("contact", "zero"), help="window start: first contact frame (clean) or frame 0 (noisy)")
    s.add_argument("--epochs", type=int, help="epochs (default: the config's: quick 20, cpu 12, paper 30)")
    s.add_argument("--seed", type=seed_arg, help="random seed (default: the config's, 0)")
    s.add_argument("--pretrained", metavar="PATH|none",
                   help="backbone.pt from `stam pretrain`, or none for random weights (default: the config's "
                        "[pretrain] step, run once into OUT/pretrain/)")
    s.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override any [train] key of the config, e.g. lr=0.001 (repeatable)")
    s.add_argument("--resume", action="store_true", help="continue from OUT/last.pt (with the config in OUT/config.json)")
    s.add_argument("--dry-run", action="store_true", help="print the resolved config; train nothing")
    s.add_argument("--quiet", action="store_true", help="no progress output")

    s = cmd("evaluate", _evaluate, "accuracy, per-class accuracy and confusion matrix (PNG) of a checkpoint")
    s.add_argument("--checkpoint", required=True, help="best.pt or last.pt of a run")
    s.add_argument("--data", help="dataset directory (default: the one the run was trained on)")
    s.add_argument("--split", choices=("train", "val", "test"), default="test", help="split to evaluate")
    s.add_argument("--out", help="directory for eval-<split>.json and confusion-<split>.png (default: the run's)")
    s.add_argument("--device", default="auto", choices=DEVICES, help="where to evaluate")

    s = cmd("experiment", _experiment, "the Tables I/II sweep: 3 models x n = 2..7 x clean/noisy x seeds, "
            "with 95% CIs (resumable)", experiment_help())
    s.add_argument("--data", required=True, help="dataset directory")
    s.add_argument("--out", required=True, help="output directory")
    s.add_argument("--config", dest="preset", default="cpu", metavar="NAME|PATH",
                   help="cpu (2 CPU cores), paper (GPU), quick (a small sweep of the quick dataset), or a .toml path")
    s.add_argument("--preset", dest="preset", default="cpu", help=argparse.SUPPRESS)   # the old spelling of --config
    s.add_argument("--seeds", type=int, help="seeds per cell (default from the config: cpu 3, paper 1)")
    s.add_argument("--models", nargs="+", choices=MODELS, metavar="MODEL",
                   help="models (default the config's: cnn, cnn_sa, stam); " + MODEL_HELP)
    s.add_argument("--frames", nargs="+", type=int, help="subset of n (default 2..7)")
    s.add_argument("--settings", nargs="+", choices=SETTINGS,
                   help="clean (trained and tested on windows from the detected onset), noisy (from frame 0), "
                        "transfer (the clean models tested from frame 0: trains the clean cells too) "
                        "(default the preset's: clean noisy)")
    s.add_argument("--clean-frames", nargs="+", type=int, metavar="N",
                   help="more n for the clean setting only, e.g. each n - 1 of --frames: a window from frame 0 that "
                        "starts o frames before contact holds the clean window of n - o frames, so its frames before "
                        "contact can be costed against it (differences.md) when --frames skips n (default none)")
    s.add_argument("--pretrain-frames", choices=("contact", "all"),
                   help="the frames the backbone is pretrained on: contact (from the detected onset on) or all "
                        "(the frames before contact too, as a model trained on noisy windows meets them) "
                        "(default the preset's [pretrain] contact_only: cpu, contact)")
    s.add_argument("--attention-at", choices=("pool5", "conv5"),
                   help="where the attention reads the backbone: pool5, after its last max-pool (the paper's F; "
                        "the configs' default), or conv5, before it, the pool following the attention (7 x 7 "
                        "positions per frame at the cpu config's 128 px instead of 3 x 3; the CNN is the same "
                        "function). Use a new --out for each")
    s.add_argument("--ray", nargs="?", const="local", metavar="ADDRESS",
                   help="train the cells as Ray tasks (one CPU each, or the config's threads; a GPU with device "
                        "cuda): alone, on a Ray instance started here; 'auto' or HOST:PORT, on that cluster, "
                        "whose nodes must mount --data and --out at the same paths (checked first). "
                        "Pretraining stays here. Same results as a local run with the same threads; needs `make ray`")

    s = cmd("compare", _compare, "two `stam experiment` runs on the same test sequences, cell by cell: "
            "B - A with paired 95% CIs, per n and averaged over n, and the change in attention's gain over the CNN",
            """two `stam experiment` runs on the same test sequences, cell by cell

For each cell (setting, n, model) that both runs have: the accuracies and the paired difference
B - A in points with its 95% CI, per n and averaged over n; the attention models' gain over the
CNN in each run and its change; and all shared cells averaged (a run-wide shift, such as another
backbone's, moves every cell together). Intervals as `stam experiment`'s: a bootstrap over the
shared test sequences (each run's seeds averaged, the same resamples for every statistic), widened
by each run's seed shift. The runs must have tested the same sequences: datasets made with the
same `gelsim generate` plan (for instance the same options at another --resolution).

  stam compare out/tables-320 out/tables-960 --out out/960-vs-320.md""")
    s.add_argument("run_a", metavar="A", help="the --out directory of the first run (the baseline)")
    s.add_argument("run_b", metavar="B", help="the --out directory of the second run")
    s.add_argument("--out", help="also write the markdown tables to this file")

    s = cmd("explain", _explain, "Grad-CAM per frame and STAM's temporal attention map for one window (PNG)")
    s.add_argument("--checkpoint", action="append", required=True, help="best.pt of a run (repeatable: cnn, cnn_sa, stam)")
    s.add_argument("--data", help="dataset directory (default: the one the first run was trained on)")
    s.add_argument("--sequence", help="sequence id (default: the split's first)")
    s.add_argument("--split", choices=("train", "val", "test"), default="test", help="split the sequence is taken from")
    s.add_argument("--out", default=".", help="output directory for gradcam.png and temporal.png")
    return p


def main(argv: list[str] | None = None) -> int:
    return dispatch(build_parser(), argv, interrupted="rerun the same command (train: with --resume) to continue")


if __name__ == "__main__":
    sys.exit(main())
