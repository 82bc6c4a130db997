"""Audio feature extractors: registry, frame alignment, causality, streaming, HuBERT weight loading.

HuBERT runs with random weights (no real weights exist on test machines) saved to a temporary file
and loaded through the real loader. HuBERT-Large (317M parameters) is built once to test loading and
its output; the remaining HuBERT properties run on the 12-layer base architecture to stay fast.
"""

from __future__ import annotations

import gc
import json
import math
from dataclasses import asdict, dataclass

import numpy as np
import pytest
import torch
import torchaudio
from hypothesis import given, settings
from hypothesis import strategies as st

from sarah_data.features import (
    AudioFeatureExtractor,
    MissingWeightsError,
    available_extractors,
    get_extractor,
    register_extractor,
)
from sarah_data.features.logmel import LogMelExtractor
from sarah_data.fixtures.audio import synthesize_dyad_audio

SPF = 1600


@pytest.fixture(scope="module")
def speech() -> np.ndarray:
    return synthesize_dyad_audio(150, seed=11).track_a  # five seconds


@pytest.fixture(scope="module")
def logmel() -> LogMelExtractor:
    return get_extractor("logmel")


def push_in_chunks(stream, wave: np.ndarray, sizes) -> np.ndarray:
    out, i, k = [], 0, 0
    while i < len(wave):
        n = sizes[k % len(sizes)]
        out.append(stream.push(wave[i: i + n]))
        i, k = i + n, k + 1
    return np.concatenate(out)


# ---------------------------------------------------------------- registry


def test_registry_lists_and_builds_extractors():
    assert {"logmel", "hubert-large"} <= set(available_extractors())
    small = get_extractor("logmel", n_mels=40)
    assert small.name == "logmel" and small.dim == 40 and small.config.n_mels == 40
    json.dumps(asdict(small.config))  # storable in a shard's attributes
    with pytest.raises(KeyError, match="available: .*logmel"):
        get_extractor("mfcc")
    with pytest.raises(TypeError, match="unknown config option"):
        get_extractor("logmel", hop=3)


def test_register_rejects_name_clashes_and_non_dataclass_configs():
    @dataclass(frozen=True)
    class _Config:
        pass

    class _Clash(AudioFeatureExtractor):
        name = "logmel"
        config_type = _Config

    with pytest.raises(ValueError, match="already taken"):
        register_extractor(_Clash)

    class _NoDataclass(AudioFeatureExtractor):
        name = "test-no-dataclass"
        config_type = dict

    with pytest.raises(TypeError, match="dataclass"):
        register_extractor(_NoDataclass)
    assert register_extractor(LogMelExtractor) is LogMelExtractor  # re-registering itself is fine


# ---------------------------------------------------------------- logmel


@settings(max_examples=15, deadline=None)
@given(num_frames=st.integers(0, 37), delta=st.integers(-2500, 2500))
def test_logmel_shape_for_any_length(logmel, speech, num_frames, delta):
    wave = speech[: max(0, num_frames * SPF + delta)]
    features = logmel.extract(wave, num_frames)
    assert features.shape == (num_frames, 80) and features.dtype == np.float32
    assert np.all(np.isfinite(features))


def test_logmel_cuts_or_pads_audio_at_the_end(logmel, speech):
    exact = logmel.extract(speech[: 40 * SPF], 40)
    np.testing.assert_array_equal(logmel.extract(speech, 40), exact)
    short = speech[: 40 * SPF - 777]
    padded = np.concatenate([short, np.zeros(777, np.float32)])
    np.testing.assert_array_equal(logmel.extract(short, 40), logmel.extract(padded, 40))


def test_logmel_streaming_equals_offline(logmel, speech):
    offline = logmel.extract(speech, 150)
    stream = logmel.stream()
    np.testing.assert_array_equal(push_in_chunks(stream, speech, [4 * SPF]), offline)
    stream.reset()
    np.testing.assert_array_equal(push_in_chunks(stream, speech, [1, 999, 4801, 12345, 1600, 0, 7]), offline)
    assert stream.push(np.zeros(0, np.float32)).shape == (0, 80)


@settings(max_examples=10, deadline=None)
@given(st.lists(st.integers(300, 20_000), min_size=1, max_size=8))
def test_logmel_streaming_equals_offline_for_any_chunking(logmel, speech, sizes):
    wave = speech[: 60 * SPF]
    np.testing.assert_array_equal(push_in_chunks(logmel.stream(), wave, sizes), logmel.extract(wave, 60))


def test_logmel_is_causal(logmel, speech):
    for t in (0, 17, 44):
        changed = speech.copy()
        changed[(t + 1) * SPF:] = np.random.default_rng(t).uniform(-0.5, 0.5, len(speech) - (t + 1) * SPF)
        before, after = logmel.extract(speech, 150), logmel.extract(changed, 150)
        np.testing.assert_array_equal(before[: t + 1], after[: t + 1])
        assert not np.array_equal(before[t + 1:], after[t + 1:])


def test_logmel_alignment_and_values(logmel):
    floor = math.log(logmel.config.log_floor)
    assert np.all(logmel.extract(np.zeros(10 * SPF, np.float32), 10) == np.float32(floor))
    # A 1 kHz tone starting exactly at frame 10: frames 0-9 still see pure silence.
    wave = np.zeros(20 * SPF, np.float32)
    wave[10 * SPF:] = 0.5 * np.sin(2 * np.pi * 1000 * np.arange(10 * SPF) / 48_000)
    features = logmel.extract(wave, 20)
    assert np.all(features[:10] == np.float32(floor))
    assert np.all(features[10:].max(axis=1) > floor + 10)
    mel_centres = torchaudio.functional.melscale_fbanks(201, 0.0, 8000.0, 80, 16_000).argmax(dim=0) * 40.0
    assert abs(float(mel_centres[features[15].argmax()]) - 1000.0) < 100.0


def test_logmel_is_deterministic_across_instances(speech):
    a = get_extractor("logmel").extract(speech, 150)
    b = get_extractor("logmel").to("cpu").extract(speech, 150)
    assert a.tobytes() == b.tobytes()


def test_bad_audio_is_rejected(logmel):
    with pytest.raises(ValueError, match="shape"):
        logmel.extract(np.zeros((2, SPF), np.float32), 1)
    with pytest.raises(ValueError, match="NaN"):
        logmel.extract(np.full(SPF, np.nan, np.float32), 1)
    with pytest.raises(TypeError, match="dtype"):
        logmel.extract(np.zeros(SPF, np.int16), 1)
    with pytest.raises(ValueError, match="NaN"):
        logmel.stream().push(np.full(10, np.inf, np.float32))


# ---------------------------------------------------------------- HuBERT


def _model_features(model: torch.nn.Module, wave: np.ndarray, layer: int | None = None) -> torch.Tensor:
    """The architecture's own output on a whole clip at 50 Hz, with the bundle's normalization."""
    with torch.inference_mode():
        x = torchaudio.functional.resample(torch.from_numpy(wave), 48_000, 16_000)[None]
        x = torch.nn.functional.layer_norm(x, x.shape)
        if layer is None:
            return model(x)[0][0]
        return model.extract_features(x, num_layers=layer)[0][layer - 1][0]


def _expected_at_motion_frames(hidden: torch.Tensor, num_frames: int) -> np.ndarray:
    # HuBERT frame i is centred at 16 kHz sample 320 i + 200; motion frame t at 533.33 (t + 0.5).
    position = np.clip(((np.arange(num_frames) + 0.5) * 16_000 / 30 - 200) / 320, 0, hidden.shape[0] - 1)
    low = np.floor(position).astype(int)
    high = np.minimum(low + 1, hidden.shape[0] - 1)
    w = (position - low)[:, None]
    h = hidden.numpy()
    return h[low] * (1 - w) + h[high] * w


def _saved_hubert(tmp_path_factory, architecture: str, seed: int):
    """A torchaudio HuBERT with random weights and the state-dict file it was saved to; the file
    (1.2 GB for large) is removed when the module is done, so a whole run fits a small disk."""
    torch.manual_seed(seed)
    model = getattr(torchaudio.models, f"hubert_{architecture}")().eval()
    path = tmp_path_factory.mktemp("hubert") / f"{architecture}.pth"
    torch.save(model.state_dict(), path)
    yield path, model
    path.unlink(missing_ok=True)
    gc.collect()  # extractors map their weight file: the space is freed once the last one is gone


@pytest.fixture
def hubert_large_file(tmp_path_factory):
    yield from _saved_hubert(tmp_path_factory, "large", 0)


@pytest.fixture(scope="module")
def hubert_base_file(tmp_path_factory):
    yield from _saved_hubert(tmp_path_factory, "base", 1)


@pytest.fixture(scope="module")
def hubert_base(hubert_base_file):
    return get_extractor("hubert-large", weights=str(hubert_base_file[0]), architecture="base",
                         past_frames=4, device="cpu")


def test_hubert_large_loads_from_a_state_dict_and_matches_the_model(hubert_large_file, speech):
    path, model = hubert_large_file
    extractor = get_extractor("hubert-large", weights=str(path), device="cpu")
    assert extractor.dim == 1024 and extractor.device == torch.device("cpu")
    wave = speech[: 31 * SPF]  # ~1 s, an odd number of frames
    features = extractor.extract(wave, 31)
    assert features.shape == (31, 1024) and features.dtype == np.float32
    np.testing.assert_allclose(features, _expected_at_motion_frames(_model_features(model, wave), 31),
                               rtol=1e-4, atol=1e-4)


def test_missing_weights_is_one_clear_line(tmp_path, monkeypatch):
    with pytest.raises(MissingWeightsError) as error:
        get_extractor("hubert-large", weights=str(tmp_path / "nope.pth"))
    message = str(error.value)
    assert "\n" not in message and str(tmp_path / "nope.pth") in message and "--hubert-weights" in message
    monkeypatch.setenv("TORCH_HOME", str(tmp_path))  # the torch hub cache moves with it
    with pytest.raises(FileNotFoundError, match=r"hub/checkpoints/hubert_fairseq_large_ll60k\.pth"):
        get_extractor("hubert-large")


def test_wrong_weight_files_are_named(tmp_path, hubert_base_file):
    with pytest.raises(ValueError, match=r"base\.pth: not a HuBERT-large state dict: .* missing"):
        get_extractor("hubert-large", weights=str(hubert_base_file[0]))
    junk = tmp_path / "junk.pth"
    junk.write_bytes(b"not a torch file")
    with pytest.raises(ValueError, match="junk.pth: cannot read"):
        get_extractor("hubert-large", weights=str(junk), architecture="base")


def test_hubert_accepts_bundle_and_pretraining_layouts(tmp_path, hubert_base_file, hubert_base, speech):
    _, model = hubert_base_file
    wave = speech[: 10 * SPF]
    reference = hubert_base.extract(wave, 10)
    # torchaudio's bundle files predate parametrized weight norm: weight_g / weight_v.
    legacy = {k.replace("parametrizations.weight.original0", "weight_g")
               .replace("parametrizations.weight.original1", "weight_v"): v for k, v in model.state_dict().items()}
    assert any(k.endswith("weight_g") for k in legacy)
    pretraining = torchaudio.models.hubert_pretrain_base()
    pretraining.wav2vec2.load_state_dict(model.state_dict())
    for name, payload in (("bundle", legacy), ("pretrain", {"state_dict": pretraining.state_dict()})):
        path = tmp_path / f"{name}.pth"
        torch.save(payload, path)
        loaded = get_extractor("hubert-large", weights=str(path), architecture="base", device="cpu")
        np.testing.assert_array_equal(loaded.extract(wave, 10), reference)
        del loaded  # its tensors map the file: one 360 MB copy on disk at a time
        gc.collect()
        path.unlink()


def test_hubert_intermediate_layer(hubert_base_file, speech):
    path, model = hubert_base_file
    extractor = get_extractor("hubert-large", weights=str(path), architecture="base", layer=3)
    wave = speech[: 25 * SPF]
    np.testing.assert_allclose(extractor.extract(wave, 25),
                               _expected_at_motion_frames(_model_features(model, wave, layer=3), 25),
                               rtol=1e-4, atol=1e-4)
    with pytest.raises(ValueError, match="layer"):
        get_extractor("hubert-large", weights=str(path), architecture="base", layer=13)


def test_hubert_shapes_padding_and_determinism(hubert_base, hubert_base_file, speech):
    for num_frames, length in ((1, SPF), (7, 7 * SPF - 1234), (13, 13 * SPF + 999), (0, 500)):
        features = hubert_base.extract(speech[:length], num_frames)
        assert features.shape == (num_frames, 768) and features.dtype == np.float32
    again = get_extractor("hubert-large", weights=str(hubert_base_file[0]), architecture="base")
    wave = speech[: 13 * SPF - 5]
    assert again.extract(wave, 13).tobytes() == hubert_base.extract(wave, 13).tobytes()


def test_hubert_stream_is_causal_and_windowed(hubert_base, speech):
    # past_frames = 4, chunk_frames = 4: each chunk is read from <= 8 frames ending at its end.
    wave = speech[: 16 * SPF]
    stream = hubert_base.stream()
    chunked = push_in_chunks(stream, wave, [4 * SPF])
    assert chunked.shape == (16, 768)
    stream.reset()
    np.testing.assert_array_equal(push_in_chunks(stream, wave[: 8 * SPF], [4 * SPF]), chunked[:8])
    # Changing audio after the end of frame 11 (a chunk end) leaves frames 0-11 untouched...
    changed = wave.copy()
    changed[12 * SPF:] = np.random.default_rng(0).uniform(-0.5, 0.5, 4 * SPF)
    after = push_in_chunks(hubert_base.stream(), changed, [4 * SPF])
    np.testing.assert_array_equal(after[:12], chunked[:12])
    assert not np.allclose(after[12:], chunked[12:])
    # ... and audio older than the window is forgotten: frames 12-15 read frames 8-15 only.
    old_changed = wave.copy()
    old_changed[: 8 * SPF] = 0.0
    np.testing.assert_array_equal(push_in_chunks(hubert_base.stream(), old_changed, [4 * SPF])[12:], chunked[12:])
    # Pushed frame by frame, every frame reads audio up to its own end only.
    per_frame = push_in_chunks(hubert_base.stream(), wave[: 6 * SPF], [SPF])
    changed_early = wave[: 6 * SPF].copy()
    changed_early[4 * SPF:] = 0.0
    np.testing.assert_array_equal(push_in_chunks(hubert_base.stream(), changed_early, [SPF])[:4], per_frame[:4])


def test_hubert_long_clips_are_segmented(hubert_base_file, speech):
    path, _ = hubert_base_file
    extractor = get_extractor("hubert-large", weights=str(path), architecture="base",
                              max_segment_frames=20, segment_context_frames=5)
    wave = speech[: 30 * SPF]
    features = extractor.extract(wave, 30)
    assert features.shape == (30, 768)
    # Segment cores are 10 frames: frames 10-19 read only frames 5-24.
    changed = wave.copy()
    changed[: 5 * SPF] = 0.0
    changed[25 * SPF:] = 0.0
    np.testing.assert_array_equal(extractor.extract(changed, 30)[10:20], features[10:20])


def _renamed(state: dict, naming: str) -> dict:
    """torchaudio's HuBERT keys as fairseq's release or Hugging Face's hubert-*-ll60k name them
    (written here independently of the loader's table, from the two projects' module names)."""
    out = {}
    for key, value in state.items():
        key = key.replace("parametrizations.weight.original0", "weight_g").replace(
            "parametrizations.weight.original1", "weight_v")
        if naming == "hf":
            key = key.replace("encoder.feature_projection.", "feature_projection.")
            key = key.replace("encoder.transformer.", "encoder.")
        else:
            key = key.replace("encoder.feature_projection.projection.", "post_extract_proj.")
            key = key.replace("encoder.feature_projection.layer_norm.", "layer_norm.")
            key = key.replace("feature_extractor.conv_layers.0.layer_norm.", "feature_extractor.conv_layers.0.2.")
            for i in range(12):
                key = key.replace(f"feature_extractor.conv_layers.{i}.conv.", f"feature_extractor.conv_layers.{i}.0.")
            key = key.replace("encoder.transformer.pos_conv_embed.conv.", "encoder.pos_conv.0.")
            key = key.replace("encoder.transformer.layer_norm.", "encoder.layer_norm.")
            key = key.replace("encoder.transformer.layers.", "encoder.layers.")
            key = key.replace(".attention.", ".self_attn.").replace(".layer_norm.", ".self_attn_layer_norm.") \
                if key.startswith("encoder.layers.") and ".final_layer_norm." not in key else key
            key = key.replace(".feed_forward.intermediate_dense.", ".fc1.").replace(".feed_forward.output_dense.", ".fc2.")
        out[key] = value
    return out


def test_hubert_accepts_fairseq_and_hugging_face_checkpoints(tmp_path, hubert_base_file, hubert_base, speech):
    """#19 item 8: the checkpoints users have, as local files: a Hugging Face model folder
    (model.safetensors or pytorch_model.bin) and fairseq's .pt (its state dict under "model",
    settings in an argparse Namespace); shards record the weights' sha256, not their path."""
    import argparse

    from safetensors.torch import save_file

    _, model = hubert_base_file
    wave = speech[: 10 * SPF]
    reference = hubert_base.extract(wave, 10)
    state = model.state_dict()
    hf = {f"hubert.{k}" if i % 2 else k: v.contiguous() for i, (k, v) in enumerate(_renamed(state, "hf").items())}
    hf["masked_spec_embed"] = torch.zeros(768)
    fairseq = {"args": argparse.Namespace(label_rate=50), "model": {
        **_renamed(state, "fairseq"), "label_embs_concat": torch.zeros(3), "final_proj.weight": torch.zeros(2)}}
    writers = {"hf_safe/model.safetensors": lambda path: save_file(hf, str(path)),
               "hf_bin/pytorch_model.bin": lambda path: torch.save(hf, path),
               "hubert_base_ls960.pt": lambda path: torch.save(fairseq, path)}
    for name, write in writers.items():  # one 360 MB copy on disk at a time
        path = tmp_path / name
        path.parent.mkdir(exist_ok=True)
        if path.parent != tmp_path:
            (path.parent / "config.json").write_text('{"model_type": "hubert"}')
        write(path)
        weights = path.parent if path.parent != tmp_path else path
        loaded = get_extractor("hubert-large", weights=str(weights), architecture="base",
                               past_frames=4, device="cpu")
        np.testing.assert_array_equal(loaded.extract(wave, 10), reference, err_msg=str(weights))
        record = loaded.record()
        assert "weights" not in record and len(record["weights_sha256"]) == 64
        del loaded  # its tensors map the file: the space is freed when both are gone
        gc.collect()
        path.unlink()

    import datetime

    bad = tmp_path / "foreign.pt"  # an object beyond tensors, as an omegaconf config would be
    torch.save({"cfg": datetime.date(2021, 6, 1), "model": _renamed(state, "fairseq")}, bad)
    with pytest.raises(ValueError, match=r"save its 'model' state dict alone"):
        get_extractor("hubert-large", weights=str(bad), architecture="base")
    with pytest.raises(FileNotFoundError, match="model.safetensors or pytorch_model.bin"):
        get_extractor("hubert-large", weights=str(tmp_path), architecture="base")
