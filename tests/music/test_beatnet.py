"""BeatNet reimplementation against the original pipeline's reference vectors, and its weights."""

from __future__ import annotations

import zipfile
from pathlib import Path

import numpy as np
import pytest

from dancegraph.errors import ModelFileError
from dancegraph.music import barpointer, beatnet, weights


@pytest.fixture(scope="module")
def ref(shared: Path) -> dict[str, np.ndarray]:
    with np.load(shared / "reference" / "beatnet" / "vibe_ace.npz") as z:
        return {k: z[k] for k in z.files}


def test_weights_installed_and_pinned() -> None:
    """The install step (`python -m dancegraph.music.weights fetch`) must have run."""
    status = weights.verify()
    assert status == {name: "ok" for name in weights.FILE_SHA256}, (
        f"BeatNet weights not installed correctly in {weights.weights_dir()}: {status}; "
        "run `python -m dancegraph.music.weights fetch`"
    )
    licence = (weights.weights_dir() / weights.LICENSE_NAME).read_text()
    assert "CC BY 4.0" in licence or "Attribution 4.0" in licence


def test_filterbank_shape_and_normalisation() -> None:
    fb = beatnet.log_filterbank()
    assert fb.shape == (705, 136)
    np.testing.assert_allclose(fb.sum(axis=0), 1.0, atol=1e-5)
    # bands ascend in frequency
    centres = (fb * np.arange(705)[:, None]).sum(axis=0)
    assert np.all(np.diff(centres) > 0)


def test_features_match_reference(ref: dict[str, np.ndarray]) -> None:
    feats = beatnet.beatnet_features(ref["audio_22050"])
    assert feats.shape == ref["features"].shape == (3073, 272)
    err = np.abs(feats - ref["features"]).max()
    assert err < 1e-5, f"feature error {err}"


def test_logits_match_reference(ref: dict[str, np.ndarray]) -> None:
    from_ref_feats = beatnet.logits(ref["features"], 1)
    assert np.abs(from_ref_feats - ref["logits"]).max() < 1e-4
    from_own_feats = beatnet.logits(beatnet.beatnet_features(ref["audio_22050"]), 1)
    assert np.abs(from_own_feats - ref["logits"]).max() < 1e-4


def test_chunked_lstm_equals_one_pass(ref: dict[str, np.ndarray]) -> None:
    """Long songs go through the LSTM in chunks with the state carried: same numbers."""
    feats = ref["features"][:1200]
    whole = beatnet.logits(feats, 2, chunk_frames=10_000)
    chunked = beatnet.logits(feats, 2, chunk_frames=250)
    assert np.abs(whole - chunked).max() < 1e-5


def test_activations_are_reference_probs(ref: dict[str, np.ndarray]) -> None:
    act = beatnet.activations(ref["audio_22050"], models=(1,))
    assert act.shape == (3073, 2)
    assert np.abs(act - ref["probs"][:, :2]).max() < 1e-5


def test_decoder_reproduces_reference_beats(ref: dict[str, np.ndarray]) -> None:
    """With BeatNet's own settings the bar-pointer decoder gives the reference output exactly."""
    dec = barpointer.decode(ref["probs"][:, :2], barpointer.MADMOM)
    assert len(dec.times) == len(ref["beats"]) == 143
    np.testing.assert_allclose(dec.times, ref["beats"][:, 0], atol=1e-9)
    np.testing.assert_array_equal(dec.positions, ref["beats"][:, 1].astype(int))
    assert set(dec.meters.tolist()) == {4}


def test_ensemble_of_three_models_is_a_probability() -> None:
    rng = np.random.default_rng(0)
    y = (rng.standard_normal(22050 * 4) * 0.1).astype(np.float32)
    act = beatnet.activations(y, models=(1, 2, 3))
    assert act.shape == (200, 2)
    assert np.all(act >= 0) and np.all(act.sum(axis=1) <= 1.0 + 1e-6)


def test_missing_weights_is_a_clear_error(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("DANCEGRAPH_BEATNET_WEIGHTS", str(tmp_path / "none"))
    monkeypatch.setattr(beatnet, "_MODELS", {})
    with pytest.raises(ModelFileError) as err:
        beatnet.load_model(1)
    assert err.value.code == "model_missing" and "weights fetch" in err.value.message


def test_corrupt_weights_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    (tmp_path / "model_1_weights.pt").write_bytes(b"not a torch file")
    monkeypatch.setenv("DANCEGRAPH_BEATNET_WEIGHTS", str(tmp_path))
    monkeypatch.setattr(beatnet, "_MODELS", {})
    with pytest.raises(ModelFileError) as err:
        beatnet.load_model(1)
    assert err.value.code == "model_file_invalid"


def test_wheel_with_wrong_hash_is_refused(tmp_path: Path) -> None:
    fake = tmp_path / weights.WHEEL_NAME
    with zipfile.ZipFile(fake, "w") as zf:
        zf.writestr("BeatNet/models/model_1_weights.pt", b"x")
    with pytest.raises(ModelFileError) as err:
        weights.extract(fake, tmp_path / "out")
    assert err.value.code == "model_hash_mismatch"
    assert not (tmp_path / "out" / "model_1_weights.pt").exists()
    assert weights.verify(tmp_path / "out") == {n: "missing" for n in weights.FILE_SHA256}
