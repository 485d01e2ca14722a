"""Distances between goals of goal-conditioned robot tasks.

Which metric fits which Gymnasium-Robotics task:

- ``"euclidean"``: ``FetchReach``, ``FetchPush``, ``FetchSlide``,
  ``FetchPickAndPlace`` (goal ``[3]``: gripper or object position) and
  ``HandReach`` (goal ``[15]``: five fingertip positions; the env's reward is
  the same norm).
- ``"pose"`` (alias ``"hand"``): ``HandManipulateBlock*``,
  ``HandManipulateEgg*``, ``HandManipulatePen*`` and their touch-sensor
  variants (goal ``[7]``: position xyz + quaternion wxyz).

The pose metric is ``||p_a - p_b|| + rotation_weight * angle(q_a, q_b)`` with
``angle = 2 * arccos(|<q_a, q_b>|)`` in ``[0, pi]``. Gymnasium-Robotics'
``_goal_distance`` computes ``2 * arccos(<q_a, q_b>)`` without the absolute
value, so it reports ``2*pi - angle`` when the two quaternions lie in opposite
hemispheres although they encode the same rotation; a memory of past goals
must treat ``q`` and ``-q`` as one orientation, hence the ``abs``. The default
``rotation_weight=0.1`` (metres per radian) is the ratio of the manipulate
envs' success thresholds (``distance_threshold=0.01`` m,
``rotation_threshold=0.1`` rad), so that "just inside the success region" on
either axis costs the same; the pen tasks use ``distance_threshold=0.05``,
for which ``0.5`` is the matching value.

Every metric maps ``[Q, d] x [N, d] -> [Q, N]`` (:meth:`GoalMetric.pairwise`)
and broadcasts elementwise (:meth:`GoalMetric.distance`), in torch. The
built-in metrics also expose a Euclidean *embedding* (:meth:`GoalMetric.embed`)
whose distances are a lower bound of the metric;
:class:`~torchrl_robotmem.goal_index.GoalIndex` uses it to run exact searches
through a KD-tree.
"""
from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import torch

__all__ = ["GoalMetric", "EuclideanMetric", "PoseMetric", "get_metric"]


class GoalMetric:
    """Base class of goal-space distances.

    Subclasses implement :meth:`distance` (elementwise with broadcasting) and
    may override :meth:`pairwise` with a faster ``[Q, d] x [N, d] -> [Q, N]``
    kernel. A metric that can be searched through a KD-tree also implements
    :meth:`embed` (and :meth:`embed_queries` when a query needs several
    embeddings): Euclidean distances between the embeddings must never exceed
    the metric (a lower bound), and equal it when :attr:`embedding_exact` is
    ``True``. A metric without an embedding is searched by brute force.
    """

    name: str = "custom"
    #: goal dimension the metric requires (``None``: any)
    goal_dim: int | None = None
    #: whether Euclidean distances between embeddings equal the metric (not only bound it)
    embedding_exact: bool = False
    #: whether :meth:`embed` is the goals themselves as float64: the index then keeps its
    #: goal snapshot in float64 and the KD-tree searches it in place (one copy of the goals)
    embedding_is_goals: bool = False

    def distance(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        """Distance between ``a[..., d]`` and ``b[..., d]`` (broadcast) -> ``[...]``."""
        raise NotImplementedError

    def pairwise(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        """All distances between the rows of ``a [Q, d]`` and ``b [N, d]`` -> ``[Q, N]``."""
        return self.distance(a.unsqueeze(-2), b.unsqueeze(-3))

    def __call__(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        return self.pairwise(a, b)

    def check_goal_dim(self, goal_dim: int) -> None:
        """Raises ``ValueError`` when the metric cannot compare goals of ``goal_dim``."""
        if self.goal_dim is not None and goal_dim != self.goal_dim:
            raise ValueError(
                f"metric {self.name!r} needs goals of dimension {self.goal_dim}, "
                f"got {goal_dim}."
            )

    @property
    def key(self) -> tuple:
        """What the metric computes, hashable: equal keys give equal distances (shared indexes use it)."""
        return (type(self), id(self))

    # -- tree embedding -------------------------------------------------------
    @property
    def embeddable(self) -> bool:
        """Whether the metric has an :meth:`embed` (and can be searched through a KD-tree)."""
        return type(self).embed is not GoalMetric.embed

    def embed(self, x: np.ndarray) -> np.ndarray:
        """Rows ``[N, d]`` -> float64 embedding ``[N, e]`` (lower-bounding the metric)."""
        raise NotImplementedError(f"{type(self).__name__} has no Euclidean embedding.")

    def embed_queries(self, q: np.ndarray) -> list[np.ndarray]:
        """Queries ``[Q, d]`` -> list of embeddings; a row's lower bound is the min over the list."""
        return [self.embed(q)]

    def __repr__(self) -> str:
        return f"{type(self).__name__}()"


class EuclideanMetric(GoalMetric):
    """Euclidean distance ``||a - b||``: Fetch tasks and ``HandReach``.

    Example:
        >>> import torch
        >>> from torchrl_robotmem.goal_index.metrics import EuclideanMetric
        >>> EuclideanMetric().pairwise(torch.zeros(1, 3), torch.tensor([[3.0, 4.0, 0.0]]))
        tensor([[5.]])
    """

    name = "euclidean"
    embedding_exact = True
    embedding_is_goals = True

    @property
    def key(self) -> tuple:
        return ("euclidean",)

    def distance(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        return torch.linalg.vector_norm(a - b, dim=-1)

    def pairwise(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        # The direct (no matmul) mode keeps small distances accurate: the
        # |a|^2 + |b|^2 - 2ab expansion loses them to cancellation.
        return torch.cdist(
            a.unsqueeze(0), b.unsqueeze(0), compute_mode="donot_use_mm_for_euclid_dist"
        ).squeeze(0)

    def embed(self, x: np.ndarray) -> np.ndarray:
        return np.ascontiguousarray(x, dtype=np.float64)


def _normalize(q: torch.Tensor) -> torch.Tensor:
    return q / torch.linalg.vector_norm(q, dim=-1, keepdim=True).clamp_min(1e-12)


class PoseMetric(GoalMetric):
    """Position + rotation-angle distance for 7-D pose goals (``HandManipulate*``).

    ``d = ||p_a - p_b|| + rotation_weight * 2 * arccos(|<q_a, q_b>|)`` where a
    goal is ``[x, y, z, qw, qx, qy, qz]``. Quaternions are normalised before
    use, and ``q`` and ``-q`` are the same rotation (distance 0).

    Args:
        rotation_weight (float, optional): metres per radian of rotation.
            Defaults to ``0.1``, the ratio of the manipulate envs' position and
            rotation success thresholds (0.01 m / 0.1 rad).

    Example:
        >>> import torch
        >>> from torchrl_robotmem.goal_index.metrics import PoseMetric
        >>> q = torch.tensor([[0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]])
        >>> minus_q = torch.tensor([[0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0]])
        >>> PoseMetric().pairwise(q, minus_q)
        tensor([[0.]])
    """

    name = "pose"
    goal_dim = 7

    def __init__(self, rotation_weight: float = 0.1):
        rotation_weight = float(rotation_weight)
        if not math.isfinite(rotation_weight) or rotation_weight < 0:
            raise ValueError(
                f"rotation_weight must be a finite number >= 0, got {rotation_weight}."
            )
        self.rotation_weight = rotation_weight

    @property
    def key(self) -> tuple:
        return ("pose", self.rotation_weight)

    def _angle_from_dot(self, dot: torch.Tensor) -> torch.Tensor:
        return 2.0 * torch.arccos(dot.abs().clamp(max=1.0))

    def distance(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        d_pos = torch.linalg.vector_norm(a[..., :3] - b[..., :3], dim=-1)
        dot = (_normalize(a[..., 3:7]) * _normalize(b[..., 3:7])).sum(-1)
        return d_pos + self.rotation_weight * self._angle_from_dot(dot)

    def pairwise(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        d_pos = torch.cdist(
            a[:, :3].unsqueeze(0),
            b[:, :3].unsqueeze(0),
            compute_mode="donot_use_mm_for_euclid_dist",
        ).squeeze(0)
        dot = _normalize(a[:, 3:7]) @ _normalize(b[:, 3:7]).T
        return d_pos + self.rotation_weight * self._angle_from_dot(dot)

    # Embedding (p, 2w q): for unit quaternions with rotation angle t between
    # them, min(|q_a - q_b|, |q_a + q_b|) = 2 sin(t/4) <= t/2, so
    # sqrt(|dp|^2 + (2w min|q_a -+ q_b|)^2) <= |dp| + w t. Queries are
    # embedded with both signs of q, rows with the stored sign.
    def embed(self, x: np.ndarray) -> np.ndarray:
        x = np.asarray(x, dtype=np.float64)
        q = x[:, 3:7]
        q = q / np.maximum(np.linalg.norm(q, axis=1, keepdims=True), 1e-12)
        return np.ascontiguousarray(
            np.concatenate([x[:, :3], (2.0 * self.rotation_weight) * q], axis=1)
        )

    def embed_queries(self, q: np.ndarray) -> list[np.ndarray]:
        e = self.embed(q)
        flipped = e.copy()
        flipped[:, 3:] *= -1
        return [e, flipped]

    def __repr__(self) -> str:
        return f"PoseMetric(rotation_weight={self.rotation_weight})"


class _CallableMetric(GoalMetric):
    """Wraps a user function ``f(a [Q, d], b [N, d]) -> [Q, N]`` (searched by brute force)."""

    def __init__(self, fn: Callable[[torch.Tensor, torch.Tensor], torch.Tensor]):
        self.fn = fn
        self.name = getattr(fn, "__name__", "custom")

    @property
    def key(self) -> tuple:
        return ("callable", self.fn)

    def pairwise(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        out = self.fn(a, b)
        if out.shape != (a.shape[0], b.shape[0]):
            raise ValueError(
                f"custom metric {self.name!r} must map [Q, d] x [N, d] -> [Q, N]; "
                f"got {tuple(out.shape)} for Q={a.shape[0]}, N={b.shape[0]}."
            )
        return out

    def distance(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        a, b = torch.broadcast_tensors(a, b)
        flat_a, flat_b = a.reshape(-1, a.shape[-1]), b.reshape(-1, b.shape[-1])
        return torch.stack(
            [self.fn(x[None], y[None])[0, 0] for x, y in zip(flat_a, flat_b)]
        ).reshape(a.shape[:-1])

    def __repr__(self) -> str:
        return f"_CallableMetric({self.name})"


_METRICS = {
    "euclidean": EuclideanMetric,
    "l2": EuclideanMetric,
    "pose": PoseMetric,
    "hand": PoseMetric,
}


def get_metric(name_or_callable: str | GoalMetric | Callable = "euclidean", **kwargs) -> GoalMetric:
    """Returns a :class:`GoalMetric` from a name, a metric, or a pairwise function.

    Args:
        name_or_callable: ``"euclidean"`` (alias ``"l2"``), ``"pose"`` (alias
            ``"hand"``), a :class:`GoalMetric` instance (returned as is), or a
            function ``f(a [Q, d], b [N, d]) -> [Q, N]`` (searched by brute
            force: no KD-tree).
        **kwargs: constructor arguments of the named metric
            (e.g. ``rotation_weight=0.5`` for ``"pose"``).

    Example:
        >>> from torchrl_robotmem.goal_index.metrics import get_metric
        >>> get_metric("hand", rotation_weight=0.5)
        PoseMetric(rotation_weight=0.5)
    """
    if isinstance(name_or_callable, GoalMetric):
        if kwargs:
            raise ValueError("metric keyword arguments are only accepted with a metric name.")
        return name_or_callable
    if isinstance(name_or_callable, str):
        try:
            cls = _METRICS[name_or_callable.lower()]
        except KeyError:
            raise ValueError(
                f"unknown metric {name_or_callable!r}; known metrics: {sorted(_METRICS)}."
            ) from None
        return cls(**kwargs)
    if callable(name_or_callable):
        if kwargs:
            raise ValueError("metric keyword arguments are only accepted with a metric name.")
        return _CallableMetric(name_or_callable)
    raise TypeError(
        f"metric must be a name, a GoalMetric or a callable, got {type(name_or_callable).__name__}."
    )
