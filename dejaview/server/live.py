"""Live answers (protocol addition "Live answers"): one observation answered from a scene's
amortised model in the server process, without queueing behind jobs.

A ``live`` message names a scene and where its source is seen now. ``LiveAnswers`` answers it
from the flow alone (``dejaview.inference.amortised.answer.live``: no rollout) on a small pool of
threads of the server process, from caches, so that only the first message for a scene pays for
more than the flow's draws:

- the scene: read and checked once per scene text (its SHA-256 with the folder its files
  resolve in), then its ``Posterior`` (the world, built once), the fingerprint of what an
  amortised model of it is trained for and its own observation vector (``observables``);
- the new target: written into that observation vector (``observables.with_target``), so a
  message costs no scene, world or problem;
- the model: ``<results_dir>/models/<fingerprint>.safetensors`` (written by ``train`` jobs,
  ``jobs._train``, or put there by hand from ``dejaview train``), loaded once and again only
  when the file changes (its size, time or inode). A scene whose statics, source, prior or kind
  of observation change has another fingerprint: its old model is simply not found for it, and
  the answer is the error ``no_model``.

``LiveQueue`` is one connection's coalescing: a connection's live messages are answered one at a
time, and of those that arrived while one was answered only the newest is answered next (the
others are dropped), so a client dragging the source at any rate costs the server at most one
answer at a time and always gets the answer to where it let go.

The server process sets torch to one thread for this (measured on a loaded 2-core machine: 2
threads made 1,000 draws 2-30x slower than one, 60 ms against 0.2-3 s); the job workers are
other processes.
"""

from __future__ import annotations

import asyncio
import collections
import hashlib
import logging
import os
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

from dejaview.server.errors import ServiceError, from_library_error
from dejaview.server.messages import LiveResultMessage

log = logging.getLogger("dejaview.server")

MODELS = "models"
"""The folder of the results dir that holds the amortised models, one per scene fingerprint."""
CACHED_SCENES = 16
CACHED_MODELS = 8


def model_path(models_dir: Path, fingerprint: str) -> Path:
    """Where the model of a scene with this fingerprint lives."""
    return Path(models_dir) / f"{fingerprint}.safetensors"


def model_digest(path: Path) -> str:
    """The SHA-256 of a model file's bytes, as hex (a train job records it: ``GET /jobs/{id}/model``
    serves the file only while it is still the one the job wrote).

    Raises:
        OSError: the file cannot be read.
    """
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


@dataclass
class _Scene:
    post: object  # the scene's Posterior
    fingerprint: str
    y: object  # (D,) its own observation vector


class LiveAnswers:
    """Answers ``live`` messages from cached posteriors and models (module docstring).

    Args:
        config: the server's ``ServerConfig`` (scene root, results dir, limits, ``live_draws``,
            ``live_samples``).
    """

    def __init__(self, config):
        self.config = config
        self.models_dir = config.results_dir / MODELS
        self.scenes: collections.OrderedDict[str, _Scene] = collections.OrderedDict()
        self.models: collections.OrderedDict[str, tuple] = collections.OrderedDict()  # fp -> (stat, model)
        self.lock = threading.Lock()  # the caches' dicts
        self.building = threading.Lock()  # one scene or model built at a time
        self.executor: ThreadPoolExecutor | None = None

    async def answer(self, message) -> LiveResultMessage:
        """The ``live-result`` of a ``LiveMessage``, computed on a thread of this pool.

        Raises:
            ServiceError: ``no_model``, the scene's errors (``invalid_scene``, ``scene_not_found``,
                ``path_outside_root``, ``scene_too_large``, ``limit_exceeded``), the library's.
        """
        if self.executor is None:
            self.executor = ThreadPoolExecutor(max_workers=2, thread_name_prefix="dejaview-live",
                                               initializer=_one_torch_thread)
        return await asyncio.get_running_loop().run_in_executor(self.executor, self._answer, message)

    def close(self) -> None:
        if self.executor is not None:
            self.executor.shutdown(wait=False, cancel_futures=True)

    def _answer(self, message) -> LiveResultMessage:
        from dejaview.inference.amortised.answer import live
        from dejaview.inference.amortised.observables import with_target
        from dejaview.inference.params import AmortisedParams

        t0 = time.perf_counter()
        try:
            scene = self._scene(message)
            model = self._model(scene)
            y = with_target(scene.post, scene.y, message.target.position, message.target.orientation)
            out = live(scene.post, model, params=AmortisedParams(live_draws=self.config.live_draws),
                       cells=tuple(message.cells or (16, 16)), y=y)
        except ServiceError:
            raise
        except Exception as exc:
            err = from_library_error(exc)
            if err.code == "internal_error":
                log.exception("error answering a live message")
            raise err from None
        samples = [[round(v, 6) for v in row] for row in out["samples"][:self.config.live_samples].tolist()]
        return LiveResultMessage(request_id=message.request_id, heatmap=out.get("heatmap"), samples=samples,
                                 most_probable=out["most_probable"], fitted=bool(out["fitted"]),
                                 draws=self.config.live_draws, model=model.fingerprint,
                                 seconds=time.perf_counter() - t0)

    # ------------------------------------------------------------ caches
    def _scene(self, message) -> _Scene:
        """The cached scene of a message; read, checked and built on a miss."""
        from dejaview.server.scenes import read_scene_input, resolve_scene_path

        root, limit = self.config.scene_root, self.config.max_scene_bytes
        if message.scene_xml is not None:
            key = _key(root, message.scene_xml.encode("utf-8", errors="surrogatepass"))
        else:  # the path's checks every time; the text's hash says whether it is the cached scene
            path = resolve_scene_path(root, message.scene_path)
            try:
                with open(path, "rb") as fh:
                    key = _key(path.parent, fh.read(limit + 1))
            except OSError as exc:
                raise ServiceError("scene_not_found",
                                   f"scene_path {message.scene_path!r}: cannot read: {exc.strerror}") from None
        hit = self._get(self.scenes, key)
        if hit is not None:
            return hit
        with self.building:
            hit = self._get(self.scenes, key)
            if hit is not None:
                return hit
            scene_input = read_scene_input(root, scene_xml=message.scene_xml, scene_path=message.scene_path,
                                           max_bytes=limit)
            entry = self._build(scene_input)
            key = _key(scene_input.base_dir, scene_input.text.encode("utf-8"))  # the text read now
            self._put(self.scenes, key, entry, CACHED_SCENES)
            return entry

    def _build(self, scene_input) -> _Scene:
        from dejaview.inference.amortised import fingerprint
        from dejaview.inference.amortised.observables import observed
        from dejaview.inference.posterior import Posterior
        from dejaview.server.scenes import check_job

        scene = scene_input.scene
        check_job("train", scene, {}, self.config)  # the server's limits, and an <inference> with a start area
        post = Posterior.from_scene(scene).without_model()
        return _Scene(post=post, fingerprint=fingerprint(post), y=observed(post))

    def _model(self, scene: _Scene):
        """The scene's model from the models folder, loaded again only when its file changed.

        Raises:
            ServiceError: ``no_model``.
        """
        from dejaview.inference.amortised import AmortisedModel

        path = model_path(self.models_dir, scene.fingerprint)
        try:
            st = os.stat(path)
        except OSError:
            raise ServiceError("no_model", f"this scene has no amortised model yet (fingerprint "
                                           f"{scene.fingerprint[:12]}): submit a 'train' job for it") from None
        stamp = (st.st_size, st.st_mtime_ns, st.st_ino)
        hit = self._get(self.models, scene.fingerprint)
        if hit is not None and hit[0] == stamp:
            return hit[1]
        with self.building:
            model = AmortisedModel.load(path)
            if model.fingerprint != scene.fingerprint:
                raise ServiceError("inference_error", f"{MODELS}/{path.name} holds a model trained for another "
                                                      f"scene ({model.fingerprint[:12]}): train this one again")
            self._put(self.models, scene.fingerprint, (stamp, model), CACHED_MODELS)
            return model

    def _get(self, cache: collections.OrderedDict, key):
        with self.lock:
            value = cache.get(key)
            if value is not None:
                cache.move_to_end(key)
            return value

    def _put(self, cache: collections.OrderedDict, key, value, size: int) -> None:
        with self.lock:
            cache[key] = value
            cache.move_to_end(key)
            while len(cache) > size:
                cache.popitem(last=False)


class LiveQueue:
    """One connection's live messages: one answered at a time, then the newest that waits (module
    docstring).

    Args:
        answer: ``async answer(message) -> reply``.
        send: called with each reply.
        fail: called with ``(exception, message)`` where an answer raised.
    """

    def __init__(self, answer, send, fail):
        self.answer, self.send, self.fail = answer, send, fail
        self.waiting = None
        self.task: asyncio.Task | None = None
        self.dropped = 0  # superseded messages, never answered

    def put(self, message) -> None:
        if self.waiting is not None:
            self.dropped += 1
        self.waiting = message
        if self.task is None or self.task.done():
            self.task = asyncio.get_running_loop().create_task(self._run())

    async def _run(self) -> None:
        while self.waiting is not None:
            message, self.waiting = self.waiting, None
            try:
                reply = await self.answer(message)
            except asyncio.CancelledError:
                raise
            except Exception as exc:
                self.fail(exc, message)
            else:
                self.send(reply)

    def close(self) -> None:
        self.waiting = None
        if self.task is not None:
            self.task.cancel()


def _key(base: Path, data: bytes) -> str:
    return hashlib.sha256(str(base).encode() + b"\0" + data).hexdigest()


def _one_torch_thread() -> None:
    import torch

    torch.set_num_threads(1)
