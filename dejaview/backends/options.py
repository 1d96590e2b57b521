"""A backend and its own settings as one object that solve, the heatmap, the CLI and the service
pass along without reading.

Which simulation engine the spheres backend runs, whether its rollouts are compiled, which
integrator Warp uses: these are the backend's business. ``BackendOptions`` holds the backend's
name and those settings; only the backend reads them (``Backend.problem_options`` and
``Backend.simulate_options`` name what it takes, ``Backend.option_problem`` checks the values).
A setting no backend takes, or one of another backend, is refused when the object is built, with
one line naming it::

    opts = BackendOptions.of("spheres", engine="torch", compile=True)
    solve(scene, backend=opts)            # solve never looks inside
    opts.make_problem(scene)              # the spheres backend's problem, compiled torch rollouts
    BackendOptions.of("warp", engine="native")  # InferenceError: engine is an option of the spheres backend, not of warp
"""

from __future__ import annotations

from dataclasses import dataclass

from dejaview.errors import DejaViewError, InferenceError


@dataclass(frozen=True)
class BackendOptions:
    """Backend name and settings ((key, value), ...), checked once by ``of`` (picklable: heatmap
    workers and Ray actors rebuild their problem from it).

    Attributes:
        name: a name of ``dejaview.backends.BACKENDS``.
        settings: the backend's own settings, as given (sorted by key).
    """

    name: str = "spheres"
    settings: tuple[tuple[str, object], ...] = ()

    @staticmethod
    def of(backend: "str | BackendOptions | None" = None, error: type[DejaViewError] = InferenceError,
           **settings) -> "BackendOptions":
        """Backend options, checked: ``backend`` a name (None: ``spheres``) or a ``BackendOptions``
        whose settings ``settings`` extend; a setting given as None is left out (not given).

        Raises:
            ``error``: an unknown backend, one that cannot run here, a setting it does not take
            (the line names the backends that do), or a bad value (the backend's own line).
        """
        from dejaview.backends import check_options, get_backend

        if isinstance(backend, BackendOptions):
            name, merged = backend.name, dict(backend.settings)
        else:
            name, merged = backend or "spheres", {}
        merged.update({k: v for k, v in settings.items() if v is not None})
        chosen = get_backend(name, error)
        check_options(chosen, merged, error, known=chosen.problem_options | chosen.simulate_options)
        reason = chosen.option_problem(merged)
        if reason:
            raise error(reason)
        return BackendOptions(name=name, settings=tuple(sorted(merged.items())))

    def get(self, key: str, default=None):
        """One setting's value, ``default`` where not given."""
        return dict(self.settings).get(key, default)

    def make_problem(self, scene, **extra):
        """The backend's ``Problem`` of a scene's ``<inference>`` (``Backend.make_problem``) with the
        settings it takes for problems, plus ``extra`` (e.g. a ``world`` to reuse).

        Raises:
            InferenceError: the scene cannot be solved.
        """
        from dejaview.backends import get_backend

        backend = get_backend(self.name)
        given = {k: v for k, v in self.settings if k in backend.problem_options}
        return backend.make_problem(scene, **given, **extra)

    def simulate(self, scene, **run):
        """The scene forward on the backend (``Backend.simulate``) with the settings it takes for
        runs; ``run``: ``steps``, ``record_every``, ``callback``, ``should_stop``, ``max_steps``.

        Raises:
            SimulationError: the scene cannot be simulated.
        """
        from dejaview.backends import get_backend
        from dejaview.errors import SimulationError

        backend = get_backend(self.name, SimulationError)
        given = {k: v for k, v in self.settings if k in backend.simulate_options}
        return backend.simulate(scene, **given, **run)


__all__ = ["BackendOptions"]
