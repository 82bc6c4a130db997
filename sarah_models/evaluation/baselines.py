"""The retrieval baselines of the paper's Table 1: Random and nearest neighbour (NN).

Both return a real training window's motion (in its window frame: the agent at the origin
facing +z at frame 0, which is also the frame a test window's conditions are given in), so
they copy the data distribution by construction and ignore causality.

* Random: "randomly samples a motion sequence from the training set". Query i gets training
  window ``rng(seed, i).integers(N)`` -- a function of (seed, i) only, so any subset or order of
  queries gives the same answers.
* NN: "a library of 2048 motion sequences randomly sampled from the training set", matched on
  the conditioning inputs "across the full clip rather than via sliding windows". The distance
  between a query q and a library window l is, over the whole clip,

      D(q, l) = w_a * mean_(k,c) (A_q - A_l)^2 + w_b * mean_(k,c) (B_q - B_l)^2
              + w_p * mean_(k,j) (P_q - P_l)^2

  Every input is first averaged over consecutive blocks of ``block`` frames (k indexes blocks;
  block k of the query is compared with block k of the library window). A, B: the agent's and
  the user's block-mean audio features, standardized per channel (mean and standard deviation
  over the library's blocks of both persons), projected on the top ``audio_components``
  principal components of those standardized blocks and whitened (unit variance per component
  c). P: the user's block-mean floor head trajectory (x, z) in the window frame, standardized
  per axis j over the library's blocks. With the default weights w_a = w_b = w_p = 1 each term
  is about 2 for unrelated clips, so the two audio streams and the user's position count
  equally. The library is one (N, P) float32 matrix whose rows are the concatenated terms
  scaled by sqrt(w / elements), so D is a squared Euclidean distance and a batch of queries is
  one matrix product. Only block means are kept while the library is read: 2 x N x T/block x D
  floats (1.7 GB for 2048 windows of 400 frames of 1024-wide HuBERT features).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping, Protocol, Sequence

import numpy as np
from tqdm import tqdm


class Windows(Protocol):
    """Training windows with the WindowDataset item contract (docs/architecture.md)."""

    def __len__(self) -> int: ...

    def __getitem__(self, index: int) -> Mapping[str, Any]: ...


def _numpy(value) -> np.ndarray:
    if hasattr(value, "detach"):
        value = value.detach().cpu().numpy()
    return np.asarray(value)


def _check_length(item: Mapping[str, Any], frames: int, what: str) -> None:
    got = _numpy(item["motion"]).shape[0] if "motion" in item else _numpy(item["user_head"]).shape[0]
    if got != frames:
        raise ValueError(f"{what}: a window of {got} frames; the training windows have {frames}")


class RandomBaseline:
    """A random training window's motion for every query (paper Tab. 1, "Random")."""

    name = "Random"
    causal = False

    def __init__(self, train_windows: Windows, seed: int = 0) -> None:
        if len(train_windows) == 0:
            raise ValueError("RandomBaseline: no training windows")
        self.windows = train_windows
        self.seed = int(seed)

    def choose(self, index: int) -> int:
        """The training window given to query ``index``."""
        return int(np.random.default_rng((self.seed, int(index))).integers(len(self.windows)))

    def motion(self, query: Mapping[str, Any], index: int) -> np.ndarray:
        """(T, Dx) motion of the chosen training window; ``query`` only fixes the length."""
        item = self.windows[self.choose(index)]
        motion = _numpy(item["motion"]).astype(np.float32)
        _check_length(query, motion.shape[0], "RandomBaseline query")
        return motion


@dataclass(frozen=True)
class NNConfig:
    """Nearest-neighbour settings. The paper states the library size (2048) and full-clip
    matching on HuBERT features and user position; the feature treatment and weights are ours."""

    library_size: int = 2048
    audio_components: int = 32  # principal components kept per audio frame (<= feature width)
    block: int = 4  # frames averaged per matching step (the VAE stride: 7.5 Hz at 30 fps)
    agent_audio_weight: float = 1.0
    user_audio_weight: float = 1.0
    trajectory_weight: float = 1.0

    def __post_init__(self) -> None:
        if self.library_size < 1 or self.audio_components < 1 or self.block < 1:
            raise ValueError(f"NNConfig: library_size, audio_components and block must be "
                             f"positive, got {self.library_size}, {self.audio_components}, "
                             f"{self.block}")
        weights = (self.agent_audio_weight, self.user_audio_weight, self.trajectory_weight)
        if min(weights) < 0 or max(weights) == 0:
            raise ValueError(f"NNConfig: weights must be >= 0 and not all 0, got {weights}")


def library_indices(num_windows: int, size: int, seed: int) -> np.ndarray:
    """``size`` distinct window indices drawn with ``default_rng(seed)`` (all of them, in order,
    when there are no more than ``size``)."""
    if num_windows <= size:
        return np.arange(num_windows, dtype=np.int64)
    return np.sort(np.random.default_rng(seed).choice(num_windows, size, replace=False)).astype(np.int64)


def _blocks(x: np.ndarray, block: int) -> np.ndarray:
    """(T, C) -> (ceil(T / block), C) block means (a shorter last block when T % block)."""
    starts = np.arange(0, x.shape[0], block)
    sums = np.add.reduceat(x, starts, axis=0)
    sizes = np.diff(np.append(starts, x.shape[0]))
    return sums / sizes[:, None]


@dataclass
class _Standardizer:
    """Per-channel standardization, PCA projection and whitening of block-mean features."""

    mean: np.ndarray  # (D,)
    std: np.ndarray  # (D,)
    basis: np.ndarray  # (D, k) principal directions of the standardized blocks, whitened
    head_mean: np.ndarray  # (2,)
    head_std: np.ndarray  # (2,)

    @classmethod
    def fit(cls, audio: np.ndarray, head: np.ndarray, components: int) -> "_Standardizer":
        """audio (..., D) and head (..., 2) block means of the library."""
        rows = audio.reshape(-1, audio.shape[-1]).astype(np.float64)
        mean, std = rows.mean(0), rows.std(0)
        std = np.where(std > 1e-8, std, 1.0)
        z = (rows - mean) / std
        eigenvalues, eigenvectors = np.linalg.eigh(z.T @ z / max(len(z) - 1, 1))
        order = np.argsort(eigenvalues)[::-1][:min(components, rows.shape[1])]
        # eigh's signs are arbitrary but fixed for a given input; distances do not see them.
        floor = 1e-8 * max(float(eigenvalues.max()), 1e-12)
        basis = eigenvectors[:, order] / np.sqrt(np.maximum(eigenvalues[order], floor))
        points = head.reshape(-1, 2).astype(np.float64)
        head_std = points.std(0)
        return cls(mean, std, basis, points.mean(0), np.where(head_std > 1e-8, head_std, 1.0))

    def audio(self, x: np.ndarray) -> np.ndarray:
        return ((x - self.mean) / self.std) @ self.basis

    def head(self, p: np.ndarray) -> np.ndarray:
        return (p - self.head_mean) / self.head_std


class NearestNeighbourBaseline:
    """Full-clip nearest neighbour on audio and user trajectory (paper Tab. 1, "NN")."""

    name = "NN"
    causal = False

    def __init__(self, train_windows: Windows, config: NNConfig = NNConfig(), seed: int = 0,
                 progress: bool = False) -> None:
        if len(train_windows) == 0:
            raise ValueError("NearestNeighbourBaseline: no training windows")
        self.windows, self.config = train_windows, config
        self.library = library_indices(len(train_windows), config.library_size, seed)
        self.frames: int | None = None
        self.audio_dim: int | None = None
        blocks = [self._block_conditions(train_windows[int(i)], f"training window {int(i)}")
                  for i in tqdm(self.library, desc="NN library", unit="window",
                                disable=not progress, leave=False)]
        agent, user, head = (np.stack(parts) for parts in zip(*blocks))
        self.standardizer = _Standardizer.fit(np.concatenate([agent, user]), head,
                                              config.audio_components)
        self.matrix = self._features(agent, user, head)  # (N, P) float32
        self._norms = np.einsum("np,np->n", self.matrix.astype(np.float64),
                                self.matrix.astype(np.float64))

    def _block_conditions(self, item: Mapping[str, Any], what: str):
        """Block means (K, D), (K, D), (K, 2) of one window's agent audio, user audio, user head."""
        if "agent_audio" not in item or "user_audio" not in item:
            raise ValueError(f"NearestNeighbourBaseline: {what} has no audio features "
                             f"(the window dataset needs an extractor)")
        agent, user, head = (_numpy(item[k]).astype(np.float64)
                             for k in ("agent_audio", "user_audio", "user_head"))
        if self.frames is None:
            self.frames, self.audio_dim = head.shape[0], agent.shape[-1]
        if head.shape[0] != self.frames or agent.shape[-1] != self.audio_dim:
            raise ValueError(f"NearestNeighbourBaseline: {what} has {head.shape[0]} frames of "
                             f"{agent.shape[-1]}-channel audio; the library has {self.frames} "
                             f"frames of {self.audio_dim}")
        block = self.config.block
        return (_blocks(agent, block).astype(np.float32), _blocks(user, block).astype(np.float32),
                _blocks(head, block).astype(np.float32))

    def _features(self, agent: np.ndarray, user: np.ndarray, head: np.ndarray) -> np.ndarray:
        """Block means (B, K, D), (B, K, D), (B, K, 2) -> (B, P) rows whose squared distances
        are D(q, l)."""
        cfg, st = self.config, self.standardizer
        terms = [(st.audio(agent.astype(np.float64)), cfg.agent_audio_weight),
                 (st.audio(user.astype(np.float64)), cfg.user_audio_weight),
                 (st.head(head.astype(np.float64)), cfg.trajectory_weight)]
        rows = [x.reshape(len(x), -1) * np.sqrt(w / x[0].size) for x, w in terms]
        return np.concatenate(rows, axis=1).astype(np.float32)

    def query_features(self, queries: Sequence[Mapping[str, Any]]) -> np.ndarray:
        """(B, P) feature rows of query windows (same length and feature width as the library)."""
        blocks = [self._block_conditions(q, f"query {n}") for n, q in enumerate(queries)]
        agent, user, head = (np.stack(parts) for parts in zip(*blocks))
        return self._features(agent, user, head)

    def distances(self, queries: Sequence[Mapping[str, Any]]) -> np.ndarray:
        """(B, N) distances D(q, l) from each query to each library window."""
        q = self.query_features(queries).astype(np.float64)
        d = (np.einsum("bp,bp->b", q, q)[:, None] + self._norms[None, :]
             - 2.0 * q @ self.matrix.T.astype(np.float64))
        return np.maximum(d, 0.0)

    def nearest(self, queries: Sequence[Mapping[str, Any]]) -> np.ndarray:
        """(B,) training-window index (into ``train_windows``) of each query's nearest neighbour;
        ties go to the earlier library entry."""
        return self.library[np.argmin(self.distances(queries), axis=1)]

    def motion(self, query: Mapping[str, Any], index: int = 0) -> np.ndarray:
        """(T, Dx) motion of the query's nearest library window (``index`` is unused: NN is
        deterministic)."""
        return _numpy(self.windows[int(self.nearest([query])[0])]["motion"]).astype(np.float32)
