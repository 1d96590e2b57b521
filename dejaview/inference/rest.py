"""Whether an answer came to rest where the source was seen lying, when, and the duration it needs.

A target seen at rest (``dejaview.losses.targets``) asks the past to bring the source to rest at
the observed pose within the scene's duration. Where the duration is too short for that (the true
past slides for 2 s, the scene simulates 1.5 s), no start explains the observation: the answer
ends still moving, off the observed rest. ``duration_warnings`` finds such answers (and samples),
simulates them on until they rest (at most ``ReportParams.extend_factor`` times the duration) and names the
duration the scene would need.
"""

from __future__ import annotations

import math

import torch

from dejaview.inference.params import ReportParams
from dejaview.losses.targets import REST_WINDOW, rest_time



def needs_rest(problem) -> bool:
    """Whether the scene observes the source lying still at its end (an untimed target at rest)."""
    return any(s.at_rest and s.time is None for s in getattr(problem, "sightings", ()))


def rest_times(problem, x: torch.Tensor, settings, steps: int | None = None) -> list[float | None]:
    """When each start of x (B, P) comes to rest (``dejaview.losses.targets.rest_time`` at
    ``ReportParams.rest_level`` x the rest noise), simulating ``steps`` steps (default the scene's duration).

    Returns:
        seconds per start, None where it still moves at the end.
    """
    steps = problem.duration_steps if steps is None else int(steps)
    with torch.no_grad():
        traj = problem.simulate(x.to(problem.dtype), steps=steps, record_every=1)
    return [rest_time(traj, problem.source, ReportParams.rest_level * settings.rest_speed, ReportParams.rest_level * settings.rest_spin,
                      index=i) for i in range(x.shape[0])]


def end_motion(problem, traj, index: int = 0) -> tuple[float, float]:
    """The source's mean speed (m/s) and spin (rad/s) over the last ``REST_WINDOW / 2`` of a
    trajectory recorded at every step."""
    from dejaview.losses.targets import REST_PARTS
    from dejaview.sim.rotation import normalize_quat, quat_conjugate, quat_multiply, quat_to_rotvec

    steps = traj.steps
    every = int(steps[1] - steps[0]) if steps.numel() > 1 else 1
    lag = min(max(1, int(round(REST_WINDOW / REST_PARTS / (traj.dt * every)))), steps.numel() - 1)
    if lag < 1:
        return 0.0, 0.0
    st = traj.states
    b = problem.source
    span = lag * every * traj.dt
    v = (st.position[-1, index, b] - st.position[-1 - lag, index, b]).norm() / span
    qa, qb = (normalize_quat(st.orientation[k, index, b]) for k in (-1 - lag, -1))
    w = quat_to_rotvec(quat_multiply(qb, quat_conjugate(qa))).norm() / span
    return float(v), float(w)


def suggested_duration(rest_s: float) -> float:
    """A duration that shows a source resting from ``rest_s`` on for a whole rest window: rounded
    up to a tenth of a second."""
    return math.ceil((rest_s + REST_WINDOW + 0.1) * 10 - 1e-9) / 10


def _later_rests(problem, x: torch.Tensor, settings) -> list[float | None]:
    """Rest times of starts x (B, P) simulated for ``ReportParams.extend_factor`` durations (within the scene
    bounds' step budget)."""
    from dejaview.scene.bounds import max_steps

    budget = max_steps() // (2 * max(x.shape[0], 1))  # integration steps at the default 2 substeps
    steps = int(min(ReportParams.extend_factor * problem.duration_steps, max(budget, problem.duration_steps)))
    return rest_times(problem, x, settings, steps=steps)


def duration_warnings(problem, settings, answer: torch.Tensor, samples=None) -> tuple[dict, list[str]]:
    """Rest report of the answer, and warnings where it (or a posterior sample) is still moving at
    the end of a scene that observes the source at rest.

    Args:
        problem: the solve's problem (any backend's).
        settings: ``PosteriorSettings`` (``rest_speed``, ``rest_spin``).
        answer: (1, P) the most probable start.
        samples: ``PosteriorSamples`` (``x`` (N, P), ``weights`` (N,)) or None.
    Returns:
        ``rest``: ``{"came_to_rest_s": seconds or None}`` (plus ``needs_duration_s`` where it
        rests only after the end); warnings: one line each.
    """
    duration = problem.duration_steps * problem.dt
    t, = rest_times(problem, answer, settings)
    rest = {"came_to_rest_s": t}
    warnings = []
    if not needs_rest(problem):
        return rest, warnings
    if t is None:
        later, = _later_rests(problem, answer, settings)
        horizon = ReportParams.extend_factor * duration
        if later is None:
            warnings.append(f"the answer is still moving at the end of the simulation ({duration:g} s) and does "
                            f"not come to rest within {horizon:g} s: it does not explain a source seen lying "
                            f"still; check the target, or give the scene a longer <simulation duration>")
        else:
            need = suggested_duration(later)
            rest["needs_duration_s"] = need
            warnings.append(f"the answer is still moving at the end of the simulation ({duration:g} s); it comes "
                            f"to rest at {later:.2f} s: the scene's duration is too short for a source seen "
                            f"lying still; set <simulation duration=\"{need:g}\"> or more")
    if samples is not None and samples.x.shape[0]:
        w = samples.weights.to(torch.float64)
        order = torch.argsort(w, descending=True)
        seen, pick = set(), []
        for i in order.tolist():
            key = tuple(samples.x[i].tolist())
            if key not in seen:
                seen.add(key)
                pick.append(i)
            if len(pick) >= ReportParams.max_checked:
                break
        idx = torch.as_tensor(pick, dtype=torch.long)
        times = rest_times(problem, samples.x[idx], settings)
        moving = [int(i) for i, tt in zip(idx.tolist(), times) if tt is None]
        if moving:
            later = _later_rests(problem, samples.x[torch.as_tensor(moving)], settings)
            known = [v for v in later if v is not None]
            share = float(w[torch.as_tensor(moving)].sum() / w.sum())
            what = (f"{len(moving)} of the {len(pick)} heaviest distinct posterior samples ({100 * share:.0f} % "
                    f"of the weight) are still moving at the end of the simulation ({duration:g} s)")
            if known:
                need = suggested_duration(max(known))
                rest["samples_need_duration_s"] = need
                warnings.append(f"{what}; they come to rest by {max(known):.2f} s: set <simulation "
                                f"duration=\"{need:g}\"> or more")
            else:
                warnings.append(f"{what} and do not come to rest within {ReportParams.extend_factor * duration:g} s")
    return rest, warnings
