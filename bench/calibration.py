"""Calibration bench: are the posterior's credible intervals honest?

    dejaview bench calibration                      # 3 scenes x 50 truths, prints the table
    dejaview bench calibration --truths 10 --scenes ramp --samples 200
    python bench/calibration.py --csv calibration.csv --plot ranks.png

Simulation-based calibration (Talts et al. 2018, "Validating Bayesian
inference algorithms with simulation-based calibration"): for each case a
truth is drawn from the scene's stated prior (``Posterior.sample``: the start
position uniform in the start area, velocities and tilt normal with the
``<prior>`` deviations), simulated, and its end pose observed with noise drawn
from ``<observation>`` (position noise on the centre of mass, a random rotation
vector on the orientation). ``dejaview.solve(scene, samples=N)`` (the code
behind ``dejaview solve --samples N``) then samples the posterior from that
observation alone, and the truth's rank among the samples is recorded per free
parameter (the weighted fraction of samples below it). If the sampler draws
from the true posterior, those ranks are uniform, so the truth falls inside
the central 50 % interval half the time and inside the 90 % interval 90 % of
the time.

Reported per scene and pooled over parameters: the coverage of the central
50 % and 90 % intervals, the histogram of the truth's rank by log posterior
density (the fraction of samples denser than the truth: uniform too if the
samples are the posterior's, whatever the parameterisation; piled at 1 when the
samples crowd the densest regions and miss the posterior's thinner bulk, at 0
in the opposite case), the sharpness (mean 90 % interval width over the
prior's 90 % width: 1 means the end taught nothing), on how many truths the
sampler's two independent runs disagreed (``max_rhat`` per truth over
``ReportParams.rhat_limit``: the warning a user sees), and a 10-bin rank
histogram (``--plot``: a PNG of them). The scenes (built in code from bundled
ones; the files are not touched), each observed at its last record
(``evaluate="final"``, the generative model of the observation):

- ``ball_off_table``: a ball rolled off a table onto the floor (position x-y
  and linear velocity free, 5 parameters; prior speed 1 m/s). Its end position
  is observed, not its orientation (the scene's own ``position`` loss): a
  rolling ball turns by its path length over its radius, so its orientation
  is a comb of narrow stripes in the start, not an observation anyone makes of
  a ball.
- ``box_thrown``: a box tossed onto the floor (position x-y, orientation and
  both velocities free, 11 parameters; prior speed 1 m/s, spin 3 rad/s, tilt
  0.3 rad): more unknowns than the 6 observed numbers, so the prior shapes the
  posterior along the directions the end does not see.
- ``ramp``: ``ball_down_ramp`` (the start position x-y alone, 2 parameters,
  position loss): the end pins the start.

``--amortised``: each scene's truths answered by ``solve --amortised`` from a model trained for
the scene first (``TrainParams`` defaults, seed 0), with the coverage of the flow's own draws
(before the importance weights) beside the weighted answers'; ``--first K``: truths K.. (another
set, held out).
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
from dataclasses import replace
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SCENES = ROOT / "examples" / "scenes"
CASES = ("ball_off_table", "box_thrown", "ramp")
LEVELS = (0.5, 0.9)
TARGETS = {0.5: (0.40, 0.60), 0.9: (0.85, 0.97)}
"""Coverage each central interval must reach, pooled over parameters and truths (issue 20)."""
BINS = 10


def base_scene(name: str):
    """The calibration scene ``name`` (module docstring), before its target is set."""
    from dejaview.scene import (
        InferenceSettings,
        Observation,
        Optimize,
        Pose,
        Prior,
        Scene,
        SceneObject,
        SimulationSettings,
        StartArea,
        Target,
    )

    if name == "ball_off_table":
        scene = Scene.from_xml(SCENES / "ball_off_table.xml")
        inf = replace(scene.inference, loss="position", evaluate="final",
                      optimize=Optimize(position=True, orientation=False, linear_velocity=True,
                                        angular_velocity=False),
                      start_area=StartArea(min=(-0.4, -0.25, 0.8), max=(0.4, 0.25, 0.8)),
                      prior=Prior(speed=1.0), observation=Observation(sigma=0.01, angle_sigma=0.1))
        return replace(scene, simulation=replace(scene.simulation, duration=1.0), inference=inf)
    if name == "box_thrown":
        return Scene(
            name="box-thrown", gravity=(0.0, 0.0, -9.81),
            simulation=SimulationSettings(dt=0.002, duration=0.8, friction=0.5, restitution=0.2),
            objects=(SceneObject(id="floor", shape="plane", fixed=True),
                     SceneObject(id="box", shape="box", size=(0.12, 0.08, 0.06), mass=0.3,
                                 pose=Pose((0.0, 0.0, 0.3)))),
            inference=InferenceSettings(
                source="box", targets=(Target(position=(0.0, 0.0, 0.03), orientation=(1.0, 0.0, 0.0, 0.0), moving=True),), loss="pose", evaluate="final",
                optimize=Optimize(position=True, orientation=True, linear_velocity=True, angular_velocity=True),
                start_area=StartArea(min=(-0.3, -0.3, 0.3), max=(0.3, 0.3, 0.3)),
                prior=Prior(speed=1.0, spin=3.0, tilt=0.3), observation=Observation(sigma=0.01, angle_sigma=0.1)))
    if name == "ramp":
        scene = Scene.from_xml(SCENES / "ball_down_ramp.xml")
        inf = replace(scene.inference, evaluate="final", heatmap=None, observation=Observation(sigma=0.01))
        return replace(scene, inference=inf)
    raise ValueError(f"unknown calibration scene {name!r}; choose from {', '.join(CASES)}")


def observe(scene, post, truth, generator):
    """The scene with its target set to the noisy observed end of the start ``truth`` (1, P),
    simulated with ``post``'s problem and observed with its noise (``post``: the scene's
    ``Posterior``)."""
    import torch

    with torch.no_grad():
        st = post.problem.simulate(truth).states
    b = post.problem.source
    origin, q_obs = sighting(scene, post, st.position[-1, 0, b], st.orientation[-1, 0, b], generator)
    inf = scene.inference
    # the end observed as it is, at rest or not (the truths are drawn without asking them to rest)
    target = replace(inf.target, position=tuple(origin.tolist()), orientation=tuple(q_obs.tolist()), moving=True)
    return replace(scene, inference=replace(inf, targets=(target,)))


def sighting(scene, post, com, q, generator):
    """The source seen with ``post``'s ``<observation>`` noise at its centre of mass com (3,) and
    orientation q (4,): (origin (3,), orientation (4,)) as a target states them; the origin for a
    position loss (the orientation not compared), else the centre of mass and a turned orientation
    (``Posterior.observation_residuals``)."""
    import torch

    from dejaview.sim.rotation import quat_multiply, quat_rotate, rotvec_to_quat

    settings, b = post.settings, post.problem.source
    eps = settings.sigma * torch.randn(3, generator=generator, dtype=com.dtype)
    eta = settings.angle_sigma * torch.randn(3, generator=generator, dtype=com.dtype)
    q_obs = quat_multiply(rotvec_to_quat(eta), q)
    if scene.inference.loss == "position":
        return com - quat_rotate(q, post.problem.world.com[b]) + eps, q_obs
    return com + eps - quat_rotate(q_obs, post.problem.world.com[b]), q_obs


def prior_width90(post) -> list[float]:
    """Width of the prior's central 90 % interval of each free parameter (physical units)."""
    lay, s = post.layout, post.settings
    out = []
    if lay.free["position"]:
        out += [0.9 * float(lay.hi[a] - lay.lo[a]) for a in lay.position_axes]
    for block, sd in (("orientation", s.tilt), ("linear_velocity", s.speed), ("angular_velocity", s.spin)):
        if lay.free[block]:
            out += [2 * 1.6449 * sd] * 3
    return out


def run_case(name: str, index: int, samples: int, amortised=None) -> dict:
    """One truth of scene ``name``: draw, observe, sample the posterior (or answer from the
    ``amortised`` model trained for the scene), rank the truth."""
    import torch

    from dejaview.inference import solve
    from dejaview.inference.solve import SolveParams
    from dejaview.inference.posterior import Posterior, PosteriorSettings
    from dejaview.inference.posterior_report import physical, weighted_quantiles
    from dejaview.backends.spheres import SpheresProblem
    from dejaview.inference.reference import log_density

    gen = torch.Generator().manual_seed(1000 + index)
    scene = base_scene(name)
    prior_post = Posterior(SpheresProblem.from_scene(scene), PosteriorSettings.from_scene(scene))
    truth = prior_post.sample(1, gen)
    observed = observe(scene, prior_post, truth, gen)
    t0 = time.perf_counter()
    result = solve(observed, SolveParams(samples=samples, seed=index, amortised=amortised))
    seconds = time.perf_counter() - t0
    lay = result.problem.layout
    smp = result.posterior
    values, true_values = physical(lay, smp.x), physical(lay, truth)[0]
    w = smp.weights
    qs = [q for level in LEVELS for q in ((1 - level) / 2, (1 + level) / 2)]
    quant = weighted_quantiles(values, w, qs)
    row = {"scene": name, "case": index, "seconds": seconds, "parameters": lay.names(),
           "unique": smp.stats["unique_samples"], "stages": smp.stats.get("stages", 0),
           "rollouts": smp.stats["rollouts"], "acceptance": smp.stats.get("mean_acceptance")}
    if amortised is not None:
        am = result.settings["amortised"]
        row.update(k_hat=am["k_hat"], fitted=am["fitted"], ess=am["ess"])
    ranks, cover, width = [], {level: [] for level in LEVELS}, []
    for j in range(values.shape[1]):
        ranks.append(float((w * (values[:, j] < true_values[j]).double()).sum()))
        for i, level in enumerate(LEVELS):
            lo, hi = float(quant[2 * i, j]), float(quant[2 * i + 1, j])
            cover[level].append(lo <= float(true_values[j]) <= hi)
            if level == 0.9:
                width.append(hi - lo)
    row["ranks"] = ranks
    agreement = result.settings["posterior"]["agreement"]  # the runs' R-hat, as the user sees it
    row["max_rhat"] = None if agreement is None else agreement["max_rhat"]
    row["cover50"], row["cover90"] = cover[0.5], cover[0.9]
    if amortised is not None:  # the flow's own draws, before the importance weights
        from dejaview.inference.amortised.observables import observed as observation_of

        flow_post = Posterior(result.problem, PosteriorSettings.from_scene(observed))
        draws, _ = amortised.sample(flow_post, observation_of(flow_post), samples, torch.Generator().manual_seed(index))
        fq = weighted_quantiles(physical(lay, draws), torch.full((samples,), 1.0 / samples, dtype=torch.float64), qs)
        for i, level in enumerate(LEVELS):
            row[f"flow_cover{int(level * 100)}"] = [bool(float(fq[2 * i, j]) <= float(true_values[j]) <= float(fq[2 * i + 1, j]))
                                                    for j in range(values.shape[1])]
    row["sharpness"] = [wd / pw for wd, pw in zip(width, prior_width90(prior_post))]
    observed_post = Posterior(result.problem, PosteriorSettings.from_scene(observed))
    truth_density = float(log_density(observed_post, truth)[0])
    row["density_rank"] = float((w * (smp.log_density > truth_density).double()).sum())
    return row


def summarize(rows: list[dict]) -> dict:
    """Pooled coverage, sharpness and the rank histogram of some rows."""
    c50 = [c for r in rows for c in r["cover50"]]
    c90 = [c for r in rows for c in r["cover90"]]
    ranks = [x for r in rows for x in r["ranks"]]
    hist = [0] * BINS
    for x in ranks:
        hist[min(int(x * BINS), BINS - 1)] += 1
    sharp = [s for r in rows for s in r["sharpness"]]
    density = [0] * (BINS // 2)
    for r in rows:
        if r.get("density_rank") is not None:
            density[min(int(r["density_rank"] * len(density)), len(density) - 1)] += 1
    from dejaview.inference.params import ReportParams

    flagged = sum(1 for r in rows if r.get("max_rhat") is not None and r["max_rhat"] > ReportParams.rhat_limit)
    flow = {}
    for level in (50, 90):
        got = [c for r in rows for c in r.get(f"flow_cover{level}", [])]
        if got:
            flow[f"flow_cover{level}"] = sum(got) / len(got)
    return {**flow, "cover50": sum(c50) / len(c50), "cover90": sum(c90) / len(c90), "n": len(c90), "flagged": flagged,
            "sharpness": sum(sharp) / len(sharp), "histogram": hist, "density_histogram": density,
            "seconds": sum(r["seconds"] for r in rows) / len(rows)}


def verdict(s: dict) -> str:
    ok = all(TARGETS[level][0] <= s[f"cover{int(level * 100)}"] <= TARGETS[level][1] for level in LEVELS)
    return "met" if ok else "missed"


def train_for(name: str, simulations: int | None = None, print_fn=None):
    """The amortised posterior of calibration scene ``name`` (its target does not matter: the model
    answers any observation), trained with the defaults (``TrainParams``) and seed 0."""
    from dataclasses import replace as _replace

    from dejaview.inference.amortised import train
    from dejaview.inference.params import TrainParams

    params = TrainParams() if simulations is None else _replace(TrainParams(), simulations=simulations)
    model = train(base_scene(name), params)
    if print_fn is not None:
        info = model.info
        print_fn(f"  {name}: trained on {info['simulations']} simulations in {info['seconds']:.0f} s "
                 f"({info['fit']['epochs']} epochs, validation -log q {info['fit']['validation_nll']:.3f})")
    return model


def run(print_fn=print, scenes=CASES, truths: int = 50, samples: int = 300, plot=None,
        verbose: bool = False, amortised: bool = False, first: int = 0, simulations: int | None = None) -> list[dict]:
    """Every scene x truth; prints a row per scene and the pooled verdict. ``amortised``: each scene's
    truths answered by ``solve --amortised`` from a model trained for it first; ``first``: the first
    truth's index (truth i draws from seed 1000 + i: another ``first`` is another, held-out set)."""
    import torch

    torch.set_num_threads(int(os.environ.get("DEJAVIEW_THREADS", "1")))
    say = print_fn or (lambda *_: None)
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    say(f"calibration: {', '.join(scenes)}; {truths} truths each, {samples} samples; load average {load:.1f}")
    rows = []
    per_scene = {}
    for name in scenes:
        mine = []
        model = train_for(name, simulations, say) if amortised else None
        for i in range(first, first + truths):
            row = run_case(name, i, samples, model)
            mine.append(row)
            rows.append(row)
            if verbose:
                say(f"  {name} {i}: {row['seconds']:.1f} s, ranks "
                    + " ".join(f"{r:.2f}" for r in row["ranks"])
                    + f", {row['unique']} distinct, {row['stages']} steps, "
                    + (f"k-hat {row['k_hat']:.2f}, " if "k_hat" in row else "")
                    + f"{row['density_rank']:.2f} of the samples denser than the truth")
        per_scene[name] = summarize(mine)
    say(f"{'scene':<16} {'params':>6} {'cover50':>8} {'cover90':>8} {'sharp':>6} {'s/case':>7}  rank histogram"
        f"  [density rank, 5 bins]")
    for name, s in per_scene.items():
        params = len(next(r for r in rows if r["scene"] == name)["parameters"])
        say(f"{name:<16} {params:>6} {s['cover50']:>8.3f} {s['cover90']:>8.3f} {s['sharpness']:>6.3f} "
            f"{s['seconds']:>7.1f}  {' '.join(str(h) for h in s['histogram'])}  "
            f"[{' '.join(str(h) for h in s['density_histogram'])}]  {verdict(s)}; runs disagree on "
            f"{s['flagged']} of {truths} truths"
            + (f"; the model did not fit {sum(not r['fitted'] for r in mine)}; the flow's own draws, before the "
               f"weights: cover50 {s['flow_cover50']:.3f}, cover90 {s['flow_cover90']:.3f}" if amortised else ""))
    pooled = summarize(rows)
    say(f"{'pooled':<16} {'':>6} {pooled['cover50']:>8.3f} {pooled['cover90']:>8.3f} "
        f"{pooled['sharpness']:>6.3f} {pooled['seconds']:>7.1f}  "
        f"{' '.join(str(h) for h in pooled['histogram'])}  {verdict(pooled)}")
    say(f"targets: 50 % interval coverage in [{TARGETS[0.5][0]:.2f}, {TARGETS[0.5][1]:.2f}], "
        f"90 % in [{TARGETS[0.9][0]:.2f}, {TARGETS[0.9][1]:.2f}], on every scene")
    if plot is not None:
        plot_histograms(per_scene, plot)
        say(f"wrote {plot}")
    return [{k: (",".join(map(str, v)) if isinstance(v, list) else v) for k, v in r.items()} for r in rows]


def plot_histograms(per_scene: dict, path) -> Path:
    """A PNG of the rank histograms, one panel per scene, with the uniform level."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(per_scene), figsize=(3.2 * len(per_scene), 2.6), dpi=100, squeeze=False)
    for ax, (name, s) in zip(axes[0], per_scene.items()):
        ax.bar([(i + 0.5) / BINS for i in range(BINS)], s["histogram"], width=1 / BINS, edgecolor="k")
        ax.axhline(s["n"] / BINS, color="r", lw=1)
        ax.set_title(f"{name}\n50%: {s['cover50']:.2f}  90%: {s['cover90']:.2f}", fontsize=9)
        ax.set_xlabel("rank of the truth")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return Path(path)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenes", default=",".join(CASES), help="comma-separated calibration scenes")
    parser.add_argument("--truths", type=int, default=50, help="truths per scene")
    parser.add_argument("--samples", type=int, default=300, help="posterior samples per truth")
    parser.add_argument("--plot", type=Path, default=None, help="write the rank histograms as a PNG here")
    parser.add_argument("--csv", type=Path, default=None, help="also write the rows as CSV here")
    parser.add_argument("--verbose", action="store_true", help="a line per truth")
    parser.add_argument("--amortised", action="store_true", help="answer from an amortised model trained per scene")
    parser.add_argument("--first", type=int, default=0, help="index of the first truth (another set: held out)")
    args = parser.parse_args(argv)
    rows = run(scenes=tuple(args.scenes.split(",")), truths=args.truths, samples=args.samples, plot=args.plot,
               verbose=args.verbose, amortised=args.amortised, first=args.first)
    if args.csv is not None:
        from dejaview.cli.bench_table import write_rows_csv

        write_rows_csv(rows, args.csv)
    return 0


if __name__ == "__main__":
    sys.path.insert(0, str(ROOT))
    sys.exit(main())
