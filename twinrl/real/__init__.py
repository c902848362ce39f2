"""The real side of the loop: the real twin and the durable record of what happened on it.

``dataset``: ``DatasetWriter`` (append-only, SIGKILL-safe recording of transitions and images) and
``read`` (arrays and episode boundaries back, with damage reported per file).
``twin``: ``make_real(name, seed=...)`` and ``RealTwin`` (a task on the MuJoCo C engine with a
hidden ``Perturbation``, RGB-D and segmentation camera) and ``render_episode``; ``perturbation``: ``Perturbation``; ``remote``:
``TwinClient`` (the real twin served in another process, what learning code is given). Those load
lazily (they import JAX, MuJoCo and Brax), so recording and reading datasets stays light.
"""

from twinrl.real.dataset import Dataset, DatasetError, DatasetWriter, Episode, read

__all__ = ["Dataset", "DatasetError", "DatasetWriter", "Episode", "read"]

_LAZY = {"make_real": "twinrl.real.twin", "RealTwin": "twinrl.real.twin", "render_episode": "twinrl.real.twin",
         "Perturbation": "twinrl.real.perturbation", "TwinClient": "twinrl.real.remote"}
__all__ += list(_LAZY)


def __getattr__(name):
    if name in _LAZY:
        import importlib
        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'twinrl.real' has no attribute {name!r}")
