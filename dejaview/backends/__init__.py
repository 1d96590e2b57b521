"""Physics backends behind one inference interface.

A backend turns a scene's ``<inference>`` into a *problem*: parameters of the
source's initial state (``ParameterLayout``, shared by every backend) ->
simulated trajectory -> loss, with gradients. The inference loop
(``dejaview.solve``), the heatmap, the CLI (``--backend``) and the service
use only this surface:

- ``backend``: its name; ``gradient_modes``: the gradient modes it offers;
- ``layout`` (ParameterLayout, may be replaced, e.g. per-candidate boxes),
  ``num_params`` (P), ``dtype``, ``source`` (index of the source among the
  movable bodies), ``body_names`` (N,), ``loss_kind``, ``evaluate``,
  ``steps`` (rollout length of the loss), ``duration_steps`` (the scene's
  whole duration), ``dt``, ``evaluations`` (loss evaluations so far);
- ``loss(x) -> (K,)`` and ``value_and_grad(x, mode) -> ((K,), (K, P))`` of
  parameters ``x`` (K, P); ``objective_and_grad(x, mode)``: what the
  optimisers minimise, ``0.5 * loss^2`` and its gradient;
- ``simulate(x, steps=None, record_every=None) -> Trajectory``
  (``dejaview.sim.integrate.Trajectory``: states (T, K, N, ...) of the
  movable bodies with centre-of-mass positions, w x y z quaternions, world
  velocities, as the sphere simulator records them);
- ``final_pose(traj, index=0)``: object-frame position and orientation of
  the source at the last record; ``trajectory_csv(traj, index=0)`` and
  ``write_trajectory(path, traj, index=0)``: the trajectory CSV of every
  movable object (scene-format spec, "Outputs");
- ``simulation_settings() -> dict``: what result.json reports.

Backends:

- ``spheres``: DejaView's sphere-packing simulator on PyTorch
  (``dejaview.backends.problem.InferenceProblem``, wrapped by ``SpheresProblem``);
- ``warp``: NVIDIA Warp's ``warp.sim`` (XPBD or semi-implicit), reverse mode
  through ``wp.Tape`` (``dejaview.backends.warp``; needs the ``warp`` extra).
"""

from __future__ import annotations

from dejaview.errors import InferenceError

BACKENDS = ("spheres", "warp")
WARP_MISSING = "the warp backend needs the extra: pip install 'dejaview[warp]'"


def warp_available() -> bool:
    """True when ``warp`` (``warp-lang``) can be imported."""
    try:
        import warp  # noqa: F401
    except ImportError:
        return False
    return True


def simulate_warp(scene, out_dir, steps: int | None = None, record_every: int = 1):
    """Run a scene forward in Warp and write ``out_dir/trajectory.csv`` (``dejaview simulate
    --backend warp`` and the service's simulate jobs).

    Returns:
        (path of trajectory.csv, Trajectory with states (T, 1, N, ...), body names (N,)).
    Raises:
        SimulationError: Warp is not installed.
    """
    from pathlib import Path

    from dejaview.errors import SimulationError
    from dejaview.io.trajectory import write_trajectory_csv

    if not warp_available():
        raise SimulationError(WARP_MISSING)
    from dejaview.backends.warp import simulate_scene

    frames, traj = simulate_scene(scene, steps=steps, record_every=record_every)
    return write_trajectory_csv(Path(out_dir) / "trajectory.csv", frames, traj), traj, frames.names


def make_problem(scene, backend: str = "spheres", **options):
    """The inference problem of a scene's ``<inference>`` on one backend.

    Args:
        scene: a ``Scene`` or a path to a scene file.
        backend: ``"spheres"`` | ``"warp"``.
        options: backend options: for ``spheres`` those of
            ``InferenceProblem.from_scene`` (``world``, ``dtype``,
            ``checkpoint_every``, ...); for ``warp`` those of
            ``WarpProblem.from_scene`` (``integrator``, ``device``, ``substeps``, ...).
    Returns:
        a problem with the interface of this module's docstring.
    Raises:
        InferenceError: unknown backend, warp not installed, or the scene cannot be solved.
    """
    from dejaview.scene import Scene

    if not hasattr(scene, "objects"):
        scene = Scene.from_xml(scene)
    if backend == "spheres":
        from dejaview.backends.spheres import SpheresProblem

        return SpheresProblem.from_scene(scene, **options)
    if backend == "warp":
        if not warp_available():
            raise InferenceError(WARP_MISSING)
        from dejaview.backends.warp import WarpProblem

        return WarpProblem.from_scene(scene, **options)
    raise InferenceError(f"unknown backend {backend!r}; choose one of {', '.join(BACKENDS)}")


def as_problem(problem):
    """A problem with this module's interface: a bare ``InferenceProblem`` is wrapped
    (``SpheresProblem``, sharing its state), anything else is returned as it is."""
    from dejaview.backends.spheres import SpheresProblem
    from dejaview.backends.problem import InferenceProblem

    if isinstance(problem, InferenceProblem):
        return SpheresProblem(problem)
    return problem


__all__ = ["BACKENDS", "WARP_MISSING", "as_problem", "make_problem", "warp_available"]
