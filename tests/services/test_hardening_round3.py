"""The "also found" probes of issue 33, each run as the prober ran it against the real app, store
and task code: a non-ASCII token, a full disk (a real tmpfs filled up), callback addresses that
hide a forbidden one, weak secrets, echoed megabytes, a batch of non-audio parts, and a result
that left the store under a running FBX export."""

from __future__ import annotations

import json
import os
import socket
import subprocess
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest
from celery.exceptions import Retry

from services import webhooks
from tests.services.conftest import _make_api, wav_bytes
from tests.services.test_worker_webhooks import LOCAL, SECRET, Receiver

served_api = contextmanager(_make_api)  # the API on explicit settings, closed at the end

# --- a real full filesystem ---------------------------------------------------------------------


@pytest.fixture()
def tmpfs(tmp_path: Path) -> Iterator[Callable[[str, str], Path]]:
    """``mount(name, size)``: a fresh tmpfs of ``size`` (``1m``, ``48m``) at ``tmp_path/name``;
    the test is skipped where mounting is not permitted; unmounted at the end."""
    mounted: list[Path] = []

    def mount(name: str, size: str) -> Path:
        root = tmp_path / name
        root.mkdir()
        done = subprocess.run(
            ["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(root)],
            capture_output=True,
        )
        if done.returncode != 0:
            pytest.skip(f"cannot mount a tmpfs here: {done.stderr.decode().strip()}")
        mounted.append(root)
        return root

    yield mount
    for root in mounted:
        subprocess.run(["umount", "-l", str(root)], capture_output=True)


def fill(root: Path, leave_bytes: int) -> Path:
    """Take all but ``leave_bytes`` of the free space of ``root``'s filesystem with one file."""
    stat = os.statvfs(root)
    ballast = root / "ballast"
    with open(ballast, "wb") as fh:
        os.posix_fallocate(fh.fileno(), 0, stat.f_bavail * stat.f_frsize - leave_bytes)
    return ballast


def sqlite_store_settings(make_settings, tmp_path: Path, **overrides):
    """Settings of the embedded default (a migrated SQLite file) with ``overrides`` (the store)."""
    from services.db import upgrade_schema

    settings = make_settings(f"sqlite:///{tmp_path / 'dg.db'}", **overrides)
    upgrade_schema(settings.database_url)
    return settings


def demo_job(api, tmp_path: Path, formats: list[str]) -> str:
    """The id of a queued job: the demo song on the demo library (imported and its graph built
    into the API's store as the test dataset), one alternative in ``formats``."""
    from tests.demo import demo_song
    from tests.services.conftest import TEST_DATASET
    from tests.services.test_worker_pipeline import _ranged_demo

    _ranged_demo(api.app.state.ctx.store, tmp_path, TEST_DATASET)
    wav, _ = demo_song(tmp_path)
    spec = {"dataset": TEST_DATASET, "alternatives": 1, "output": {"formats": formats}}
    resp = api.submit(wav.read_bytes(), spec)
    assert resp.status_code == 202, resp.text
    return resp.json()["id"]


def _scratch_files(settings) -> list[str]:
    from services.config import object_store

    scratch = object_store(settings).scratch
    return sorted(p.name for p in scratch.iterdir()) if scratch.is_dir() else []


# --- 1. a preview token whose digits are not ASCII ----------------------------------------------


@pytest.mark.parametrize("token", ["².x", "1²3.abc", "٣.abc", "12.sig-é", "١٢٣٤٥٦٧٨٩٠١٢.x"])
def test_a_preview_token_with_non_ascii_digits_is_401_not_500(api, token):
    resp = api.client.get(f"/v1/jobs/{'0' * 32}/preview", params={"token": token})
    assert resp.status_code == 401, resp.text
    assert resp.json()["code"] == "preview_token_invalid"


def asgi_post(app, path: str, headers: list[tuple[bytes, bytes]], body: bytes) -> int:
    """POST ``body`` to ``app`` as an ASGI server hands it over, ``headers`` byte for byte (an
    HTTP client would re-encode a non-ASCII value); returns the answer's status."""
    import anyio

    statuses: list[int] = []

    async def receive() -> dict:
        return {"type": "http.request", "body": body, "more_body": False}

    async def send(message: dict) -> None:
        if message["type"] == "http.response.start":
            statuses.append(message["status"])

    scope = {
        "type": "http",
        "asgi": {"version": "3.0"},
        "http_version": "1.1",
        "method": "POST",
        "scheme": "http",
        "path": path,
        "raw_path": path.encode(),
        "query_string": b"",
        "root_path": "",
        "headers": headers,
        "client": ("127.0.0.1", 50000),
        "server": ("testserver", 80),
    }
    anyio.run(app, scope, receive, send)
    return statuses[0]


def test_a_content_length_of_non_ascii_digits_is_not_a_500(api, song_wav):
    """``'²'.isdigit()`` is True and ``int('²')`` raises: the size pre-check reads ASCII only."""
    import httpx

    upload = httpx.Request(
        "POST", "http://testserver/v1/jobs", files={"audio": ("a.wav", song_wav)}
    )
    headers = [
        (b"x-api-key", api.key.encode()),
        (b"content-type", upload.headers["content-type"].encode()),
        (b"content-length", "²".encode("latin-1")),  # ASGI header bytes are read as latin-1
    ]
    assert asgi_post(api.app, "/v1/jobs", headers, upload.read()) == 202


# --- 2. a full disk ---------------------------------------------------------------------------


def test_an_upload_to_a_full_store_is_a_coded_503_and_leaves_nothing(
    make_settings, pg_url, tmpfs, song_wav
):
    root = tmpfs("store", "2m")
    settings = make_settings(pg_url, store_root=str(root))
    with served_api(settings) as api:
        ballast = fill(root, 128 * 1024)  # the 0.5 MB song cannot fit
        full = api.submit(song_wav, {})
        left = _scratch_files(settings)
        kept = api.get("/v1/jobs").json()["items"]
        ballast.unlink()  # space comes back: the same upload is taken
        again = api.submit(song_wav, {})
    assert full.status_code == 503, full.text
    assert full.json()["code"] == "store_full" and int(full.headers["Retry-After"]) > 0
    assert left == [] and kept == []
    assert again.status_code == 202, again.text


def run_as_retry(task, job_id: str, retries: int) -> None:
    """Run ``task``'s body for ``job_id`` as its ``retries``-th retry: Celery's request context
    with that count; a further retry raises ``celery.exceptions.Retry`` carrying its countdown
    (``when``) instead of being published, so the test decides when the next try runs."""
    task.push_request(
        id=f"test-{job_id}",
        args=[job_id],
        kwargs={},
        retries=retries,
        is_eager=True,
        called_directly=False,
    )
    try:
        task.run(job_id)
    finally:
        task.pop_request()


def test_a_job_stopped_by_a_full_disk_is_retried_later_and_succeeds_once_space_is_freed(
    make_settings, tmp_path, tmpfs
):
    from services.worker import tasks

    root = tmpfs("store", "48m")
    settings = sqlite_store_settings(make_settings, tmp_path, store_root=str(root))
    with served_api(settings) as api:
        job_id = demo_job(api, tmp_path, ["bvh"])
        ballast = fill(root, 4 * 1024)  # the analysis cannot be cached, nor the result written

        # the try after the five quick retries: before, the job failed service_unavailable here
        with pytest.raises(Retry) as retry:
            run_as_retry(tasks.run_job, job_id, tasks.MAX_RETRIES)
        assert retry.value.when == tasks.disk_full_delay(tasks.MAX_RETRIES) == 300
        assert api.get(f"/v1/jobs/{job_id}").json()["status"] == "queued"

        ballast.unlink()
        run_as_retry(tasks.run_job, job_id, tasks.MAX_RETRIES + 1)
        assert api.get(f"/v1/jobs/{job_id}").json()["status"] == "succeeded"
    waited = sum(tasks.disk_full_delay(n) for n in range(tasks.DISK_FULL_RETRIES))
    assert waited >= 2 * 3600  # the schedule outlasts a disk-full episode of two hours


# --- 3. callback addresses that carry a forbidden one --------------------------------------------

HIDDEN_LOOPBACK = [
    "http://[::127.0.0.1]/hook",  # IPv4-compatible
    "http://[::ffff:127.0.0.1]/hook",  # IPv4-mapped
    "http://[64:ff9b::7f00:1]/hook",  # NAT64 well-known prefix
    "http://[64:ff9b::a9fe:a9fe]/latest/meta-data/",  # NAT64 of the metadata address
    "http://[64:ff9b:1::808:808]/hook",  # local-use NAT64: never public
    "http://[2002:7f00:1::]/hook",  # 6to4 of 127.0.0.1
    "http://[2002:a00:5::1]/hook",  # 6to4 of 10.0.0.5
    "http://[2001:0:4136:e378:8000:63bf:80ff:fffe]/hook",  # Teredo, client 127.0.0.1
    "http://[2001:0:7f00:1:0:ffff:f5ff:fffa]/hook",  # Teredo, server 127.0.0.1, client 10.0.0.5
]


@pytest.mark.parametrize("url", HIDDEN_LOOPBACK)
def test_ipv6_forms_of_forbidden_addresses_are_refused_at_submit_and_at_send(url):
    with pytest.raises(webhooks.CallbackForbidden):
        webhooks.check_callback_url(url)
    result = webhooks.deliver(url, b"{}", SECRET, attempts=3, sleep=lambda s: None)
    assert not result.ok and result.attempts == 1 and not result.retryable
    assert (result.error or "").startswith("callback_url_forbidden")


@pytest.mark.parametrize(
    "url",
    [
        "http://[64:ff9b::808:808]/hook",  # NAT64 of 8.8.8.8
        "http://[2002:808:808::1]/hook",  # 6to4 of 8.8.8.8
        "http://[2606:4700:4700::1111]/hook",
        "http://8.8.8.8/hook",
    ],
)
def test_ipv6_forms_of_public_addresses_still_pass(url):
    webhooks.check_callback_url(url)


@pytest.fixture()
def dns(monkeypatch: pytest.MonkeyPatch) -> dict[str, list[str]]:
    """Names the resolver answers with the listed addresses in turn (the last one repeats),
    logged per lookup in ``dns["lookups"]``; every other name and literal goes to the real
    ``socket.getaddrinfo``, which the HTTP client's own connect also calls."""
    real = socket.getaddrinfo
    answers: dict[str, list[str]] = {"lookups": []}

    def getaddrinfo(host, port, *args, **kwargs):
        if isinstance(host, str) and host in answers and host != "lookups":
            answers["lookups"].append(host)
            queue = answers[host]
            address = queue.pop(0) if len(queue) > 1 else queue[0]
            return real(address, port, *args, **kwargs)
        return real(host, port, *args, **kwargs)

    monkeypatch.setattr(socket, "getaddrinfo", getaddrinfo)
    return answers


def test_a_name_resolving_to_loopback_is_refused_at_submit(make_settings, pg_url, dns, song_wav):
    dns["hooks.example.test"] = ["127.0.0.1"]
    settings = make_settings(pg_url, webhook_allow_networks=[])
    urls = [
        "http://hooks.example.test/done",
        "http://[::127.0.0.1]:8001/",
        "http://[2002:7f00:1::]/",
    ]
    with served_api(settings) as api:
        answers = [api.submit(song_wav, {"callback_url": url}) for url in urls]
        kept = api.get("/v1/jobs").json()["items"]
    assert [r.status_code for r in answers] == [422] * 3, answers[0].text
    assert {r.json()["code"] for r in answers} == {"callback_url_forbidden"}
    assert kept == []


def test_a_name_is_resolved_once_and_the_post_pinned_to_the_checked_address(dns):
    """The name answers the allowed receiver first, then a forbidden address (DNS rebinding):
    the one POST goes to the checked address, with the name kept in the Host header."""
    with Receiver() as rx:
        port = rx.url.split(":")[2].split("/")[0]
        dns["rebind.example.test"] = ["127.0.0.1", "10.255.255.1"]
        result = webhooks.deliver(
            f"http://rebind.example.test:{port}/hook",
            b"{}",
            SECRET,
            attempts=1,
            allow_networks=LOCAL,
            timeout=3.0,
        )
    assert result.ok, result.error
    assert dns["lookups"] == ["rebind.example.test"]
    assert [c["headers"]["Host"] for c in rx.calls] == [f"rebind.example.test:{port}"]


# --- 4. weak secrets ----------------------------------------------------------------------------


@pytest.mark.parametrize(
    "secret",
    [" " * 40, "a" * 36, "abcdefghij" * 4, " " * 32 + "abcdefgh", "ab" * 20, "password" * 5],
)
def test_weak_secrets_are_refused_outside_the_embedded_default(secret):
    from pydantic import ValidationError

    from services.config import Settings

    with pytest.raises(ValidationError, match="DANCEGRAPH_WEBHOOK_SECRET"):
        Settings(
            database_url="postgresql+psycopg://postgres@127.0.0.1:5432/none",
            broker_url="redis://127.0.0.1:6379/0",
            webhook_secret=secret,
            preview_secret="5f0c9e2a7b41d83e6a9c0f17b2d4e85a3c6f9b0e",
        )


def test_random_secrets_pass_the_strength_rule():
    import secrets

    from services.config import secret_weakness

    assert all(secret_weakness(secrets.token_hex(16)) is None for _ in range(2000))
    assert secret_weakness(secrets.token_urlsafe(32)) is None


# --- 5. what a problem echoes -------------------------------------------------------------------


def test_a_megabyte_unknown_spec_key_answers_a_small_422(api, song_wav):
    key = "k" * 1_000_000
    resp = api.submit(song_wav, json.dumps({key: 1}))
    assert resp.status_code == 422, resp.text[:300]
    assert len(resp.content) < 4096
    body = resp.json()
    assert body["field"].startswith("spec.kkk") and body["field"].endswith("…")
    assert "k" * 200 not in resp.text


def test_ten_thousand_unknown_keys_list_a_bounded_number_of_errors(api, song_wav):
    resp = api.submit(song_wav, json.dumps({f"unknown_{i}": i for i in range(10_000)}))
    assert resp.status_code == 422
    assert len(resp.json()["errors"]) <= 32 and len(resp.content) < 16_384


def test_a_60_kb_job_id_is_echoed_bounded_in_the_404(api):
    resp = api.get(f"/v1/jobs/{'j' * 60_000}")
    assert resp.status_code == 404
    assert len(resp.content) < 4096 and "j" * 200 not in resp.text


# --- 6. a batch of non-audio parts --------------------------------------------------------------


def _written_bytes() -> int:
    """Bytes this process handed to write() so far (``/proc/self/io`` ``wchar``)."""
    for line in Path("/proc/self/io").read_text().splitlines():
        if line.startswith("wchar:"):
            return int(line.split()[1])
    raise AssertionError("no wchar in /proc/self/io")


def test_a_batch_stops_at_its_first_non_audio_part_without_writing_it(api):
    if not Path("/proc/self/io").exists():
        pytest.skip("no /proc/self/io here to count written bytes")
    song = wav_bytes(10.0)
    junk = [os.urandom(1 << 20) * 24 for _ in range(3)]  # three parts of 24 MiB each
    files = [("audio", ("song.wav", song, "audio/wav"))]
    files += [("audio", (f"junk{i}.mp3", part, "audio/mpeg")) for i, part in enumerate(junk)]
    before = _written_bytes()
    resp = api.post("/v1/batches", files=files, data={"spec": "{}"})
    written = _written_bytes() - before
    assert resp.status_code == 415, resp.text
    assert resp.json()["code"] == "audio_undecodable" and resp.json()["field"] == "audio[1]"
    assert written < len(song) + (2 << 20)  # the song and a little: not the 72 MiB of junk
    assert _scratch_files(api.settings) == []
    assert api.get("/v1/jobs").json()["items"] == []


# --- 7. the result leaves the store under a running FBX export ----------------------------------


@pytest.mark.parametrize("store_kind", ["fs", "s3"])
def test_a_result_gone_before_the_fbx_export_fails_the_job_with_a_named_reason(
    request, make_settings, tmp_path, store_kind
):
    from services.worker import pipeline, tasks

    extra = {"store_url": request.getfixturevalue("s3_url")} if store_kind == "s3" else {}
    settings = sqlite_store_settings(make_settings, tmp_path, **extra)
    with served_api(settings) as api:
        store = api.app.state.ctx.store
        job_id = demo_job(api, tmp_path, ["bvh", "fbx"])
        assert pipeline.run_job(job_id, settings).status == "fbx_queued"

        store.delete_prefix(f"jobs/{job_id}")  # an operator empties the bucket's results
        ran = tasks.export_fbx.apply(args=[job_id])
        assert ran.state == "SUCCESS"  # the task ends; the job carries the reason
        job = api.get(f"/v1/jobs/{job_id}").json()
    assert job["status"] == "failed", job
    assert job["error"]["code"] == "result_missing"
