"""``gelsim bench``: time per frame and error of each fidelity level, and the convergence study.

:func:`run_bench` runs every level on the same fixed scenes (a pressed sphere and catalog fabrics
under each action: a fine weave, a coarse knit and a pile fabric by default) at one resolution
and reports, per level, the CPU time per frame (end to end, and by stage) and the error against
the ``reference`` level on the same scenes:

* **texture** (fabric scenes, in each fabric's pitch band and over the reference's contact region,
  :mod:`gelsim.texture`): *kept relief*, the RMS of the gel surface's relief in the band over the
  reference's, and *image texture*, the RMS of the texture's own share of the image (a noiseless,
  markerless frame minus the frame of the same imprint smoothed beyond the band,
  :func:`gelsim.texture.texture_frames`) over the reference's, once with each level's own renderer
  (``image_texture``: the reference's is pyrender) and once with the fast shader for both
  (``image_texture_fast``: only the gel differs). Ratios per scene (pooled over its in-contact
  frames), then the geometric mean, the smallest and the largest over the scenes; the ``*_err``
  are the mean of ``|1 - ratio|`` over the scenes (0: the reference's texture, 0.5: half of it
  lost or half again);
* **contact area**: mean ``|A - A_ref| / A_ref`` over the in-contact frames (the gel's contact
  area, texture-scale contact included);
* **markers**: mean distance between a level's and the reference's marker centres over the
  in-contact frames, mm, for all markers and for those inside the reference's contact patch;
* **force**: mean ``|normal force|`` difference over all frames, N, each level with its own
  physics timestep;
* **image**: L1 (DN, 0-255), PSNR (dB, from the MSE pooled over frames) and SSIM (Wang et al. 2004:
  11x11 Gaussian window, sigma 1.5, per RGB channel) over the in-contact frames, whole image.

So that image, marker and texture differences measure the image knobs, every level renders on the
*reference* level's contact simulation (same positions, forces, shear and twist); each level's own
physics run is timed and gives the force error. Same scenes, seeds and camera noise for every
level. :func:`run_shortcut_study` times the balanced level with and without the shortcuts of
:mod:`gelsim.sequence` and with labels only. :func:`run_convergence` sweeps one knob at a time
with the same metrics; :func:`run_pitch_study` measures the kept texture against the pixels per
texture period on the finest weaves.

The yardstick runs (the reference level, a sweep's finest value) cost seconds per 960x720 frame
(the elastic imprint): :class:`RunCache` keeps them on disk, keyed by everything they depend on
(scene, sizes, sensor, fidelity, contact, and the source of every module but this package's).

Reports: :func:`write_reports` writes ``bench.json``, ``bench.md`` and ``bench_pareto.png``;
:func:`write_convergence` writes ``convergence.json``, ``convergence.md`` and ``convergence.png``.

One job per module: :mod:`.scenes` (what is run: :class:`BenchConfig`, :class:`Scene`), :mod:`.runs` (one
level on one scene, timed: :func:`run_level`, whose sequence streams its frame records into the bench's
sinks), :mod:`.metrics` (image metrics and error pooling), :mod:`.texture` (the texture metric),
:mod:`.cache` (the yardstick cache), :mod:`.levels` (the level table), :mod:`.shortcuts` (the shortcut
study), :mod:`.reports` (the level table's reports), :mod:`.convergence` (the one-knob sweeps) and
:mod:`.pitch` (texture against pixels per period).
"""
from __future__ import annotations

from .cache import RunCache, measured_run
from .convergence import (IMPRINT_METRICS, SWEEP_HOLD, SWEEPS, convergence_markdown, convergence_plot, run_convergence,
                          write_convergence)
from .levels import run_bench, run_benches
from .metrics import ErrorAcc, accumulate, psnr_from_mse, ssim
from .pitch import PITCH_FABRICS, PITCH_FORCE_N, PITCH_VARIANTS, pitch_markdown, pitch_plot, run_pitch_study
from .reports import PARETO_PANELS, markdown_table, pareto_plot, write_reports
from .runs import TIMED_STAGES, LevelRun, make_renderer, run_level
from .scenes import (DEFAULT_FABRICS, DEFAULT_FRAMES, DEFAULT_PRECONTACT, DEFAULT_RESOLUTION, DEFAULT_RESOLUTIONS,
                     LARGE_FRAMES, LARGE_PIXELS, QUICK, SCENE_SEED_STRIDE, SHORTCUT_FRAMES, SHORTCUT_PRECONTACT,
                     SPHERE_DIAMETER_MM, SPHERE_FORCE_N, SPHERE_FRICTION, BenchConfig, Scene, bench_profile,
                     default_frames, prepare_scene, scene_motion, scenes_for)
from .shortcuts import run_shortcut_study
from .texture import SceneTexture, measure_texture

__all__ = [
    "RunCache", "measured_run", "IMPRINT_METRICS", "SWEEP_HOLD", "SWEEPS", "convergence_markdown", "convergence_plot",
    "run_convergence", "write_convergence", "run_bench", "run_benches", "ErrorAcc", "accumulate", "psnr_from_mse",
    "ssim", "PITCH_FABRICS", "PITCH_FORCE_N", "PITCH_VARIANTS", "pitch_markdown", "pitch_plot", "run_pitch_study",
    "PARETO_PANELS", "markdown_table", "pareto_plot", "write_reports", "TIMED_STAGES", "LevelRun", "make_renderer",
    "run_level", "DEFAULT_FABRICS", "DEFAULT_FRAMES", "DEFAULT_PRECONTACT", "DEFAULT_RESOLUTION",
    "DEFAULT_RESOLUTIONS", "LARGE_FRAMES", "LARGE_PIXELS", "QUICK", "SCENE_SEED_STRIDE", "SHORTCUT_FRAMES",
    "SHORTCUT_PRECONTACT", "SPHERE_DIAMETER_MM", "SPHERE_FORCE_N", "SPHERE_FRICTION", "BenchConfig", "Scene",
    "bench_profile", "default_frames", "prepare_scene", "scene_motion", "scenes_for", "run_shortcut_study",
    "SceneTexture", "measure_texture",
]
