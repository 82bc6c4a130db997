"""Shared pytest fixtures. Each block names its owner; expensive artefacts are session-scoped."""

import pytest
import torch


@pytest.fixture(autouse=True, scope="session")
def one_torch_thread():
    """Tests run tiny models of many small ops: one intra-op thread avoids the thread hand-offs
    that dominate them (10x or more on a busy 2-core machine). Subprocesses are unaffected."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


# --- procedural body model (owner: sarah_data/body) ------------------------------------------
@pytest.fixture(scope="session")
def procedural_model_path(tmp_path_factory):
    """The procedural body model (seed 0), written once per session. Read-only."""
    from sarah_data.body import write_procedural_body_model

    return write_procedural_body_model(tmp_path_factory.mktemp("body_model") / "procedural_body_model.npz")


@pytest.fixture(scope="session")
def procedural_body_model(procedural_model_path):
    """`BodyModel` of the procedural body model on the CPU, 256 shell points. Do not mutate."""
    from sarah_data.body import BodyModel

    return BodyModel.from_file(procedural_model_path, device="cpu")


# --- fixture_raw_dir (owner: sarah_data/fixtures) -------------------------------------------
import pytest as _pytest_for_fixture_raw_dir  # noqa: E402

FIXTURE_RAW_ARGS = dict(sessions=2, sequences_per_session=2, seconds=8.0, seed=0)


@_pytest_for_fixture_raw_dir.fixture(scope="session")
def fixture_raw_dir(tmp_path_factory):
    """A generated Embody 3D tree (`sarah-fixtures OUT` with FIXTURE_RAW_ARGS): OUT/aiagent/,
    OUT/body_models/SMPLX_PROCEDURAL.npz, OUT/fixture_truth.json + .npz. Read-only."""
    from sarah_data.fixtures.dyads import make_fixtures

    out = tmp_path_factory.mktemp("fixture_raw")
    make_fixtures(out, **FIXTURE_RAW_ARGS)
    return out


# --- prepared shards (owner: sarah_data/prep) -------------------------------------------------
PREP_RAW_ARGS = dict(sessions=3, sequences_per_session=2, seconds=30.0, seed=1)


@pytest.fixture(scope="session")
def prep_raw_dir(tmp_path_factory):
    """Fixture dyads for the prep tests (PREP_RAW_ARGS): long enough for 400-frame windows."""
    from sarah_data.fixtures.dyads import make_fixtures

    out = tmp_path_factory.mktemp("prep_raw")
    make_fixtures(out, **PREP_RAW_ARGS)
    return out


@pytest.fixture(scope="session")
def prepared_shards(prep_raw_dir, tmp_path_factory):
    """`sarah-prep prep_raw_dir shards -j 1` run once; returns the shards folder. Read-only."""
    from sarah_cli.prep import main

    out = tmp_path_factory.mktemp("prepared") / "shards"
    assert main([str(prep_raw_dir), str(out), "-j", "1", "--no-progress"]) == 0
    return out
