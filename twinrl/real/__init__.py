"""The real side of the loop: the real twin and the durable record of what happened on it.

``dataset``: ``DatasetWriter`` (append-only, SIGKILL-safe recording of transitions and images) and
``read`` (arrays and episode boundaries back, with damage reported per file).
"""

from twinrl.real.dataset import Dataset, DatasetError, DatasetWriter, Episode, read

__all__ = ["Dataset", "DatasetError", "DatasetWriter", "Episode", "read"]
