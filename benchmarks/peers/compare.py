"""gelsim's fast renderer beside the peer simulators taxim and tacto: ms per frame on the same height maps.

Runs each simulator's runner in its own venv (run_ours.py with this Python,
run_taxim.py and run_tacto.py with the venvs from setup_envs.sh), on one core
(taskset -c 0 and every thread pool at 1) and with the tools' defaults, then
prints a Markdown table (or one JSON document with --json). Not part of the
test suite.

    benchmarks/peers/setup_envs.sh
    .venv/bin/python benchmarks/peers/compare.py [--modes one-core,default] [--frames 10] [--json]
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
DEFAULT_ENVS = Path(os.environ.get("GELSIM_PEERS_DIR", Path.home() / ".cache" / "gelsim-peers"))
PEERS = ("ours", "taxim", "tacto-egl", "tacto-osmesa")
MODES = ("one-core", "default")
THREAD_VARS = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMEXPR_NUM_THREADS",
               "LP_NUM_THREADS", "XLA_FLAGS", "PYOPENGL_PLATFORM")
# one-core settings: BLAS/OpenMP pools, Mesa llvmpipe's raster threads, XLA's CPU thread pool
ONE_CORE_ENV = {"OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1",
                "NUMEXPR_NUM_THREADS": "1", "LP_NUM_THREADS": "1",
                "XLA_FLAGS": "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"}
# the comparison the task sets: our fast level at least this many times faster at equal resolution
TARGET_SPEEDUP = 10.0


def runner_command(peer: str, envs: Path) -> tuple[list[str], dict]:
    if peer == "ours":
        return [sys.executable, str(HERE / "run_ours.py")], {}
    if peer == "taxim":
        return [str(envs / "taxim" / "bin" / "python"), str(HERE / "run_taxim.py")], {}
    if peer.startswith("tacto-"):
        return ([str(envs / "tacto" / "bin" / "python"), str(HERE / "run_tacto.py")],
                {"PYOPENGL_PLATFORM": peer.split("-", 1)[1]})
    raise SystemExit(f"compare.py: unknown peer {peer!r}; choose from {', '.join(PEERS)}")


def run_one(peer: str, mode: str, args) -> dict:
    cmd, extra = runner_command(peer, args.envs_dir)
    if not Path(cmd[0]).exists():
        return {"peer": peer, "mode": mode, "error": f"{cmd[0]} missing; run benchmarks/peers/setup_envs.sh"}
    env = {k: v for k, v in os.environ.items() if k not in THREAD_VARS}
    env.update(extra)
    if mode == "one-core":
        env.update(ONE_CORE_ENV)
        if shutil.which("taskset"):
            cmd = ["taskset", "-c", str(args.core)] + cmd
    warmup = args.warmup if peer in ("ours", "taxim") else args.gl_warmup
    cmd += ["--frames", str(args.frames), "--warmup", str(warmup), "--png-dir", args.png_dir]
    if args.only:
        cmd += ["--only", args.only]
    load0 = os.getloadavg()
    t0 = time.time()
    print(f"[{time.strftime('%H:%M:%S')}] {mode}: {peer} (load {load0[0]:.2f})", file=sys.stderr, flush=True)
    p = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=args.timeout)
    out = {"peer": peer, "mode": mode, "command": " ".join(cmd), "wall_s": round(time.time() - t0, 1),
           "loadavg_before": [round(v, 2) for v in load0], "loadavg_after": [round(v, 2) for v in os.getloadavg()]}
    if p.returncode != 0:
        out["error"] = f"exit {p.returncode}: " + p.stderr.strip()[-2000:]
        return out
    doc = json.loads(p.stdout.strip().splitlines()[-1])
    out.update(doc)
    return out


def table(runs: list[dict]) -> str:
    """Markdown: every peer case beside ours (render, and press+render) at the same mode, size and scene."""
    ours = {}
    for run in runs:
        if run["peer"] == "ours":
            for r in run.get("results", []):
                ours[(run["mode"], r["width"], r["height"], r["scene"], r["variant"])] = r["ms_median"]
    lines = ["| mode | resolution | scene | peer (variant) | peer ms/frame | ours render ms | speed-up "
             "| ours press+render ms | speed-up |",
             "|---|---|---|---|---:|---:|---:|---:|---:|"]
    for run in runs:
        if run["peer"] == "ours":
            continue
        if "error" in run:
            lines.append(f"| {run['mode']} | | | {run['peer']}: FAILED | | | | | |")
            continue
        for r in run["results"]:
            key = (run["mode"], r["width"], r["height"], r["scene"])
            o1, o2 = ours.get(key + ("render",)), ours.get(key + ("press+render",))
            ms = r["ms_median"]
            f = lambda v: "n/a" if v is None else f"{v:.1f}"  # noqa: E731
            s = lambda v: "n/a" if v is None else f"{ms / v:.0f}x"  # noqa: E731
            lines.append(f"| {run['mode']} | {r['width']}x{r['height']} | {r['scene']} | {r['peer']} {r['variant']} "
                         f"| {ms:.0f} | {f(o1)} | {s(o1)} | {f(o2)} | {s(o2)} |")
    lines += ["", "| mode | resolution | scene | ours variant | ms/frame (median) | p10-p90 |",
              "|---|---|---|---|---:|---|"]
    for run in runs:
        if run["peer"] == "ours" and "results" in run:
            for r in run["results"]:
                lines.append(f"| {run['mode']} | {r['width']}x{r['height']} | {r['scene']} | {r['variant']} "
                             f"| {r['ms_median']:.1f} | {r['ms_p10']:.1f}-{r['ms_p90']:.1f} |")
    return "\n".join(lines)


def summary(runs: list[dict]) -> list[dict]:
    """Per mode, size and scene: the fastest peer case against ours (render), and whether the target holds."""
    ours, peers = {}, {}
    for run in runs:
        for r in run.get("results", []):
            key = (run["mode"], f"{r['width']}x{r['height']}", r["scene"])
            if run["peer"] == "ours":
                if r["variant"] == "render":
                    ours[key] = r["ms_median"]
            else:
                name = f"{r['peer']} {r['variant']}"
                best = peers.setdefault(key, {}).get(r["peer"])
                if best is None or r["ms_median"] < best[1]:
                    peers[key][r["peer"]] = (name, r["ms_median"])
    out = []
    for key, by_peer in peers.items():
        for peer, (name, ms) in by_peer.items():
            o = ours.get(key)
            out.append({"mode": key[0], "resolution": key[1], "scene": key[2], "peer": peer,
                        "fastest_variant": name, "peer_ms": round(ms, 2), "ours_ms": None if o is None else round(o, 2),
                        "speedup": None if o is None else round(ms / o, 1),
                        "meets_10x": None if o is None else ms / o >= TARGET_SPEEDUP})
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--modes", default=",".join(MODES), help="comma-separated: one-core, default (default both)")
    ap.add_argument("--peers", default=",".join(PEERS), help=f"comma-separated subset of {', '.join(PEERS)} "
                                                             "(default all)")
    ap.add_argument("--frames", type=int, default=10, help="timed frames per case, count (default 10)")
    ap.add_argument("--warmup", type=int, default=3, help="untimed frames first (JIT), gelsim and taxim (default 3)")
    ap.add_argument("--gl-warmup", type=int, default=1, help="untimed frames first, tacto (default 1)")
    ap.add_argument("--core", type=int, default=0, help="CPU for the one-core mode (default 0)")
    ap.add_argument("--only", default="", help="case filter passed to the runners, e.g. 640x480/sphere (default all)")
    ap.add_argument("--envs-dir", type=Path, default=DEFAULT_ENVS,
                    help="where setup_envs.sh put the venvs (default $GELSIM_PEERS_DIR or ~/.cache/gelsim-peers)")
    ap.add_argument("--png-dir", default=os.environ.get("TMPDIR", "/tmp"),
                    help="one PNG per case goes here (default $TMPDIR or /tmp)")
    ap.add_argument("--timeout", type=float, default=3600, help="per runner, s (default 3600)")
    ap.add_argument("--save", type=Path, help="also write the JSON document to this file")
    ap.add_argument("--json", action="store_true", help="print one JSON document instead of the tables")
    ap.add_argument("--from", dest="from_files", type=Path, nargs="+",
                    help="instead of measuring, merge documents saved with --save (a peer and mode found in "
                         "several: the last file's run wins) and print or --save/--json the result")
    args = ap.parse_args(argv)
    if args.from_files:
        merged = {}
        for f in args.from_files:
            for run in json.loads(f.read_text())["runs"]:
                merged[(run["peer"], run["mode"])] = run
        runs = sorted(merged.values(), key=lambda r: (MODES.index(r["mode"]), PEERS.index(r["peer"])))
        doc = {"target_speedup": TARGET_SPEEDUP, "merged_from": [str(f) for f in args.from_files],
               "summary": summary(runs), "runs": runs}
        return finish(doc, runs, args)
    os.makedirs(args.png_dir, exist_ok=True)
    runs = []
    for mode in args.modes.split(","):
        if mode not in MODES:
            ap.error(f"unknown mode {mode!r}; choose from {', '.join(MODES)}")
        for peer in args.peers.split(","):
            runs.append(run_one(peer, mode, args))
    up = subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()
    doc = {"target_speedup": TARGET_SPEEDUP, "nproc": os.cpu_count(), "uptime_end": up,
           "summary": summary(runs), "runs": runs}
    return finish(doc, runs, args)


def finish(doc: dict, runs: list[dict], args) -> int:
    if args.save:
        from gelsim.atomic import atomic_write_text

        atomic_write_text(args.save, json.dumps(doc, indent=1))
    if args.json:
        print(json.dumps(doc))
    else:
        print(table(runs))
        print("\nload average (1, 5, 15 min) before each run:")
        for r in runs:
            print(f"  {r['mode']:8s} {r['peer']:13s} {r.get('loadavg_before')}  "
                  f"(gelsim {r.get('versions', {}).get('gelsim_commit', '-')})")
    return 1 if any("error" in r for r in runs) else 0


if __name__ == "__main__":
    sys.exit(main())
