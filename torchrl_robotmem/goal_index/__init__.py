"""Exact nearest-goal recall over the transitions of a TorchRL storage.

One job a module:

* :mod:`.index`: :class:`GoalIndex` (the facade), :meth:`GoalIndex.for_storage`
  (the one index a storage shares with the sampler, the transform and
  :class:`~torchrl_robotmem.RobotMemory`) and :func:`recall`;
* :mod:`.filters`: :class:`RowFilter`, the ``success_only`` / ``env`` / ``run``
  filters as one value, shared by every reader;
* :mod:`.tracking`: :class:`~.tracking.ColumnTracker`, the only module reading
  storage state (columns through :mod:`torchrl_robotmem.storage.columns`,
  TorchRL's mutation revision), and the changed rows since a revision;
* :mod:`.views`: the segments answering one filter, kept in step with the tracker;
* :mod:`.segments`: exact search of one segment (KD-tree or brute force);
* :mod:`.metrics`: goal distances (:class:`GoalMetric`, ``"euclidean"``,
  ``"pose"``) and their Euclidean embeddings.
"""
from __future__ import annotations

from .filters import RowFilter
from .index import GoalIndex, recall
from .metrics import EuclideanMetric, GoalMetric, PoseMetric, get_metric

__all__ = ["EuclideanMetric", "GoalIndex", "GoalMetric", "PoseMetric", "RowFilter", "get_metric", "recall"]
