"""What a solve reports of the posterior samples: ``posterior.csv``, the summary in ``result.json``
(modes with their probability mass, central intervals) and the start-position heatmap.

Parameters are reported in physical units under the layout's names
(``ParameterLayout.names``): ``position.x`` (m, object-frame origin),
``orientation.rx`` (rad, rotation vector applied on top of the ``<pose>``
orientation), ``linear_velocity.x`` (m/s), ``angular_velocity.x`` (rad/s) and, where inferred,
``physics.friction``, ``physics.restitution`` and ``physics.stiffness`` (their values:
``dejaview.sim.physics``).
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import torch

from dejaview.inference.params import ReportParams

CSV_HEADER = ("sample", "weight", "x", "y", "z", "qw", "qx", "qy", "qz", "vx", "vy", "vz", "wx", "wy", "wz")
"""``posterior.csv``'s header (scene-format spec, "Additions to version 1")."""
PHYSICS_COLUMNS = ("friction", "restitution", "stiffness")
"""... and its columns after ``wz`` where physics was inferred (values, ``dejaview.sim.physics``)."""
PATHS_HEADER = ("sample", "step", "time", "x", "y", "z")
"""``posterior_paths.csv``'s header: the source's object-frame origin along a few samples' pasts."""


def physical(layout, x: torch.Tensor) -> torch.Tensor:
    """The free parameters x (N, P) in physical units (N, P), in ``layout.names()`` order."""
    with torch.no_grad():
        dec = layout.decode(x.to(layout.base_position.dtype))
    cols = []
    if layout.free["position"]:
        cols += [dec["position"][:, a] for a in layout.position_axes]
    if layout.free["orientation"]:
        r = layout.scale["orientation"] * x[:, layout.block_slice("orientation")]
        cols += [r[:, i] for i in range(3)]
    for block in ("linear_velocity", "angular_velocity"):
        if layout.free[block]:
            cols += [dec[block][:, i] for i in range(3)]
    if layout.physics is not None:
        with torch.no_grad():
            values = layout.physics_values(x.to(torch.float64))
        cols += [values[:, i] for i in layout.physics.free]
    return torch.stack(cols, -1).to(torch.float64) if cols else x[:, :0].to(torch.float64)


def weighted_quantiles(values: torch.Tensor, weights: torch.Tensor, qs) -> torch.Tensor:
    """Quantiles (len(qs), P) of weighted samples values (N, P), weights (N,) summing to 1
    (the inverse of the weighted empirical CDF, interpolated between midpoints)."""
    out = []
    for j in range(values.shape[1]):
        v, order = torch.sort(values[:, j])
        w = weights[order]
        c = torch.cumsum(w, 0) - 0.5 * w
        out.append(torch.tensor(np.interp(np.asarray(qs, dtype=float), c.numpy(), v.numpy()),
                                dtype=torch.float64))
    return torch.stack(out, -1) if out else torch.zeros(len(qs), 0, dtype=torch.float64)


def rhat(values: torch.Tensor, run: torch.Tensor) -> torch.Tensor:
    """Rank-normalised R-hat (P,) of values (N, P) drawn by independent runs ``run`` (N,) (Vehtari,
    Gelman, Simpson, Carpenter and Buerkner 2021, their equation for several chains, the runs as
    chains): the pooled samples' normal scores, then ``sqrt(var+ / W)`` with W the mean variance
    within the runs and var+ that plus the variance between the runs' means. About 1 where the
    runs draw from the same distribution; above 1 where they landed in different parts of it
    (a rugged posterior whose branches the moves do not cross), whatever the parameter's units.
    NaN with fewer than two runs."""
    labels = torch.unique(run)
    p = values.shape[1]
    if labels.numel() < 2:
        return torch.full((p,), float("nan"), dtype=torch.float64)
    n = values.shape[0]
    ranks = values.argsort(0).argsort(0).double() + 1.0  # ties (duplicated particles) broken by order
    z = torch.special.ndtri((ranks - 0.375) / (n + 0.25))
    means = torch.stack([z[run == k].mean(0) for k in labels])
    within = torch.stack([z[run == k].var(0) for k in labels]).mean(0)
    m = n / labels.numel()  # the runs' mean size
    between = means.var(0)  # B / m
    var_plus = (m - 1) / m * within + between
    return torch.sqrt(var_plus / within.clamp_min(1e-300))


def chain_rows(run: torch.Tensor) -> list[torch.Tensor]:
    """Row indices of each independent run's samples ``run`` (N,), in their order, cut to the
    smallest run's size: the equal-length chains ``ess_bulk`` and ArviZ (``posterior.nc``) use (an
    odd N's two runs differ by one sample)."""
    rows = [torch.nonzero(run == k).flatten() for k in torch.unique(run)]
    k = min(r.numel() for r in rows)
    return [r[:k] for r in rows]


def ess_bulk(values: torch.Tensor, run: torch.Tensor) -> torch.Tensor:
    """Bulk effective sample size (P,) of values (N, P) with the runs ``run`` (N,) as chains
    (``chain_rows``): ArviZ 0.23's ``ess(method="bulk")`` (Vehtari et al. 2021: each chain split
    in two, the pooled draws' normal scores, autocorrelations along the draws cut by Geyer's
    initial monotone sequence), so the number is the one ArviZ gives for ``posterior.nc``. A run's
    samples are in particle order, and after a resampling its copies of one ancestor lie side by
    side: the autocorrelation counts them as one draw where the moves have not pulled them apart.
    NaN below 4 samples a chain."""
    from scipy.special import ndtri
    from scipy.stats import rankdata

    rows = chain_rows(run)
    out = []
    for j in range(values.shape[1]):
        a = np.stack([values[r, j].numpy() for r in rows]).astype(float)
        if a.shape[1] < 4 or not np.isfinite(a).all():
            out.append(float("nan"))
            continue
        half = a.shape[1] // 2
        split = np.concatenate([a[:, :half], a[:, -half:]])
        z = ndtri((rankdata(split, method="average").reshape(split.shape) - 0.375) / (split.size + 0.25))
        out.append(_ess(z))
    return torch.tensor(out, dtype=torch.float64)


def _ess(a: np.ndarray) -> float:
    """ESS of chains a (M, D) by Geyer's initial monotone sequence (ArviZ 0.23's ``_ess``)."""
    m, d = a.shape
    if a.max() - a.min() < np.finfo(float).resolution:
        return float(a.size)
    centred = a - a.mean(1, keepdims=True)
    f = np.fft.rfft(centred, n=2 * d, axis=1)
    acov = np.fft.irfft(f * np.conjugate(f), n=2 * d, axis=1)[:, :d] / d
    mean_var = acov[:, 0].mean() * d / (d - 1.0)
    var_plus = mean_var * (d - 1.0) / d + (a.mean(1).var(ddof=1) if m > 1 else 0.0)
    rho = np.zeros(d)
    rho[0], even, odd = 1.0, 1.0, 1.0 - (mean_var - acov[:, 1].mean()) / var_plus
    rho[1] = odd
    t = 1
    while t < d - 3 and even + odd > 0.0:
        even = 1.0 - (mean_var - acov[:, t + 1].mean()) / var_plus
        odd = 1.0 - (mean_var - acov[:, t + 2].mean()) / var_plus
        if even + odd >= 0:
            rho[t + 1], rho[t + 2] = even, odd
        t += 2
    max_t = t - 2
    if even > 0:
        rho[max_t + 1] = even
    t = 1
    while t <= max_t - 2:  # monotone: each pair's sum at most the one before
        if rho[t + 1] + rho[t + 2] > rho[t - 1] + rho[t]:
            rho[t + 1] = rho[t + 2] = (rho[t - 1] + rho[t]) / 2.0
        t += 2
    tau = -1.0 + 2.0 * rho[:max_t + 1].sum() + rho[max_t + 1:max_t + 2].sum()
    return float(a.size / max(tau, 1.0 / np.log10(a.size)))


def interval_levels() -> list[float]:
    """The quantiles ``summary`` reports: the median, then each ``ReportParams.intervals`` level's
    lower and upper end."""
    qs = [0.5]
    for level in ReportParams.intervals:
        qs += [(1 - level) / 2, (1 + level) / 2]
    return qs


def interval_entry(quant: torch.Tensor, j: int) -> dict:
    """Column j of quantiles (len(interval_levels()), P) as ``{"median", "50%": [lo, hi], ...}``."""
    return {"median": float(quant[0, j]),
            **{f"{int(level * 100)}%": [float(quant[1 + 2 * i, j]), float(quant[2 + 2 * i, j])]
               for i, level in enumerate(ReportParams.intervals)}}


def summary(samples, layout, modes) -> dict:
    """``result.json``'s ``posterior``: sampler statistics, the modes with their probability mass
    (the share of samples nearest to each of the search's distinct modes) and, per free
    parameter, the median and the central 50 % and 90 % intervals in physical units.

    Args:
        samples: ``PosteriorSamples``; layout: ``ParameterLayout``; modes: the search's ``Mode`` list.
    """
    w = samples.weights
    values = physical(layout, samples.x)
    quant = weighted_quantiles(values, w, interval_levels())
    intervals = {}
    run = samples.run if samples.run is not None else torch.zeros(values.shape[0], dtype=torch.long)
    r = rhat(values, run)  # NaN for one run
    e = ess_bulk(values, run)
    for j, name in enumerate(layout.names()):
        intervals[name] = {**interval_entry(quant, j),
                           **({"rhat": float(r[j])} if bool(torch.isfinite(r[j])) else {}),
                           **({"ess": float(e[j])} if bool(torch.isfinite(e[j])) else {})}
    found = []
    for k, index in enumerate(samples.mode_index):
        mass = float(w[samples.component == k].sum())
        if mass < ReportParams.min_mode_mass:
            continue
        mode = modes[index]
        with torch.no_grad():
            state = {key: v[0].tolist() for key, v in
                     layout.decode(mode.x.unsqueeze(0).to(layout.base_position.dtype)).items()}
        found.append({"probability": mass, "neg_log_posterior": mode.cost, "initial_state": state})
    found.sort(key=lambda m: -m["probability"])
    finite = r[torch.isfinite(r)]
    agreement = None if finite.numel() == 0 else {
        "max_rhat": float(finite.max()), "limit": ReportParams.rhat_limit, "runs_agree": bool(finite.max() <= ReportParams.rhat_limit)}
    return {"samples": int(samples.x.shape[0]), "sampler": samples.stats, "modes": found,
            "intervals": intervals, "agreement": agreement}


def physics_report(layout, best: torch.Tensor, posterior: dict | None) -> dict:
    """``result.json``'s ``physics``: the most probable friction, restitution and stiffness (the
    answer's, ``best`` (1, P)), which were inferred and their prior, and, with samples, the inferred
    ones' median and central intervals (``summary``'s ``physics.*`` entries)."""
    with torch.no_grad():
        values = layout.physics_values(best.to(torch.float64))[0].tolist()
    out = {"most_probable": dict(zip(PHYSICS_COLUMNS, values)), "inferred": list(layout.physics.names),
           "prior": layout.physics.to_json()}
    if posterior is not None:
        out["intervals"] = {n: posterior["intervals"][f"physics.{n}"] for n in layout.physics.names}
    return out


def truth_report(post, samples, layout, truth: dict, intervals: dict | None = None) -> dict:
    """Where a known true start lies in the posterior (benchmarks, the demo, the examples' truths).

    Args:
        post: the ``Posterior``; samples: ``PosteriorSamples`` or None; layout: its ``ParameterLayout``.
        truth: the true ``initial_state`` (position, orientation, linear_velocity, angular_velocity).
        intervals: ``summary``'s intervals (None: without samples).
    Returns:
        ``neg_log_posterior`` and ``observation_chi2`` of the truth; with samples its
        ``credible_level``: the posterior mass of the starts more probable than it (the smallest
        highest-density region holding it; uniform in [0, 1] over truths drawn from the prior), and
        per parameter whether its central 90 % interval holds the truth (``in_90``).
    """
    from dejaview.inference.reference import log_density

    x = layout.encode(position=truth.get("position"), orientation=truth.get("orientation"),
                      linear_velocity=truth.get("linear_velocity"),
                      angular_velocity=truth.get("angular_velocity")).to(torch.float64)
    cost, chi2, _ = post.cost(x)
    out = {"neg_log_posterior": float(cost[0]), "observation_chi2": float(chi2[0])}
    if samples is not None:
        level = log_density(post, x)[0]
        out["credible_level"] = float(samples.weights[samples.log_density > level].sum())
        if intervals is not None:
            value = physical(layout, x)[0]
            out["in_90"] = {name: bool(iv["90%"][0] <= float(value[j]) <= iv["90%"][1])
                            for j, (name, iv) in enumerate(intervals.items())}
    return out


def agreement_warning(agreement: dict | None, what: str) -> str | None:
    """The one-line warning the CLI prints where ``summary``'s ``agreement`` says the runs disagree
    (None where they agree or there was one run); ``what``: what not to trust."""
    if agreement is None or agreement["runs_agree"]:
        return None
    return (f"warning: the sampler's independent runs disagree (R-hat up to {agreement['max_rhat']:.2f} > "
            f"{agreement['limit']:g}): the posterior is rugged; do not trust {what} (docs/inference.md)")


def state_rows(layout, x: torch.Tensor) -> torch.Tensor:
    """(N, 13) the source's initial states of parameters x (N, P) in ``CSV_HEADER``'s order after
    ``weight`` (object-frame origin, orientation w x y z, linear and angular velocity)."""
    with torch.no_grad():
        dec = layout.decode(x.to(layout.base_position.dtype))
    return torch.cat([dec["position"], dec["orientation"], dec["linear_velocity"], dec["angular_velocity"]], -1)


def write_rows(path, header, weights: torch.Tensor, rows: torch.Tensor) -> Path:
    """A CSV of ``sample,weight,...`` rows: header (names), weights (N,), rows (N, C) written exactly."""
    path = Path(path)
    with open(path, "w", newline="", encoding="utf-8") as fh:
        writer = csv.writer(fh, lineterminator="\n")
        writer.writerow(header)
        for i, (w, row) in enumerate(zip(weights.tolist(), rows.tolist())):
            writer.writerow([i, repr(float(w)), *(repr(float(v)) for v in row)])
    return path


def write_csv(path, samples, layout) -> Path:
    """``posterior.csv``: one row per sample, the source's initial state (spec header ``CSV_HEADER``)
    and, where physics was inferred, its friction, restitution and stiffness (``PHYSICS_COLUMNS``)."""
    parts = [state_rows(layout, samples.x)]
    if layout.physics is not None:
        with torch.no_grad():
            parts.append(layout.physics_values(samples.x.to(torch.float64)))
    return write_rows(path, CSV_HEADER + (PHYSICS_COLUMNS if layout.physics is not None else ()),
                      samples.weights, torch.cat(parts, -1))


def path_samples(samples, count: int = ReportParams.paths, seed: int = 0) -> list[int]:
    """Indices of up to ``count`` distinct samples drawn by weight (systematic resampling over
    the distinct samples, so a mode holding 40 % of the mass gets about 40 % of the paths),
    sorted."""
    x, w = samples.x, samples.weights.to(torch.float64)
    distinct, inverse = torch.unique(x, dim=0, return_inverse=True)
    mass = torch.zeros(distinct.shape[0], dtype=torch.float64).index_add_(0, inverse, w)
    first = torch.full((distinct.shape[0],), x.shape[0], dtype=torch.long)
    first = first.scatter_reduce(0, inverse, torch.arange(x.shape[0]), reduce="amin")
    k = min(count, distinct.shape[0])
    if k == 0 or float(mass.sum()) <= 0:
        return []
    gen = torch.Generator().manual_seed(int(seed))
    u = (torch.rand(1, generator=gen, dtype=torch.float64) + torch.arange(k, dtype=torch.float64)) / k
    picks = torch.searchsorted(torch.cumsum(mass / mass.sum(), 0), u).clamp_max(distinct.shape[0] - 1)
    return sorted({int(first[i]) for i in picks.tolist()})


def write_paths(path, problem, samples, count: int = ReportParams.paths, seed: int = 0) -> Path:
    """``posterior_paths.csv``: the source's trajectory (object-frame origin, ``PATHS_HEADER``)
    from a few samples (``path_samples``), re-simulated together; ``sample`` is the row of
    ``posterior.csv`` it starts from. About ``ReportParams.path_records`` records each, the last step
    included."""
    from dejaview.sim.trajectory_csv import trajectory_rows

    chosen = path_samples(samples, count, seed)
    path = Path(path)
    with open(path, "w", newline="", encoding="utf-8") as fh:
        writer = csv.writer(fh, lineterminator="\n")
        writer.writerow(PATHS_HEADER)
        if chosen:
            every = max(1, int(problem.duration_steps) // ReportParams.path_records)
            with torch.no_grad():
                traj = problem.simulate(samples.x[chosen].to(problem.dtype), record_every=every)
            source = problem.frames.names[problem.source]
            for b, index in enumerate(chosen):
                for row in trajectory_rows(problem.frames, traj, b):
                    if row[2] == source:
                        writer.writerow([index, row[0], row[1], *row[3:6]])
    return path


def read_csv(path) -> tuple[np.ndarray, np.ndarray]:
    """``posterior.csv`` back: weights (N,) and states (N, 13) in ``CSV_HEADER``'s order, read by
    name (columns after them, such as the inferred physics, are left out)."""
    with open(path, newline="", encoding="utf-8") as fh:
        reader = csv.reader(fh)
        header = tuple(next(reader))
        if header[:len(CSV_HEADER)] != CSV_HEADER or header[len(CSV_HEADER):] not in ((), PHYSICS_COLUMNS):
            raise ValueError(f"{path}: not a posterior.csv header: {','.join(header)}")
        data = np.array([[float(v) for v in row] for row in reader], dtype=float).reshape(-1, len(header))
    return data[:, 1], data[:, 2:len(CSV_HEADER)]


def position_histogram(positions: torch.Tensor, weights: torch.Tensor, lo, hi, cells) -> np.ndarray:
    """The posterior's marginal over the start area's x-y cells: (ny, nx) probabilities,
    ``[j][i]`` for column i (x) and row j (y, from -y up), summing to 1.

    Args:
        positions: (N, 3) start positions; weights: (N,); lo, hi: the area's (x, y) corners;
        cells: (nx, ny).
    """
    nx, ny = int(cells[0]), int(cells[1])
    fx = (positions[:, 0] - lo[0]) / (hi[0] - lo[0])
    fy = (positions[:, 1] - lo[1]) / (hi[1] - lo[1])
    i = (fx * nx).floor().clamp(0, nx - 1).long()
    j = (fy * ny).floor().clamp(0, ny - 1).long()
    grid = torch.zeros(ny * nx, dtype=torch.float64).index_add_(0, j * nx + i, weights.to(torch.float64))
    total = float(grid.sum())
    return (grid / total).reshape(ny, nx).numpy() if total > 0 else grid.reshape(ny, nx).numpy()
