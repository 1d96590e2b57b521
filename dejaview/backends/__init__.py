"""Physics backends behind one protocol (``dejaview.backends.base``).

A backend (``Backend``) builds a *problem* from a scene's ``<inference>`` and runs scenes forward.
Every problem derives from ``Problem``: parameters of the source's initial state
(``ParameterLayout``, shared by every backend) -> simulated trajectory -> loss, with gradients. The
base owns the loss (``dejaview.losses``), the objective, the gradients, the final pose and the
trajectory CSV; a backend supplies the rollout. The inference loop (``dejaview.solve``), the
heatmap, the CLI (``--backend``) and the service reach backends through this module only:

- ``get_backend(name)``: the registered ``Backend`` (``BACKENDS``: the names);
- ``BackendOptions.of(name, **settings)``: a backend with its own settings (the engine, the
  integrator, ...), checked once and passed through solve, heatmap, CLI and service unread;
- ``make_problem(scene, backend, **options)``: its problem;
- ``simulate(scene, backend, ...)``: the scene forward, a ``SimulationRun``.

Backends:

- ``spheres``: DejaView's sphere-packing simulator, torch or native engine
  (``dejaview.backends.spheres``);
- ``warp``: NVIDIA Warp's ``warp.sim`` (XPBD or semi-implicit), reverse mode through ``wp.Tape``
  (``dejaview.backends.warp``; needs the ``warp`` extra, imported only when used).
"""

from __future__ import annotations

from dejaview.backends.base import Backend, Problem
from dejaview.backends.options import BackendOptions
from dejaview.backends.spheres import SpheresBackend
from dejaview.errors import DejaViewError, InferenceError

WARP_MISSING = "the warp backend needs the extra: pip install 'dejaview[warp]'"


def warp_available() -> bool:
    """True when ``warp`` (``warp-lang``) can be imported."""
    try:
        import warp  # noqa: F401
    except ImportError:
        return False
    return True


class WarpBackend:
    """The ``warp`` backend (``Backend``); ``dejaview.backends.warp`` is imported on first use."""

    name = "warp"
    gradient_modes = ("reverse",)
    simulate_options = frozenset({"max_steps", "device", "integrator", "substeps", "iterations", "restitution"})
    problem_options = frozenset({"device", "integrator", "substeps", "iterations", "restitution", "max_envs",
                                 "orientation_weight", "max_speed", "max_spin"})

    def available(self) -> str | None:
        return None if warp_available() else WARP_MISSING

    def option_problem(self, options: dict) -> str | None:
        """Why ``options`` cannot run, or None (``dejaview.backends.warp.settings.override_problem``;
        the scene's own ``warp-*`` attributes are checked with the scene)."""
        from dejaview.backends.warp.settings import override_problem

        reasons = (override_problem(k, v) for k, v in options.items() if v is not None)
        return next((r for r in reasons if r), None)

    def make_problem(self, scene, **options) -> Problem:
        """``WarpProblem.from_scene(scene, **options)`` (``integrator``, ``device``, ``substeps``, ...)."""
        from dejaview.backends.warp import WarpProblem

        return WarpProblem.from_scene(scene, **options)

    def simulate(self, scene, *, steps=None, record_every=1, callback=None, should_stop=None, **options):
        """One Warp run (options: ``max_steps``, the step budget; ``device``, ``integrator``,
        ``substeps``, ``iterations``, ``restitution``); ``should_stop`` is polled before it,
        ``callback`` called after it."""
        import time

        from dejaview.backends.warp import simulate_scene, warp_settings
        from dejaview.errors import SimulationError
        from dejaview.scene import bounds
        from dejaview.sim.simulate import SimulationRun, SimulationStopped

        check_options(self, options, SimulationError)
        max_steps = bounds.max_steps(options.pop("max_steps", None))
        substeps = warp_settings(scene, **{k: v for k, v in options.items() if k != "device"})["substeps"]
        reason = bounds.budget_problem(scene.simulation.steps if steps is None else int(steps), substeps,
                                       max_steps, "the simulation")
        if reason:
            raise SimulationError(reason)
        if should_stop is not None and should_stop():
            raise SimulationStopped("stopped before the first step")
        start = time.perf_counter()
        frames, traj = simulate_scene(scene, steps=steps, record_every=record_every, **options)
        n = int(traj.steps[-1])
        if callback is not None:
            callback(n, n)
        return SimulationRun(world=frames, trajectory=traj, steps=n, elapsed_s=time.perf_counter() - start,
                             backend="warp")


REGISTRY: dict[str, Backend] = {b.name: b for b in (SpheresBackend(), WarpBackend())}
"""Every backend by name: the one place a backend is registered."""
BACKENDS = tuple(REGISTRY)


def check_options(backend: Backend, options, error: type[DejaViewError] = InferenceError,
                  known: frozenset[str] | None = None) -> None:
    """Raise ``error`` naming the first of ``options`` not in ``known`` (default: what
    ``backend.simulate`` takes), and which backends do take it."""
    known = backend.simulate_options if known is None else known
    unknown = sorted(set(options) - known)
    if unknown:
        owners = [b.name for b in REGISTRY.values() if unknown[0] in b.problem_options | b.simulate_options]
        where = f"an option of the {' and '.join(owners)} backend" if owners else "no backend's option"
        raise error(f"{unknown[0].replace('_', '-')} is {where}, not of {backend.name}")


def get_backend(name: str, error: type[DejaViewError] = InferenceError) -> Backend:
    """The backend called ``name``, ready to run.

    Raises:
        ``error`` (InferenceError by default): unknown name, or a backend that cannot run here
        (one line saying what to install).
    """
    if name not in REGISTRY:
        raise error(f"unknown backend {name!r}; choose one of {', '.join(BACKENDS)}")
    backend = REGISTRY[name]
    missing = backend.available()
    if missing:
        raise error(missing)
    return backend


def make_problem(scene, backend: "str | BackendOptions" = "spheres", **options) -> Problem:
    """The inference problem of a scene's ``<inference>`` on one backend.

    Args:
        scene: a ``Scene`` or a path to a scene file.
        backend: a name of ``BACKENDS``, or ``BackendOptions`` (its settings, then ``options``).
        options: the backend's own (``SpheresProblem.from_scene``: ``world``, ``dtype``,
            ``checkpoint_every``, ``engine``, ...; ``WarpProblem.from_scene``: ``integrator``,
            ``device``, ``substeps``, ...).
    Raises:
        InferenceError: unknown backend, warp not installed, or the scene cannot be solved.
    """
    from dejaview.scene import Scene

    if not hasattr(scene, "objects"):
        scene = Scene.from_xml(scene)
    if isinstance(backend, BackendOptions):
        return backend.make_problem(scene, **options)
    return get_backend(backend).make_problem(scene, **options)


def simulate(scene, backend: str = "spheres", **options):
    """Run a scene forward on one backend (``Backend.simulate``): a ``SimulationRun``.

    Raises:
        SimulationError: unknown backend, warp not installed, or the scene cannot be simulated.
    """
    from dejaview.errors import SimulationError

    return get_backend(backend, SimulationError).simulate(scene, **options)


def as_problem(problem) -> Problem:
    """``problem`` itself, checked: every backend's problem is a ``Problem`` (the spheres
    backend's ``SpheresProblem`` included).

    Raises:
        InferenceError: something that is not a ``Problem``.
    """
    if not isinstance(problem, Problem):
        raise InferenceError(f"not a backend problem: {type(problem).__name__}")
    return problem


__all__ = ["BACKENDS", "REGISTRY", "WARP_MISSING", "Backend", "BackendOptions", "Problem", "as_problem",
           "check_options", "get_backend", "make_problem", "simulate", "warp_available"]
