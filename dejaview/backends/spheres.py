"""The ``spheres`` backend: DejaView's sphere-packing simulator behind the backend protocol.

``SpheresProblem`` ties a
World, the scene's other bodies' initial states, the source's ``ParameterLayout``, the target and
the loss settings together. It supplies the rollout; ``Problem`` the loss, gradients and I/O.
``loss(x)`` maps parameters (B, P) to losses (B,) and is free of data-dependent Python branches, so
it runs under ``torch.func`` transforms (forward mode) as well as autograd (reverse mode).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field

import torch

from dejaview.backends.base import (DEFAULT_ORIENTATION_WEIGHT, GRADIENT_MODES, Problem, check_inference,
                                    loss_record_every, loss_steps, model_points, sightings_of)
from dejaview.backends.params import ParameterLayout, layout_from_scene
from dejaview.errors import InferenceError
from dejaview.sim.integrate import rollout
from dejaview.sim.physics import PhysicsModel
from dejaview.sim.rotation import normalize_quat, quat_rotate
from dejaview.sim.state import State, Trajectory
from dejaview.sim.world import World


@dataclass
class SpheresProblem(Problem):
    """The ``spheres`` backend's problem: DejaView's sphere-packing simulator (``dejaview.sim``),
    torch or native engine, both gradient modes (the rest: ``Problem``).

    Attributes:
        world: the World.
        layout: ParameterLayout of the source.
        source: index of the source body in the world.
        base: State (1, N, ...) of every body as given in the scene.
        targets: the scene's Targets.
        sightings: what each observes (``dejaview.losses.targets``).
        loss_kind: ``pose`` | ``add`` | ``position``.
        evaluate: ``best`` | ``final``.
        steps: rollout length (up to the target time when it is pinned).
        penalties: ((body_a, body_b, weight), ...).
        orientation_weight: metres per radian in the pose loss.
        points: (M, 3) model points (object frame) for the ADD loss, or None.
        checkpoint_every: reverse-mode checkpoint chunk (None: no checkpointing).
        compile: run the rollouts of gradient evaluations through ``torch.compile``
            (``rollout(compile=True)``): faster per loss + gradient than eager torch
            after a first compile of minutes (``docs/benchmarks.md``); not combined
            with checkpointing. Rollouts without autograd (screening,
            the final re-simulation) stay on ``engine``: they are few, and each grad
            mode would need its own compile.
        engine: simulation engine of the rollouts (``dejaview.sim.native.ENGINES``):
            ``auto`` (default) runs the native C++ simulator where it applies (float64
            on the CPU), the same model with exact forward- and reverse-mode gradients,
            the fastest by far (``docs/benchmarks.md``, "Simulator"); ``torch`` runs
            ``dejaview.sim.integrate``. ``compile`` implies ``torch`` for the rollouts
            it compiles.
    """

    world: World
    layout: ParameterLayout
    source: int
    base: State
    targets: tuple
    sightings: tuple = ()
    loss_kind: str = "pose"
    evaluate: str = "best"
    steps: int = 0
    penalties: tuple = ()
    orientation_weight: float = DEFAULT_ORIENTATION_WEIGHT
    points: torch.Tensor | None = None
    checkpoint_every: int | None = None
    record_every: int = 1
    compile: bool = False
    engine: str = "auto"
    evaluations: int = field(default=0, init=False)

    @staticmethod
    def from_scene(scene, world: World | None = None, *, dtype=torch.float64,
                   orientation_weight: float = DEFAULT_ORIENTATION_WEIGHT,
                   checkpoint_every: int | None = None, max_speed: float = 3.0,
                   max_spin: float = 10.0, engine: str = "auto", compile: bool = False) -> "SpheresProblem":
        """Build the problem of a scene's ``<inference>`` (``engine``, ``compile``: the attributes).

        Raises:
            InferenceError: no inference section, nothing free, fixed/unknown source or target.
        """
        from dejaview.sim.build import initial_state

        inf = check_inference(scene)
        world = world if world is not None else World.from_scene(scene, dtype=dtype)
        try:
            src = world.body_index(inf.source)
        except Exception:
            raise InferenceError(f"source {inf.source!r} is not a movable object") from None
        for p in inf.penalties:
            for name in p.between:
                known = name in world.names or any(s.name == name for s in world.statics)
                if not known:
                    raise InferenceError(f"penalty names unknown object {name!r}")
        physics = PhysicsModel.from_scene(scene, world)
        layout = layout_from_scene(scene, dtype=world.dtype, max_speed=max_speed, max_spin=max_spin,
                                   physics=physics)
        if layout.size == 0:
            raise InferenceError("no free parameter: the start area pins the position and nothing "
                                 "else is free")
        steps = loss_steps(scene, world.dt, world.steps)
        points = None
        if inf.loss == "add":
            points = model_points(scene, scene.object(inf.source), world.dtype)
        return SpheresProblem(
            world=world, layout=layout, source=src, base=initial_state(world, scene),
            targets=tuple(inf.targets), sightings=sightings_of(scene, world.dt, world.steps),
            loss_kind=inf.loss, evaluate=inf.evaluate, steps=steps,
            penalties=tuple((p.between[0], p.between[1], p.weight) for p in inf.penalties),
            orientation_weight=orientation_weight, points=points, checkpoint_every=checkpoint_every,
            record_every=loss_record_every(scene, steps, world.dt), engine=engine, compile=compile)

    # ----------------------------------------------------------------- rollout
    @functools.cached_property
    def _source_com_offset(self) -> bool:
        """Whether the source's centre of mass is off its object-frame origin."""
        return bool(self.world.com[self.source].detach().ne(0).any())

    def initial_state(self, x: torch.Tensor) -> State:
        """State (B, N, ...) with the source's initial state from parameters x (B, P)."""
        s = self.layout.decode(x)
        b = x.shape[0]
        # the source alone (World.state wants every body): object-frame origin -> centre of mass
        q = normalize_quat(s["orientation"])
        position = s["position"]
        if self._source_com_offset:  # (a centred mesh, e.g. a box or a ball, skips the rotation)
            position = position + quat_rotate(q, self.world.com[self.source].expand_as(position))
        src = (position, q, s["linear_velocity"], s["angular_velocity"])
        if self.world.num_bodies == 1:  # the source alone: its state is the whole state
            return State(*(t[:, None] for t in src))
        base = self.base.index(slice(0, 1))
        out = []
        for field_name, value in zip(("position", "orientation", "linear_velocity", "angular_velocity"),
                                     (t[:, None] for t in src)):
            full = getattr(base, field_name).expand(b, *getattr(base, field_name).shape[1:])
            parts = [full[:, i:i + 1] for i in range(self.world.num_bodies)]
            parts[self.source] = value
            out.append(torch.cat(parts, 1))
        return State(*out)

    def simulate(self, x: torch.Tensor, steps: int | None = None, record_every: int | None = None,
                 checkpoint: bool = False) -> Trajectory:
        """Rollout from parameters x (B, P) (with inferred physics: each candidate's own)."""
        model = self.layout.physics
        compiled = self.compile and torch.is_grad_enabled() and model is None
        physics = None if model is None else model.engine_logs(self.layout.physics_z(x))
        return rollout(self.world, self.initial_state(x), steps=self.steps if steps is None else steps,
                       record_every=record_every or self.record_every,
                       checkpoint_every=self.checkpoint_every if checkpoint and not compiled else None,
                       compile=compiled, engine="torch" if compiled else self.engine, physics=physics)

    # ------------------------------------------------------------ backend surface
    backend = "spheres"
    gradient_modes = GRADIENT_MODES

    @property
    def frames(self) -> World:
        return self.world

    @property
    def dt(self) -> float:
        return self.world.dt

    @property
    def duration_steps(self) -> int:
        return self.world.steps

    def simulation_settings(self) -> dict:
        """Simulation numbers for result.json."""
        return {"dt": self.world.dt, "substeps": self.world.substeps, "steps": self.steps}

    def backend_options(self):
        """``BackendOptions`` of this problem's engine (a worker rebuilds it with that engine;
        compiled rollouts stay in this process: each compile takes minutes)."""
        from dejaview.backends.options import BackendOptions

        return BackendOptions.of(self.backend, engine=self.engine)

    def __repr__(self) -> str:
        return f"SpheresProblem({self.world.names}, source={self.source}, P={self.num_params})"



class SpheresBackend:
    """The ``spheres`` backend (``dejaview.backends.base.Backend``)."""

    name = "spheres"
    gradient_modes = GRADIENT_MODES
    simulate_options = frozenset({"dtype", "engine", "world", "max_steps", "memory_limit"})
    problem_options = frozenset({"dtype", "engine", "compile", "world", "checkpoint_every", "orientation_weight",
                                 "max_speed", "max_spin"})

    def available(self) -> str | None:
        return None

    def option_problem(self, options: dict) -> str | None:
        """Why ``options`` cannot run, or None: ``engine`` one of ``dejaview.sim.native.ENGINES``;
        ``compile`` compiles torch rollouts, so not with the native engine; the native engine
        runs in float64, so not with ``dtype`` float32."""
        from dejaview.sim.native import ENGINES

        engine = options.get("engine", "auto")
        if engine not in ENGINES:
            return f"unknown engine {engine!r}; choose one of {', '.join(ENGINES)}"
        if options.get("compile") and engine == "native":
            return ("compile applies to the torch engine; the native engine is compiled C++ already: drop "
                    "--compile or choose --engine torch")
        if options.get("dtype") not in (None, torch.float64) and engine == "native":
            return "the native engine runs in float64; drop --float32 or use --engine torch"
        return None

    def make_problem(self, scene, **options) -> SpheresProblem:
        """``SpheresProblem.from_scene(scene, **options)`` (``world``, ``dtype``, ``engine``, ...)."""
        return SpheresProblem.from_scene(scene, **options)

    def simulate(self, scene, *, steps=None, record_every=1, callback=None, should_stop=None, **options):
        """``dejaview.sim.simulate.simulate`` (options: ``dtype``, ``engine``, ``world``, ``max_steps``,
        ``memory_limit``)."""
        from dejaview.backends import check_options
        from dejaview.errors import SimulationError
        from dejaview.sim.simulate import simulate

        check_options(self, options, SimulationError)
        return simulate(scene, steps=steps, record_every=record_every, callback=callback,
                        should_stop=should_stop, **options)
