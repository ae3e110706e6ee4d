"""Mark detection in worker processes: frames handed over in shared memory, one block per camera.

Detection is mostly many small numpy and OpenCV calls, so threads serialise on the GIL: four
2048 × 2048 frames took as long with two threads as with one (13 ms) and they also compete with
the REST API in the server process. Worker processes run them side by side, away from HTTP.
A frame is copied once into its camera's shared-memory block (~0.1 ms for 4 MiB). The camera
geometry and the recipe are pickled once per (camera, recipe) pair and sent as bytes with a
token; a worker unpickles a token's pair once and keeps the objects, so the detector's window
prediction cache (keyed on those very objects) hits from the second trigger on, as in-process.

Workers are started with ``spawn``: forking a process that runs camera threads and event loops
can copy a held lock into the child. One trigger runs at a time (the runtime's trigger thread) and
waits for its detections, so a camera's block is never written while a worker reads it.
"""

from __future__ import annotations

import itertools
import multiprocessing as mp
import pickle
from collections import OrderedDict
from concurrent.futures import Future, ProcessPoolExecutor
from multiprocessing import shared_memory

import numpy as np

from mvpose_core.cache import IdentityCache
from mvpose_core.detect import DetectOptions, MarkDetection, detect_marks
from mvpose_core.scene import ViewCamera
from mvpose_core.station import RecipeConfig
from mvpose_core.transforms import Array

_attached: dict[str, shared_memory.SharedMemory] = {}  # worker side: blocks by name
_models: OrderedDict[int, tuple[ViewCamera, RecipeConfig]] = OrderedDict()  # worker: by token
_MODELS_KEPT = 64


def _init_worker() -> None:
    import cv2

    cv2.setNumThreads(1)  # parallelism comes from the processes; OpenCV threads would oversubscribe


def _warm() -> int:
    return 0


def _detect(name: str, shape: tuple[int, int], token: int, models: bytes,
            prior: Array, options: DetectOptions, near: Array | None) -> list[MarkDetection]:
    block = _attached.get(name)
    if block is None:
        block = _attached[name] = shared_memory.SharedMemory(name=name)
    pair = _models.get(token)
    if pair is None:
        pair = _models[token] = pickle.loads(models)
        while len(_models) > _MODELS_KEPT:
            _models.popitem(last=False)
    _models.move_to_end(token)
    image = np.ndarray(shape, dtype=np.uint8, buffer=block.buf)
    return detect_marks(image, pair[0], pair[1], prior, options, near)


class DetectPool:
    """``workers`` processes detecting marks; :meth:`submit` mirrors a call of detect_marks."""

    def __init__(self, workers: int) -> None:
        if workers < 1:
            raise ValueError(f"a detection pool needs at least 1 worker, got {workers}")
        self.workers = workers
        self._pool = ProcessPoolExecutor(workers, mp_context=mp.get_context("spawn"),
                                         initializer=_init_worker)
        self._blocks: dict[str, shared_memory.SharedMemory] = {}
        # (camera, recipe) pairs sent so far, by identity: their token and pickled bytes.
        self._sent: IdentityCache[tuple[int, bytes]] = IdentityCache(_MODELS_KEPT)
        self._tokens = itertools.count(1)
        # Import the detector in every worker now, not in the first trigger.
        for f in [self._pool.submit(_warm) for _ in range(workers)]:
            f.result(timeout=120)

    def submit(self, cam: ViewCamera, image: np.ndarray, recipe: RecipeConfig, prior: Array,
               options: DetectOptions, near: Array | None = None,
               ) -> Future[list[MarkDetection]]:
        image = np.asarray(image)
        if image.dtype != np.uint8 or image.ndim != 2:
            # The detector's own check names the problem; it runs here, in-process.
            fut: Future[list[MarkDetection]] = Future()
            try:
                fut.set_result(detect_marks(image, cam, recipe, prior, options, near))
            except Exception as err:
                fut.set_exception(err)
            return fut
        block = self._blocks.get(cam.camera_id)
        if block is None or block.size < image.nbytes:
            if block is not None:
                block.close()
                block.unlink()
            block = shared_memory.SharedMemory(create=True, size=image.nbytes)
            self._blocks[cam.camera_id] = block
        np.ndarray(image.shape, dtype=np.uint8, buffer=block.buf)[...] = image
        shape = (int(image.shape[0]), int(image.shape[1]))
        token, models = self._token(cam, recipe)
        return self._pool.submit(_detect, block.name, shape, token, models, prior, options,
                                 near)

    def _token(self, cam: ViewCamera, recipe: RecipeConfig) -> tuple[int, bytes]:
        return self._sent.get((cam, recipe), None,
                              lambda: (next(self._tokens), pickle.dumps((cam, recipe))))

    def close(self) -> None:
        self._pool.shutdown(wait=True, cancel_futures=True)
        for block in self._blocks.values():
            block.close()
            block.unlink()
        self._blocks.clear()
