"""Every bad input of a job submission gets its specific 4xx problem, and leaves nothing behind:
no job row, no stored blob, no temporary upload, no queued message."""

from __future__ import annotations

import io

import numpy as np
import pytest
import soundfile as sf
from sqlalchemy import func, select

from services.db import session_scope
from services.models import Job
from tests.services.conftest import broker_messages, wav_bytes


def _flac_silence(seconds: int, sr: int = 8000) -> bytes:
    """A real FLAC file of ``seconds`` of silence (tiny: FLAC stores silence in a few bytes)."""
    buf = io.BytesIO()
    with sf.SoundFile(buf, "w", samplerate=sr, channels=1, format="FLAC", subtype="PCM_16") as fh:
        block = np.zeros(sr * 60, dtype=np.int16)
        for _ in range(seconds // 60):
            fh.write(block)
    return buf.getvalue()


def _nothing_written(api) -> None:
    with session_scope(api.settings.database_url) as session:
        n = session.scalar(
            select(func.count()).select_from(Job).where(Job.tenant_id == api.tenant_id)
        )
    assert n == 0
    store = api.app.state.ctx.store
    assert list(store.list("blobs")) == [] if store.exists("blobs") else True
    tmp = store.root / "tmp"
    assert not tmp.exists() or list(tmp.iterdir()) == []
    assert broker_messages(api.settings) == []


def _problem(resp, status: int, code: str, field: str | None):
    assert resp.status_code == status, resp.text
    assert resp.headers["content-type"].startswith("application/problem+json")
    body = resp.json()
    assert body["code"] == code, body
    assert body["status"] == status
    assert body["field"] == field, body
    assert body["detail"]
    return body


@pytest.fixture(scope="module")
def two_hour_flac() -> bytes:
    return _flac_silence(2 * 3600)


def test_no_audio_part(api):
    _problem(api.submit(None, {"alternatives": 1}), 422, "audio_missing", "audio")
    _nothing_written(api)


def test_audio_sent_as_text_field(api):
    resp = api.post("/v1/jobs", files=[("audio", (None, "not a file")), ("spec", (None, "{}"))])
    _problem(resp, 422, "audio_missing", "audio")
    _nothing_written(api)


def test_not_multipart(api):
    _problem(
        api.post("/v1/jobs", json={"spec": {}}),
        415,
        "content_type_unsupported",
        "header.Content-Type",
    )
    _nothing_written(api)


def test_empty_file(api):
    _problem(api.submit(b"", {}), 422, "audio_empty", "audio")
    _nothing_written(api)


def test_one_second_file(api):
    body = _problem(api.submit(wav_bytes(1.0), {}), 422, "audio_too_short", "audio")
    assert "1.0 s" in body["detail"]
    _nothing_written(api)


def test_non_audio_bytes_named_mp3(api):
    junk = b"<html><body>definitely not a song</body></html>" * 50
    body = _problem(api.submit(junk, {}, filename="song.mp3"), 415, "audio_undecodable", "audio")
    assert "song.mp3" in body["detail"]
    _nothing_written(api)


def test_audio_magic_but_corrupt(api):
    # the first bytes say WAV, the rest is garbage: the header reader refuses it
    corrupt = b"RIFF\x24\x00\x00\x00WAVEjunk" + b"\x01" * 4000
    _problem(api.submit(corrupt, {}, filename="x.wav"), 415, "audio_undecodable", "audio")
    _nothing_written(api)


def test_two_hour_file(api, two_hour_flac):
    assert len(two_hour_flac) < 1_000_000  # a real 2-hour file, small because it is silence
    body = _problem(
        api.submit(two_hour_flac, {}, filename="long.flac"), 422, "audio_too_long", "audio"
    )
    assert "7200 s" in body["detail"]
    _nothing_written(api)


def test_over_limit_upload(api, song_wav):
    # a limit below the song's size: refused while the body streams in, nothing kept
    api.app.state.ctx.settings.max_upload_bytes = 50_000
    assert len(song_wav) > 50_000
    _problem(api.submit(song_wav, {}), 413, "upload_too_large", "audio")
    big = b"\0" * (50_000 + 2 * 1024 * 1024)  # past the whole-body limit as well
    _problem(api.submit(big, {}), 413, "upload_too_large", "audio")
    _nothing_written(api)


def test_declared_length_over_limit_refused_before_reading(api):
    api.app.state.ctx.settings.max_upload_bytes = 10_000
    resp = api.post(
        "/v1/jobs",
        content=b"x" * 10,
        headers={"Content-Type": "multipart/form-data; boundary=abc", "Content-Length": str(10**9)},
    )
    _problem(resp, 413, "upload_too_large", "audio")
    _nothing_written(api)


def test_malformed_spec_json(api, song_wav):
    _problem(api.submit(song_wav, '{"alternatives": 3,'), 422, "spec_malformed", "spec")
    _problem(api.submit(song_wav, "[1, 2]"), 422, "spec_malformed", "spec")
    _nothing_written(api)


def test_unknown_spec_field(api, song_wav):
    _problem(
        api.submit(song_wav, {"alternatives": 2, "tempo_hint": 120}),
        422,
        "spec_unknown_field",
        "spec.tempo_hint",
    )
    _problem(
        api.submit(song_wav, {"weights": {"rythm": 1.0}}),
        422,
        "spec_unknown_field",
        "spec.weights.rythm",
    )
    _nothing_written(api)


def test_unknown_dataset(api, song_wav):
    body = _problem(
        api.submit(song_wav, {"dataset": "no-such-dataset"}), 422, "unknown_dataset", "spec.dataset"
    )
    assert "no-such-dataset" in body["detail"]
    listed = {"dataset": ["cmu-salsa", "no-such-dataset"]}  # a list: every library must exist
    body = _problem(api.submit(song_wav, listed), 422, "unknown_dataset", "spec.dataset")
    assert "no-such-dataset" in body["detail"]
    _nothing_written(api)


def test_negative_alternatives(api, song_wav):
    body = _problem(
        api.submit(song_wav, {"alternatives": -2}), 422, "spec_invalid", "spec.alternatives"
    )
    assert body["errors"][0]["field"] == "spec.alternatives"
    _nothing_written(api)


def test_invalid_nested_spec_names_the_field(api, song_wav):
    _problem(
        api.submit(song_wav, {"include": [{"node": "bad node"}]}),
        422,
        "spec_invalid",
        "spec.include[0].node",
    )
    _nothing_written(api)


def test_two_audio_parts_on_jobs(api, song_wav):
    files = [
        ("audio", ("a.wav", song_wav, "audio/wav")),
        ("audio", ("b.wav", song_wav, "audio/wav")),
    ]
    resp = api.post("/v1/jobs", files=files)
    _problem(resp, 422, "audio_multiple", "audio")
    _nothing_written(api)


def test_malformed_multipart(api):
    resp = api.post(
        "/v1/jobs",
        content=b"--abc\r\nContent-Disposition: form-data\r\n\r\nnope",
        headers={"Content-Type": "multipart/form-data"},
    )
    assert resp.status_code in (400, 422), resp.text
    assert resp.json()["code"] in ("multipart_malformed", "audio_missing")
    _nothing_written(api)


@pytest.mark.parametrize(
    ("headers", "code"),
    [
        ({}, "auth_missing"),
        ({"X-API-Key": "dg_wrong"}, "auth_invalid"),
        ({"Authorization": "Bearer dg_wrong"}, "auth_invalid"),
    ],
)
def test_missing_or_wrong_key(api, song_wav, headers, code):
    files = [("audio", ("a.wav", song_wav, "audio/wav")), ("spec", (None, "{}"))]
    resp = api.client.post("/v1/jobs", files=files, headers=headers)
    _problem(resp, 401, code, "header.X-API-Key")
    assert resp.headers["www-authenticate"].startswith("Bearer")
    for url in ("/v1/jobs", "/v1/datasets", "/v1/jobs/whatever", "/v1/batches/whatever"):
        assert api.client.get(url, headers=headers).status_code == 401
    _nothing_written(api)


def test_bearer_key_accepted(api):
    resp = api.client.get("/v1/jobs", headers={"Authorization": f"Bearer {api.key}"})
    assert resp.status_code == 200


def test_bad_query_parameters(api):
    _problem(api.get("/v1/jobs?limit=0"), 422, "request_invalid", "query.limit")
    _problem(api.get("/v1/jobs?status=exploded"), 422, "request_invalid", "query.status")
    _problem(api.get("/v1/jobs?cursor=!!notacursor"), 422, "cursor_invalid", "query.cursor")


def test_bad_idempotency_key_header(api, song_wav):
    resp = api.submit(song_wav, {}, headers={"Idempotency-Key": "k" * 201})
    _problem(resp, 422, "request_invalid", "header.Idempotency-Key")
    _nothing_written(api)


def test_text_postgres_cannot_store_is_refused(api, song_wav):
    """NUL characters (which PostgreSQL text and JSONB refuse) are a 4xx, never a 500."""
    _problem(
        api.submit(song_wav, {"recreate": "60_\u000003"}), 422, "spec_invalid", "spec.recreate"
    )
    assert api.get("/v1/jobs/abc%00def").status_code == 404
    assert api.get("/v1/batches/abc%00def").status_code == 404
    assert api.get("/v1/datasets/abc%00def").status_code == 404
    assert api.get("/v1/jobs", params={"batch_id": "a\x00b"}).status_code == 422
    import base64

    cursor = base64.urlsafe_b64encode(b'["2026-01-01T00:00:00", "a\\u0000b"]').decode()
    _problem(api.get("/v1/jobs", params={"cursor": cursor}), 422, "cursor_invalid", "query.cursor")
    _nothing_written(api)


def test_odd_file_name_is_cleaned(api, song_wav):
    # the client's name is display-only: base name, no control or bidi-override characters
    resp = api.submit(song_wav, {}, filename="../../etc/\u202esong.wav")
    assert resp.status_code == 202, resp.text
    assert resp.json()["audio"]["filename"] == "song.wav"


def test_spec_as_a_file_part(api, song_wav):
    """`curl -F spec=@spec.json` sends the spec as a file: accepted, and checked the same way."""
    files = [
        ("audio", ("a.wav", song_wav, "audio/wav")),
        ("spec", ("spec.json", b'{"alternatives": 4}', "application/json")),
    ]
    resp = api.post("/v1/jobs", files=files)
    assert resp.status_code == 202 and resp.json()["spec"]["alternatives"] == 4
    files[1] = ("spec", ("spec.json", b"\xff\xfe{", "application/json"))
    _problem(api.post("/v1/jobs", files=files), 422, "spec_malformed", "spec")


def test_over_limit_chunked_upload_is_cut_while_streaming(api, song_wav):
    """Without a Content-Length (chunked transfer) the limit is enforced on the bytes as they come."""
    api.app.state.ctx.settings.max_upload_bytes = 50_000
    boundary = "dgboundary"
    head = (
        f'--{boundary}\r\nContent-Disposition: form-data; name="audio"; filename="big.wav"\r\n'
        "Content-Type: audio/wav\r\n\r\n"
    ).encode()

    def body():
        yield head
        for _ in range(64):  # 64 x 16 KiB = 1 MiB, far past 50 kB + form overhead
            yield b"\0" * 16384
        yield f"\r\n--{boundary}--\r\n".encode()

    resp = api.post(
        "/v1/jobs",
        content=body(),
        headers={"Content-Type": f"multipart/form-data; boundary={boundary}"},
    )
    _problem(resp, 413, "upload_too_large", "audio")
    _nothing_written(api)


def test_truncated_multipart_body(api, song_wav):
    """A body cut off inside the audio part (a dropped connection) keeps nothing."""
    boundary = "cutoff"
    body = (
        f'--{boundary}\r\nContent-Disposition: form-data; name="audio"; filename="a.wav"\r\n\r\n'.encode()
        + song_wav[:100_000]
    )
    resp = api.post(
        "/v1/jobs",
        content=body,
        headers={"Content-Type": f"multipart/form-data; boundary={boundary}"},
    )
    _problem(resp, 400, "multipart_malformed", "body")
    _nothing_written(api)
