"""Scenes drawn at random: a base view, the flow, the frame rate, the seeding and one to three nuisances together,
each at a random strength. Error, grade and interval per scene, default settings, as unseen_scenes.py.

    PYTHONPATH=. .venv/bin/python benchmarks/combo_scenes.py [--n 24] [--first 0] [--duration 5]
        [--workdir /tmp/combo_scenes] [--results results]

Scene k is drawn from a generator seeded with k (the same k gives the same scene on every machine) and rendered
once into WORKDIR/c<k>/ (``--geometry``: WORKDIR/g<k>/, the river 6-30 m wide and the camera scaled with it, the
image 640x480 to 1920x1080) (kept: a second call reuses it; ``draw.json`` there says what was drawn). Each runs
through ``fieldtool run`` in a subprocess. The truth is the generator's, integrated from the drawn profile. The
row's rule is unseen_scenes.py's: it passes when the exit code is not 2 and either |error| <= 5 %, or the grade
is not good, the truth lies in the 95 % interval and its half-width is <= 25 %; a good grade with |error| > 5 %
fails. Printed beside: the **confidently wrong** rows (graded good with |error| > 5 %, or doubtful with the truth
outside the interval), the ones this benchmark is for, and the honest refusals (graded unusable, exit 3).

The draws are meant to reach past the presets: flows of 0.4-2x the base's speed at 12-30 fps, seeding from a
third to one and a half times the base's density and faint to bright, and nuisances combined (dusk, rain,
shadows, exposure pumping, debris, standing waves, glitter under haze, haze alone, shake, wind ripples, glints on
the section, patchy seeding, JPEG blocking, vignetting).
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import unseen_scenes as us  # noqa: E402

from fieldtool.synthetic import presets, render_scene  # noqa: E402
from fieldtool.synthetic.nuisances import Nuisances  # noqa: E402

BASES = ("oblique", "nadir", "far_bank")
FPS = (12.0, 15.0, 20.0, 24.0, 25.0, 30.0)


def _low_light(rng, s, n):
    b = rng.uniform(6, 16)
    return (
        replace(s, water_gray=rng.uniform(18, 30) / 255, particle_brightness=b / 255, noise_sigma=0.0,
                bank_gray=0.16, bank_contrast=0.06),
        replace(n, read_noise=rng.uniform(2.5, 5.0), shot_gain=rng.uniform(0.2, 0.5), vignette=rng.uniform(0, 0.4)),
        f"dusk (tracers {b:.0f} grey levels)",
    )


def _rain(rng, s, n):
    r = rng.uniform(1.0, 4.0)
    return s, replace(n, rain_rate_m2s=r, rain_streaks=int(rng.integers(0, 80))), f"rain {r:.1f}/m2/s"


def _shadows(rng, s, n):
    d = rng.uniform(0.3, 0.7)
    return s, replace(n, shadow_band_depth=d, leaf_shadows=int(rng.integers(0, 16))), f"shadow band {d:.2f}"


def _exposure(rng, s, n):
    a = rng.uniform(0.08, 0.3)
    return s, replace(n, exposure_amp=a, white_balance_amp=rng.uniform(0, 0.2)), f"exposure pumping {a:.2f}"


def _debris(rng, s, n):
    k = int(rng.integers(3, 12))
    return s, replace(n, debris=k), f"{k} debris"


def _standing(rng, s, n):
    a = rng.uniform(0.03, 0.08)
    return s, replace(n, standing_amp=a, jump_amp=rng.uniform(0.0, 0.2)), f"standing waves {a:.2f}"


def _glitter(rng, s, n):
    k = int(rng.integers(150, 500))
    return (replace(s, particle_brightness=min(s.particle_brightness, rng.uniform(0.05, 0.3))),
            replace(n, glitter_per_frame=k, glitter_halfwidth_px=rng.uniform(30, 80), haze=rng.uniform(0.15, 0.4)),
            f"glitter {k}/frame")


def _haze(rng, s, n):
    h = rng.uniform(0.2, 0.55)
    return s, replace(n, haze=h), f"haze {h:.2f}"


def _shake(rng, s, n):
    p = rng.uniform(0.5, 3.0)
    return (replace(s, shake_px=p, shake_deg=rng.uniform(0.05, 0.3), shake_drift_px_s=rng.uniform(0, 20)), n,
            f"shake {p:.1f} px")


def _ripples(rng, s, n):
    a = rng.uniform(0.02, 0.08)
    return replace(s, ripple_amp=a, ripple_dir_deg=rng.uniform(90, 270)), n, f"ripples {a:.2f}"


def _section_glints(rng, s, n):
    k = int(rng.integers(8, 40))
    return replace(s, section_glints=k, glint_duty=rng.uniform(0.2, 0.5)), n, f"{k} glints on the section"


def _patchy(rng, s, n):
    c = rng.uniform(0.3, 0.65)
    return replace(s, patch_cover=c, patch_scale_m=rng.uniform(0.8, 2.5)), n, f"patchy seeding {c:.2f}"


def _jpeg(rng, s, n):
    q = int(rng.integers(25, 60))
    return replace(s, jpeg_quality=q), n, f"JPEG q{q}"


NUISANCES = (_low_light, _rain, _shadows, _exposure, _debris, _standing, _glitter, _haze, _shake, _ripples,
             _section_glints, _patchy, _jpeg)


RESOLUTIONS = ((640, 480), (960, 540), (1280, 720), (1920, 1080))


def _other_river(k: int, s, words: list[str]):
    """``s`` with its river, banks, camera, targets and survey scaled by a factor drawn in 0.5-2.5 (a brook to a
    30 m river, the particles as they were) and the camera's image size drawn from :data:`RESOLUTIONS`."""
    rng = np.random.default_rng(5000 + k)
    f = float(rng.uniform(0.5, 2.5))
    w, h = RESOLUTIONS[int(rng.integers(len(RESOLUTIONS)))]
    r, c, lv = s.river, s.camera, s.river.level_m

    def at(p):
        return (p[0] * f, p[1] * f, lv + (p[2] - lv) * f)

    river = replace(r, width_m=r.width_m * f, depth_m=r.depth_m * f, left_bank_m=r.left_bank_m * f,
                    right_bank_m=r.right_bank_m * f, left_bank_height_m=r.left_bank_height_m * f,
                    right_bank_height_m=r.right_bank_height_m * f,
                    island_m=None if r.island_m is None else (r.island_m[0] * f, r.island_m[1] * f))
    cam = replace(c, position_m=at(c.position_m), target_m=at(c.target_m), width_px=w, height_px=h)
    words.insert(1, f"{river.width_m:.0f} m wide, {w}x{h}")
    return replace(s, river=river, camera=cam, gcp_offset_m=s.gcp_offset_m * f, gcp_half_dx_m=s.gcp_half_dx_m * f,
                   gcp_size_m=s.gcp_size_m * f, survey_spacing_m=s.survey_spacing_m * f,
                   roi_half_length_m=s.roi_half_length_m * f, max_extent_m=s.max_extent_m * f,
                   texture_res_m=s.texture_res_m * min(f, 1.0) * (0.75 if w > 1280 else 1.0))


def draw(k: int, duration: float, geometry: bool = False):
    """Scene ``k``: (SceneSpec, the words that say what was drawn); ``geometry``: another river and camera
    (:func:`_other_river`)."""
    rng = np.random.default_rng(1000 + k)
    base = BASES[int(rng.integers(len(BASES)))]
    s = presets.get(base, seed=k)
    u = float(s.river.u_max_ms * rng.uniform(0.4, 2.0))
    fps = float(FPS[int(rng.integers(len(FPS)))])
    dens = float(s.particle_density_m2 * rng.uniform(0.33, 1.5))
    bright = float(rng.uniform(0.2, 0.8))
    s = replace(s, name=f"c{k}", seed=k, duration_s=duration, fps=fps, river=replace(s.river, u_max_ms=u),
                particle_density_m2=dens, particle_brightness=bright, noise_sigma=float(rng.uniform(1.0, 5.0)))
    words = [base, f"u {u:.2f} m/s", f"{fps:g} fps", f"seeding {dens:.0f}/m2 at {bright:.2f}"]
    if geometry:
        s = _other_river(k, s, words)
    n = Nuisances()
    for f in rng.choice(len(NUISANCES), size=int(rng.integers(1, 4)), replace=False):
        s, n, said = NUISANCES[int(f)](rng, s, n)
        words.append(said)
    return replace(s, nuisances=n), words


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=24, help="scenes")
    ap.add_argument("--first", type=int, default=0, help="first scene's number")
    ap.add_argument("--duration", type=float, default=5.0)
    ap.add_argument("--workdir", default="/tmp/combo_scenes")
    ap.add_argument("--results", default="results", help="results folder inside each scene's (keep before/after)")
    ap.add_argument("--geometry", action="store_true",
                    help="other rivers and cameras: width 6-30 m, image 640x480 to 1920x1080 (scenes g<k>)")
    a = ap.parse_args()
    rows, said = [], {}
    print(us.HEAD + "  what was drawn", flush=True)
    for k in range(a.first, a.first + a.n):
        spec, words = draw(k, a.duration, a.geometry)
        name = f"{'g' if a.geometry else 'c'}{k:03d}"
        d = Path(a.workdir) / name
        if not (d / "truth.json").exists():
            render_scene(spec, d)
            (d / "draw.json").write_text(json.dumps({"words": words, "spec": asdict(spec)}, default=str, indent=1))
        q_true = json.loads((d / "truth.json").read_text())["discharge_m3s"]
        rc, res, dt = us.run_cli(d / "project.toml", d / a.results)
        r = us.row(name, k, rc, res, q_true, dt)
        rows.append(r)
        said[id(r)] = ", ".join(words)
        print(us.fmt(r, "  " + said[id(r)]), flush=True)
    wrong = [r for r in rows if (r["grade"] == "good" and (r["err"] is None or abs(r["err"]) > 5.0))
             or (r["grade"] == "doubtful" and r["inside"] is False and abs(r["err"] or 0.0) > 5.0)]
    errs = [abs(r["err"]) for r in rows if r["err"] is not None and r["grade"] in ("good", "doubtful")]
    n_fail = sum(not r["pass"] for r in rows)
    unusable = sum(r["grade"] == "unusable" for r in rows)
    print(f"{len(rows) - n_fail}/{len(rows)} pass; confidently wrong {len(wrong)} "
          f"({', '.join(r['preset'] for r in wrong) or 'none'}); unusable {unusable}; "
          f"exit 2 in {sum(r['rc'] == 2 for r in rows)}; median |error| of the good and doubtful "
          f"{np.median(errs) if errs else float('nan'):.2f} %")
    return 1 if n_fail else 0


if __name__ == "__main__":
    sys.exit(main())
