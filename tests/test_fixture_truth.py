"""The prepared shards against the fixture generator's own truth (issue acceptance 4).

The truth comes from the generator's geometry, never from our pipeline; the eye midpoints are
checked against the `smplx` package's own forward pass, an implementation independent of ours.
"""

import json

import h5py
import numpy as np
import smplx
import torch

from sarah_data.constants import NUM_BETAS
from sarah_data.embody3d import load_person, read_corpus
from sarah_data.fixtures.layout import BODY_MODEL_FILE


def _truth(raw):
    meta = json.loads((raw / "fixture_truth.json").read_text())
    with np.load(raw / meta["arrays"], allow_pickle=False) as arrays:
        return meta, {k: arrays[k] for k in arrays.files}


def _shard_people(shards):
    manifest = json.loads((shards / "manifest.json").read_text())
    for sequence, entry in sorted(manifest["sequences"].items()):
        with h5py.File(shards / entry["file"], "r") as handle:
            for person in entry["persons"]:
                group = handle[sequence][person]
                yield sequence, person, {k: group[k][()] for k in ("speaking", "gaze", "head", "valid")}


def test_speaking_labels_match_the_truth(prepared_shards, prep_raw_dir):
    _, truth = _truth(prep_raw_dir)
    correct = total = 0
    for sequence, person, arrays in _shard_people(prepared_shards):
        expected = truth[f"{sequence}/{person}/speaking"]
        correct += int(np.sum(arrays["speaking"].astype(bool) == expected))
        total += expected.size
    assert correct / total >= 0.95, f"speaking-label frame accuracy {correct / total:.3f}"


def test_gaze_scores_match_the_truth_facing_geometry(prepared_shards, prep_raw_dir):
    _, truth = _truth(prep_raw_dir)
    errors = []
    for sequence, person, arrays in _shard_people(prepared_shards):
        tracked = arrays["valid"].astype(bool)
        expected = truth[f"{sequence}/{person}/gaze_cos"]
        errors.append(np.abs(arrays["gaze"] - expected)[tracked])
    errors = np.concatenate(errors)
    assert errors.mean() < 0.05 and np.quantile(errors, 0.95) < 0.15, (errors.mean(), np.quantile(errors, 0.95))


def test_head_trajectories_are_the_smplx_eye_midpoints(prepared_shards, prep_raw_dir):
    corpus = read_corpus(prep_raw_dir / "aiagent")
    # smplx.create takes the model type from the file name, as it does for SMPLX_NEUTRAL.npz
    model = smplx.create(str(prep_raw_dir / "body_models" / BODY_MODEL_FILE), num_betas=NUM_BETAS,
                         use_pca=False, flat_hand_mean=True, gender="neutral", batch_size=8)
    assert isinstance(model, smplx.SMPLX)
    shards = {(s, p): a for s, p, a in _shard_people(prepared_shards)}
    checked = 0
    for pair in corpus.pairs:
        for person in pair.persons:
            if (pair.sequence, person) not in shards:
                continue
            frames = np.linspace(0, pair.length - 1, 8).astype(np.int64)
            params = {k: torch.tensor(np.asarray(v[frames]), dtype=torch.float32)
                      for k, v in load_person(pair, person).params.items()}
            with torch.no_grad():
                joints = model(**params, return_verts=False).joints[:, :55].numpy()
            eyes = (joints[:, 23] + joints[:, 24]) / 2
            np.testing.assert_allclose(shards[(pair.sequence, person)]["head"][frames], eyes[:, [0, 2]], atol=1e-4)
            checked += 1
    assert checked >= 4
