"""Where a frame of the default dataset spends its CPU: the stages the records hold, and the steps inside them.

    python benchmarks/profile_frame.py [--fabrics 4] [--sequences-per-fabric 5] [--json]

Generates a sample of the default dataset (balanced, 960x720, H.264; the fabrics spread over the catalog as
``bench_generate.py`` spreads them) with one worker in this process, after a warm-up sample (compiled kernels
loaded, tables built), and reports CPU ms per frame (this thread's CPU time, which other processes on the
machine do not inflate):

* by stage, from the sequences' records (``fabric``, ``physics``, ``imprint``, ``markers``, ``optics``,
  ``encode``), as ``gelsim generate`` records them;
* by step inside the stages: each named function is wrapped by a thin timer for the run (a few microseconds per
  call), so a step's figure is its calls' CPU time including what they call. Steps nest (the texture stage is
  part of the two-scale press, which is part of the imprint): the table gives each its parent. A step whose
  function is not found (renamed, moved) is reported as missing rather than guessed.

The figures are per frame of the sample, in contact or not (the sample's frames are 90% in contact).
"""
from __future__ import annotations

import argparse
import functools
import importlib
import os
import shutil
import tempfile
import time
from pathlib import Path

from gelsim.cli import print_json, run_script

# (label, parent label, module, attribute path): the function as the caller looks it up (a name imported
# into another module is wrapped there).
STEPS = (
    ("imprint: press", "imprint", "gelsim.engines", "press"),
    ("two-scale press", "imprint: press", "gelsim.gel", "press_twoscale"),
    ("macro solve", "two-scale press", "gelsim.gel.twoscale", "solve_macro"),
    ("  crown pooling", "macro solve", "gelsim.gel.twoscale", "_crown_pool"),
    ("  contact solve on the cloth", "macro solve", "gelsim.gel.twoscale", "solve_on_cloth"),
    ("  layer convolutions (DFT)", "contact solve on the cloth", "gelsim.gel.layer", "Operator._conv"),
    ("texture stage", "two-scale press", "gelsim.gel.twoscale", "texture_depth"),
    ("  bearing cut", "texture stage", "gelsim.gel.twoscale", "_bearing_cut"),
    ("macro floor", "two-scale press", "gelsim.gel.texture_kernels", "macro_floor"),
    ("texture onto depth", "two-scale press", "gelsim.gel.twoscale", "TextureDepth.add_to"),
    ("cloth support (stiffness, operators)", "two-scale press", "gelsim.gel.twoscale", "cloth_stiffness"),
    ("cloth support (stiffness, operators)", "two-scale press", "gelsim.gel.twoscale", "cloth_operator"),
    ("membrane blur", "imprint: press", "gelsim.gel", "membrane_blur"),
    ("markers: displace", "markers", "gelsim.engines", "displace"),
    ("optics: render", "optics", "gelsim.optics", "Renderer.render_input"),
    ("shaded bands (compose)", "optics: render", "gelsim.optics.lut", "LutShader.compose"),
    ("  shadows and depth/halo terms", "shaded bands (compose)", "gelsim.optics.lut", "LutShader.term_parts"),
    ("  table lookup", "shaded bands (compose)", "gelsim.optics.lut", "lookup_rows"),
    ("  camera blur", "shaded bands (compose)", "gelsim.optics", "gaussian_blur"),
    ("  marker factors", "optics: render", "gelsim.optics.composite", "MarkerShading.prepare"),
    ("  markers drawn", "shaded bands (compose)", "gelsim.optics.composite", "MarkerShading.apply"),
    ("  noise and 8 bits", "shaded bands (compose)", "gelsim.optics.composite", "Readout.apply"),
    ("encode: video writer", "encode", "gelsim.video", "VideoWriter.write"),
    ("fabric: patch sample (per frame)", "fabric", "gelsim.scene", "HeightPatch.sample"),
    ("fabric: image patch (per sequence)", "fabric", "gelsim.sequence", "travel_patch"),
    ("fabric: physics surface (per sequence)", "fabric", "gelsim.sequence", "physics_surface"),
    ("fabric: crown envelope (per sequence)", "fabric", "gelsim.sequence", "crown_envelope_patch"),
    ("physics: contact simulation", "physics", "gelsim.sequence", "simulate"),
)


def _wrap(module: str, path: str, clock, seconds: dict, label: str) -> bool:
    """Wrap ``module.path`` to add its calls' ``clock`` seconds to ``seconds[label]``; False if not found."""
    try:
        obj = importlib.import_module(module)
    except ImportError:
        return False
    *owners, name = path.split(".")
    for o in owners:
        obj = getattr(obj, o, None)
        if obj is None:
            return False
    f = getattr(obj, name, None)
    if f is None or not callable(f):
        return False
    depth = [0]   # (a recursive call is not counted twice)

    @functools.wraps(f)
    def timed(*a, **k):
        if depth[0]:
            return f(*a, **k)
        depth[0] += 1
        t = clock()
        try:
            return f(*a, **k)
        finally:
            seconds[label] = seconds.get(label, 0.0) + clock() - t
            depth[0] -= 1

    setattr(obj, name, timed)
    return True


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--fabrics", type=int, default=4)
    ap.add_argument("--sequences-per-fabric", type=int, default=5)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    from gelsim.dataset import GenerateConfig, generate, summarize_timings
    from gelsim.errors import GelsimError
    from gelsim.runtime import configure_worker
    from gelsim.stream import stage_clock

    if args.fabrics < 1 or args.sequences_per_fabric < 1:
        raise GelsimError("--fabrics and --sequences-per-fabric must be at least 1")
    configure_worker()
    seconds: dict[str, float] = {}
    missing = [label for label, _, mod, path in STEPS if not _wrap(mod, path, stage_clock, seconds, label)]
    out = Path(tempfile.mkdtemp(prefix="gelsim-profile-frame-"))
    try:
        generate(GenerateConfig(fabrics=args.fabrics, sequences_per_fabric=1), out / "warm", workers=1, previews=False)
        seconds.clear()
        manifest = generate(GenerateConfig(fabrics=args.fabrics, sequences_per_fabric=args.sequences_per_fabric),
                            out / "ds", workers=1, previews=False)
        timing = summarize_timings(out / "ds", manifest)
    finally:
        shutil.rmtree(out, ignore_errors=True)
    frames = timing["frames"]
    stages = {k: round(v, 3) for k, v in timing["stages_ms_per_frame"].items()}
    parents = {label: parent for label, parent, _, _ in STEPS}
    steps = [{"step": label, "in": parents[label], "cpu_ms_per_frame": round(1000 * seconds.get(label, 0.0) / frames, 3)}
             for label in dict.fromkeys(label for label, _, _, _ in STEPS) if label not in missing]
    result = {"sample": {"fabrics": args.fabrics, "sequences": len(manifest["sequences"]), "frames": frames},
              "stages_cpu_ms_per_frame": stages, "cpu_ms_per_frame": round(sum(stages.values()), 3),
              "steps": steps, "missing_steps": missing, "load_avg": os.getloadavg()[0],
              "date": time.strftime("%Y-%m-%d %H:%M")}
    if args.json:
        print_json(result)
        return 0
    print(f"{frames} frames ({len(manifest['sequences'])} sequences), balanced 960x720; CPU ms per frame; "
          f"load average {result['load_avg']:.2f}")
    print("| stage | CPU ms |\n|---|---:|")
    for k, v in sorted(stages.items(), key=lambda kv: -kv[1]):
        print(f"| {k} | {v:.2f} |")
    print(f"| all | {result['cpu_ms_per_frame']:.2f} |")
    print("\n| step | within | CPU ms |\n|---|---|---:|")
    for s in steps:
        print(f"| {s['step']} | {s['in']} | {s['cpu_ms_per_frame']:.2f} |")
    if missing:
        print("not found (renamed or moved): " + ", ".join(missing))
    return 0


if __name__ == "__main__":
    run_script(main)
