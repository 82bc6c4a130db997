"""Random and nearest-neighbour baselines on constructed windows."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings, strategies as st

from sarah_models.evaluation.baselines import (NearestNeighbourBaseline, NNConfig, RandomBaseline, library_indices)

T, D, DX = 16, 6, 9


class Windows:
    """Windows following the WindowDataset item contract; motion row 0 holds the index."""

    def __init__(self, n: int, seed: int = 0, offset: float = 0.0, scale: float = 1.0) -> None:
        rng = np.random.default_rng(seed)
        self.agent = rng.normal(size=(n, T, D)) * scale + offset
        self.user = rng.normal(size=(n, T, D)) * scale + offset
        self.head = np.cumsum(rng.normal(0, 0.1, (n, T, 2)), axis=1) + rng.normal(0, 1, (n, 1, 2))
        self.motion = rng.normal(size=(n, T, DX)).astype(np.float32)
        self.motion[:, 0, 0] = np.arange(n)
        self.reads = 0

    def __len__(self) -> int:
        return len(self.motion)

    def __getitem__(self, i: int) -> dict:
        self.reads += 1
        f32 = lambda a: torch.from_numpy(np.asarray(a, dtype=np.float32))  # noqa: E731
        return {"motion": f32(self.motion[i]), "agent_audio": f32(self.agent[i]),
                "user_audio": f32(self.user[i]), "user_head": f32(self.head[i])}


def test_library_indices_are_seeded_distinct_and_all_when_few():
    assert np.array_equal(library_indices(5, 8, seed=3), np.arange(5))
    a, b = library_indices(100, 20, seed=1), library_indices(100, 20, seed=1)
    assert np.array_equal(a, b) and len(np.unique(a)) == 20 and np.all(np.diff(a) > 0)
    assert not np.array_equal(a, library_indices(100, 20, seed=2))


@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 1000), components=st.integers(1, 8), block=st.integers(1, 5))
def test_nn_returns_the_library_item_when_the_query_is_one(seed, components, block):
    windows = Windows(30, seed)
    nn = NearestNeighbourBaseline(windows, NNConfig(library_size=12, audio_components=components,
                                                    block=block), seed=seed)
    items = [windows[int(i)] for i in nn.library]
    assert np.array_equal(nn.nearest(items), nn.library)
    for i in nn.library[:3]:
        np.testing.assert_array_equal(nn.motion(windows[int(i)]), windows.motion[i])
    d = nn.distances(items)
    assert d.shape == (12, 12) and np.allclose(np.diag(d), 0.0, atol=1e-5)
    np.testing.assert_allclose(d, d.T, atol=1e-4)  # a squared Euclidean distance


def test_nn_trajectory_term_is_the_mean_squared_standardized_distance():
    windows = Windows(10, seed=4)
    nn = NearestNeighbourBaseline(windows, NNConfig(audio_components=D, block=1,
                                                    agent_audio_weight=0.0, user_audio_weight=0.0,
                                                    trajectory_weight=1.0))
    std = windows.head.reshape(-1, 2).std(0)
    query = Windows(1, seed=99)
    expected = (((query.head[0] - windows.head) / std) ** 2).mean(axis=(1, 2))
    np.testing.assert_allclose(nn.distances([query[0]])[0], expected, rtol=1e-4, atol=1e-5)
    assert nn.nearest([query[0]])[0] == int(np.argmin(expected))


def test_nn_balances_audio_and_trajectory_by_weights():
    """Two candidates: one matches the query's audio, the other its user trajectory; the
    weights decide which is nearest."""
    windows = Windows(8, seed=5)
    query = {k: v.clone() for k, v in windows[0].items()}
    query["user_head"] = windows[1]["user_head"].clone()  # audio of 0, trajectory of 1
    audio_only = NearestNeighbourBaseline(windows, NNConfig(trajectory_weight=0.0))
    trajectory_only = NearestNeighbourBaseline(windows, NNConfig(agent_audio_weight=0.0,
                                                                 user_audio_weight=0.0))
    assert audio_only.nearest([query])[0] == 0
    assert trajectory_only.nearest([query])[0] == 1


def test_nn_ignores_per_channel_affine_changes_of_the_audio():
    """Features are standardized per channel over the library, so rescaling and shifting every
    audio channel of library and query alike leaves the distances unchanged."""
    plain, shifted = Windows(20, seed=6), Windows(20, seed=6, offset=3.0, scale=5.0)
    queries_plain, queries_shifted = Windows(4, seed=7), Windows(4, seed=7, offset=3.0, scale=5.0)
    cfg = NNConfig(library_size=15, audio_components=4, block=2)
    a = NearestNeighbourBaseline(plain, cfg, seed=1).distances([queries_plain[i] for i in range(4)])
    b = NearestNeighbourBaseline(shifted, cfg, seed=1).distances(
        [queries_shifted[i] for i in range(4)])
    np.testing.assert_allclose(a, b, rtol=1e-3, atol=1e-4)


def test_nn_errors_name_the_problem():
    windows = Windows(6)
    nn = NearestNeighbourBaseline(windows, NNConfig(library_size=4))
    short = {k: v[: T // 2] for k, v in windows[0].items()}
    with pytest.raises(ValueError, match="query 0 has 8 frames"):
        nn.nearest([short])
    silent = {k: v for k, v in windows[0].items() if k != "user_audio"}
    with pytest.raises(ValueError, match="no audio features"):
        nn.nearest([silent])
    with pytest.raises(ValueError, match="no training windows"):
        NearestNeighbourBaseline(Windows(0))
    with pytest.raises(ValueError, match="weights"):
        NNConfig(agent_audio_weight=0, user_audio_weight=0, trajectory_weight=0)


def test_random_is_seeded_order_free_and_returns_training_motion():
    windows = Windows(50)
    query = windows[0]
    a, b = RandomBaseline(windows, seed=3), RandomBaseline(windows, seed=3)
    picks = [a.choose(i) for i in range(40)]
    assert picks == [b.choose(i) for i in reversed(range(40))][::-1]  # order of queries is free
    assert picks != [RandomBaseline(windows, seed=4).choose(i) for i in range(40)]
    assert len(set(picks)) > 20  # spread over the training windows
    for i in (0, 7):
        np.testing.assert_array_equal(a.motion(query, i), windows.motion[a.choose(i)])
    with pytest.raises(ValueError, match="8 frames"):
        a.motion({k: v[:8] for k, v in query.items()}, 0)
    with pytest.raises(ValueError, match="no training windows"):
        RandomBaseline(Windows(0))
