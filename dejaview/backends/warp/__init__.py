"""The ``warp`` backend: NVIDIA Warp's ``warp.sim`` (warp-lang 1.9.1) behind the backend protocol.

Imported only when asked for (``make_problem(scene, "warp")``); needs the ``warp`` extra
(``pip install 'dejaview[warp]'``). Runs on Warp's ``cuda`` device when there is one, else on
``cpu`` (kernels are compiled by Warp's bundled clang on first use and kept in its kernel cache).

- ``settings``: the ``warp-*`` attributes of ``<simulation>`` (no Warp import);
- ``model``: the scene as ``warp.sim`` models, rollouts, the tape's reverse pass;
- ``links``: a moving robot's links as kinematic bodies driven along their paths;
- ``problem``: ``WarpProblem``, whose rollouts hand Warp's states to torch, so the losses are
  ``dejaview.losses`` as on every backend.

What it does and its known limits: ``docs/engines.md``, "The Warp backend".
"""

from dejaview.backends.warp.model import BodyFrames, WarpSimulator, default_device, simulate_scene
from dejaview.backends.warp.problem import WarpProblem
from dejaview.backends.warp.settings import INTEGRATORS, warp_settings

__all__ = ["INTEGRATORS", "BodyFrames", "WarpProblem", "WarpSimulator", "default_device", "simulate_scene",
           "warp_settings"]
