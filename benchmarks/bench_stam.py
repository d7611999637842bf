"""Training throughput of the three stam models, in sequences per second.

For each model and n, times forward + backward + SGD step on random windows of
``--batch`` sequences (whole model trained, as in the paper preset) and, with
``--frozen``, the head-only step on precomputed backbone features (the cpu preset).
Runs on the GPU when one is available (``--device``). Not a test: numbers depend on the
machine and its load; the load average is reported beside them.

    python benchmarks/bench_stam.py [--width 0.5] [--image-size 128] [--frames 2 7] [--json]
"""
from __future__ import annotations

import argparse
import os
import platform
import time

import torch

from gelsim.cli import print_result, run_script
from stam.models import MODEL_NAMES, build


def bench(name: str, n: int, args, device: torch.device, frozen: bool) -> float:
    torch.manual_seed(0)
    model = build(name, n, args.classes, width=args.width, image_size=args.image_size,
                  hidden=args.hidden).to(device).train()
    if frozen:
        model.backbone.requires_grad_(False)
        with torch.no_grad():
            x = model.frame_features(torch.randn(args.batch, n, 3, args.image_size, args.image_size, device=device))
        step_in = model.forward_features
    else:
        x = torch.randn(args.batch, n, 3, args.image_size, args.image_size, device=device)
        step_in = model
    y = torch.randint(0, args.classes, (args.batch,), device=device)
    opt = torch.optim.SGD([p for p in model.parameters() if p.requires_grad], lr=1e-3, momentum=0.9)

    def step():
        loss = torch.nn.functional.cross_entropy(step_in(x), y)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()

    for _ in range(args.warmup):
        step()
    if device.type == "cuda":
        torch.cuda.synchronize()
    t0 = time.perf_counter()
    for _ in range(args.steps):
        step()
    if device.type == "cuda":
        torch.cuda.synchronize()
    return args.batch * args.steps / (time.perf_counter() - t0)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--width", type=float, default=0.5, help="AlexNet channel multiplier (default 0.5, cpu preset)")
    p.add_argument("--image-size", type=int, default=128, help="px (default 128, cpu preset; the paper: 224)")
    p.add_argument("--frames", type=int, nargs="+", default=[2, 3, 4, 5, 6, 7], help="values of n (default 2..7)")
    p.add_argument("--models", nargs="+", default=list(MODEL_NAMES), choices=MODEL_NAMES)
    p.add_argument("--hidden", type=int, default=0, help="fc6/fc7 width (default 0 = 4096 x width; cpu preset 512)")
    p.add_argument("--batch", type=int, default=16, help="sequences per step (default 16)")
    p.add_argument("--classes", type=int, default=100, help="classes (default 100)")
    p.add_argument("--steps", type=int, default=5, help="timed steps (default 5)")
    p.add_argument("--warmup", type=int, default=1, help="untimed steps (default 1)")
    p.add_argument("--threads", type=int, default=0, help="torch CPU threads (default: torch's)")
    p.add_argument("--device", default="auto", help="auto, cpu or cuda (default auto)")
    p.add_argument("--frozen", action="store_true", help="also time head-only steps on precomputed features")
    p.add_argument("--json", action="store_true", help="print one JSON document")
    args = p.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    device = torch.device("cuda" if args.device == "auto" and torch.cuda.is_available() else
                          ("cpu" if args.device == "auto" else args.device))
    rows = []
    for name in args.models:
        for n in args.frames:
            row = {"model": name, "frames": n, "train_seq_per_s": round(bench(name, n, args, device, False), 2)}
            if args.frozen:
                row["head_only_seq_per_s"] = round(bench(name, n, args, device, True), 2)
            rows.append(row)
            if not args.json:
                print(f"{name:7s} n={n}: {row['train_seq_per_s']:8.2f} seq/s"
                      + (f", head only {row['head_only_seq_per_s']:9.1f} seq/s" if args.frozen else ""), flush=True)
    res = {"device": torch.cuda.get_device_name(0) if device.type == "cuda" else platform.processor() or "cpu",
           "threads": torch.get_num_threads(), "load_average": os.getloadavg(), "width": args.width,
           "image_size_px": args.image_size, "hidden": args.hidden, "batch": args.batch, "results": rows}
    return print_result(args.json, res, f"device {res['device']}, {res['threads']} threads, "
                        f"load average {res['load_average']}")


if __name__ == "__main__":
    run_script(main)
