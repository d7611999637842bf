"""The level table's reports: bench.md (:func:`markdown_table`), bench.json and bench_pareto.png
(:func:`write_reports`)."""
from __future__ import annotations

from pathlib import Path

from ..atomic import atomic_write_json, atomic_write_text, write_figure
from ..errors import GelsimError
from .runs import TIMED_STAGES


def runs_of(doc: dict) -> list[dict]:
    """The single-resolution results in a :func:`run_benches` document (or a single result)."""
    return doc["runs"] if "runs" in doc else [doc]


def fmt(v, nd: int) -> str:
    if v is None:
        return "-"
    return f"{v:.{nd}f}"


def _ratio(lv: dict, name: str) -> str:
    v, lo, hi = lv.get(name), lv.get(f"{name}_min"), lv.get(f"{name}_max")
    if v is None:
        return "-"
    return f"{v:.2f}" if lo is None or hi is None or hi - lo < 0.005 else f"{v:.2f} ({lo:.2f}-{hi:.2f})"


def _header(r: dict) -> str:
    s = r["settings"]
    w, h = s["resolution"]
    cached = sum(lv.get("cached_scenes", 0) for lv in r["levels"])
    return (f"{w}x{h} px, {len(s['scenes'])} scenes ({', '.join(s['scenes'])}), {s['frames']} frames each "
            f"({s['precontact']} before contact), errors against `{s['reference']}` on the same contact; "
            f"{s['cpu_count']} CPUs, load average {s['load_avg']}, {s['date']}, {s.get('bench_seconds', '?')} s in all"
            + (f" ({s['bench_cpu_seconds']} s of CPU)" if "bench_cpu_seconds" in s else "")
            + (f"; {cached} level-scene runs read from the cache (their times are those measured when they ran)"
               if cached else "") + ".")


def markdown_table(doc: dict) -> str:
    """The bench result (one :func:`run_bench` result or a :func:`run_benches` document) as Markdown:
    per resolution, the level table (texture, contact, markers, force, image), the texture ratios
    per scene, the time by stage and the shortcut table."""
    lines = []
    for r in runs_of(doc):
        s = r["settings"]
        w, h = s["resolution"]
        levels = r["levels"]
        lines += [f"### {w}x{h}", "", "Bench: " + _header(r), "",
                  "| level | CPU ms/frame | kept relief | image texture, fast shader | image texture, own renderer "
                  "| contact area err | marker err (mm) | in contact (mm) | force err (N) | image L1 (DN) | PSNR (dB) "
                  "| SSIM |",
                  "|---" * 12 + "|"]
        for lv in levels:
            lines.append(f"| {lv['name']} | {lv['cpu_ms_per_frame']:.1f} | {_ratio(lv, 'kept_relief')} | "
                         f"{_ratio(lv, 'image_texture_fast')} | {_ratio(lv, 'image_texture')} | "
                         f"{fmt(lv.get('contact_area_err'), 3)} | "
                         f"{fmt(lv['marker_err_mm'], 4)} | {fmt(lv.get('marker_err_contact_mm'), 4)} | "
                         f"{fmt(lv['force_err_n'], 4)} | {fmt(lv['image_l1'], 3)} | {fmt(lv['psnr'], 2)} | "
                         f"{fmt(lv['ssim'], 4)} |")
        fabric_scenes = [sc for sc in s["scenes"] if any(
            p["scene"] == sc and p.get("kept_relief") is not None for lv in levels for p in lv.get("per_scene", []))]
        if fabric_scenes:
            lines += ["", "Texture per scene, kept relief / image texture through the fast shader / through the "
                      "level's own renderer (ratios to the reference; contact-area error in brackets):", "", "| scene | " + " | ".join(lv["name"] for lv in levels) + " |",
                      "|---" * (1 + len(levels)) + "|"]
            for sc in fabric_scenes:
                cells = []
                for lv in levels:
                    p = next((p for p in lv.get("per_scene", []) if p["scene"] == sc), {})
                    cells.append(f"{fmt(p.get('kept_relief'), 2)} / {fmt(p.get('image_texture_fast'), 2)} / "
                                 f"{fmt(p.get('image_texture'), 2)} ({fmt(p.get('contact_area_err'), 2)})")
                lines.append(f"| {sc} | " + " | ".join(cells) + " |")
        lines += ["", "Time per frame: end to end (process CPU, all threads; wall) and by stage (CPU ms; "
                  "pyrender's OpenGL threads count under optics):", "",
                  "| level | CPU ms/frame | wall ms/frame | " + " | ".join(TIMED_STAGES) + " |",
                  "|---" * (3 + len(TIMED_STAGES)) + "|"]
        for lv in levels:
            st = lv["stages_ms"]
            lines.append(f"| {lv['name']} | {lv['cpu_ms_per_frame']:.1f} | {fmt(lv.get('wall_ms_per_frame'), 1)} | "
                         + " | ".join(f"{st.get(k, 0.0):.1f}" for k in TIMED_STAGES) + " |")
        if r.get("shortcuts"):
            lines += ["", f"Shortcuts: the same scenes as {s.get('shortcut_frames', '?')}-frame sequences "
                      f"({s.get('shortcut_precontact', '?')} before contact, as in ViTac Cloth), one contact each; "
                      "differences against the run with all shortcuts:", "",
                      "| level | variant | CPU ms/frame | " + " | ".join(TIMED_STAGES)
                      + " | max pixel diff (DN) | max marker diff (px) | max indentation diff (mm) |",
                      "|---" * (3 + len(TIMED_STAGES) + 3) + "|"]
            for row in r["shortcuts"]:
                st = row["stages_ms"]
                lines.append(f"| {row['level']} | {row['variant']} | {row.get('cpu_ms_per_frame', float('nan')):.1f} | "
                             + " | ".join(f"{st.get(k, 0.0):.1f}" for k in TIMED_STAGES)
                             + f" | {row['max_abs_dn']:.0f} | {row['max_marker_px']:.4f} | "
                               f"{row['max_indentation_mm']:.2e} |")
        lines.append("")
    return "\n".join(lines)


# Pareto panels: (key, axis label), each against CPU ms per frame; the ratios with their range over
# the fabric scenes as bars and the reference's 1 as a line (a level may keep too much texture as
# well as too little: the errors below count both).
PARETO_PANELS = (("kept_relief", "kept relief (ratio to reference; bars: scenes' range)"),
                 ("image_texture_fast", "image texture, fast shader (ratio; bars: range)"),
                 ("texture_err", "texture error: mean |1 - kept relief|"),
                 ("image_texture_fast_err", "image texture error, fast shader: mean |1 - ratio|"),
                 ("marker_err_contact_mm", "marker error in the contact (mm)"),
                 ("contact_area_err", "contact-area error (relative)"))


def pareto_plot(doc: dict, path: Path) -> None:
    """The texture ratios and the texture, image-texture, marker (in contact) and contact-area
    errors against CPU ms per frame (log), one point per level, one line per resolution."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    runs = runs_of(doc)
    fig, axes = plt.subplots(3, 2, figsize=(11, 11))
    for ax, (key, label) in zip(axes.ravel(), PARETO_PANELS):
        ratio = key in ("kept_relief", "image_texture_fast")
        for j, r in enumerate(runs):
            w, h = r["settings"]["resolution"]
            levels = sorted((lv for lv in r["levels"] if lv.get(key) is not None), key=lambda lv: lv["cpu_ms_per_frame"])
            if not levels:
                continue
            xs = [lv["cpu_ms_per_frame"] for lv in levels]
            ys = [lv[key] for lv in levels]
            line, = ax.plot(xs, ys, "-o" if j % 2 == 0 else "--s", label=f"{w}x{h}")
            if ratio:
                lo = [y - lv[f"{key}_min"] for y, lv in zip(ys, levels)]
                hi = [lv[f"{key}_max"] - y for y, lv in zip(ys, levels)]
                ax.errorbar(xs, ys, yerr=[lo, hi], fmt="none", ecolor=line.get_color(), capsize=3, alpha=0.7)
            for i, lv in enumerate(levels):  # staggered labels: neighbouring levels may nearly coincide
                ax.annotate(lv["name"], (xs[i], ys[i]), textcoords="offset points",
                            xytext=(6, 6 if (i + j) % 2 == 0 else -12), fontsize=8)
        if ratio:
            ax.axhline(1.0, color="black", lw=0.8)
        ax.set_xscale("log")
        ax.set_xlabel("CPU ms per frame, end to end (log)")
        ax.set_ylabel(label, fontsize=9)
        ax.set_ylim(bottom=0)
        ax.grid(True, alpha=0.3)
        if sum(1 for r in runs if any(lv.get(key) is not None for lv in r["levels"])) > 1:
            ax.legend(fontsize=8)
    scenes = runs[0]["settings"]["scenes"]
    fig.suptitle(f"gelsim fidelity levels against `{runs[0]['settings']['reference']}`, {len(scenes)} scenes "
                 "(errors: lower left is better)")
    fig.tight_layout()
    write_figure(path, fig, dpi=100)


def write_reports(doc: dict, out_dir: str | Path) -> dict[str, Path]:
    """Write bench.json, bench.md and bench_pareto.png under ``out_dir``; returns their paths."""
    return write_report(doc, out_dir, "bench", "bench_pareto", markdown_table, pareto_plot)


def write_report(result: dict, out_dir: str | Path, stem: str, plot_stem: str, markdown, plot) -> dict[str, Path]:
    """``stem``.json, ``stem``.md (from ``markdown(result)``) and ``plot_stem``.png (``plot(result, path)``)."""
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise GelsimError(f"--out {out} is a file; give a directory")
    paths = {"json": out / f"{stem}.json", "markdown": out / f"{stem}.md", "plot": out / f"{plot_stem}.png"}
    atomic_write_json(paths["json"], result)
    atomic_write_text(paths["markdown"], markdown(result))
    plot(result, paths["plot"])
    return paths
