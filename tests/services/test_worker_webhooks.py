"""Webhook signing and delivery against a real local HTTP receiver."""

from __future__ import annotations

import json
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import pytest

from services import webhooks

SECRET = "test-secret"
LOCAL = ["127.0.0.1/32"]  # the test receivers listen on loopback: allowed explicitly


class Receiver:
    """A local HTTP server that answers the queued statuses in turn (then 200) and records calls."""

    def __init__(self, statuses: list[int] | None = None):
        self.statuses = list(statuses or [])
        self.calls: list[dict] = []
        receiver = self

        class Handler(BaseHTTPRequestHandler):
            def do_POST(self):  # noqa: N802 (http.server's naming)
                body = self.rfile.read(int(self.headers.get("Content-Length", 0)))
                receiver.calls.append({"headers": dict(self.headers), "body": body})
                status = receiver.statuses.pop(0) if receiver.statuses else 200
                self.send_response(status)
                if 300 <= status < 400:  # a redirect back to this receiver
                    self.send_header("Location", "/redirected")
                self.send_header("Content-Length", "0")
                self.end_headers()

            def log_message(self, *_args):
                pass

        self.server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.url = f"http://127.0.0.1:{self.server.server_address[1]}/hook"
        self.thread = threading.Thread(target=self.server.serve_forever, daemon=True)

    def __enter__(self) -> Receiver:
        self.thread.start()
        return self

    def __exit__(self, *_exc) -> None:
        self.server.shutdown()
        self.server.server_close()


def test_signature_verifies_and_detects_tampering():
    body = webhooks.encode_payload("job.succeeded", {"id": "j1", "status": "succeeded"})
    sig = webhooks.sign(body, SECRET)
    assert sig.startswith("sha256=") and len(sig) == 7 + 64
    assert webhooks.verify(body, sig, SECRET)
    assert not webhooks.verify(body + b" ", sig, SECRET)
    assert not webhooks.verify(body, sig, "other-secret")
    assert not webhooks.verify(body, "", SECRET)


def test_delivery_retries_transient_failures_then_succeeds_signed():
    sleeps: list[float] = []
    with Receiver([503, 500]) as rx:
        body = webhooks.encode_payload("job.succeeded", {"id": "j1"})
        result = webhooks.deliver(
            rx.url,
            body,
            SECRET,
            attempts=5,
            base_delay=0.5,
            sleep=sleeps.append,
            allow_networks=LOCAL,
        )
    assert result.ok and result.attempts == 3 and result.status_code == 200
    assert sleeps == [0.5, 1.0]  # exponential backoff
    assert len(rx.calls) == 3
    ids = {c["headers"][webhooks.DELIVERY_HEADER] for c in rx.calls}
    assert len(ids) == 1  # one delivery id across the retries
    for call in rx.calls:
        assert call["body"] == body
        assert webhooks.verify(call["body"], call["headers"][webhooks.SIGNATURE_HEADER], SECRET)
        assert call["headers"][webhooks.EVENT_HEADER] == "job.succeeded"
    assert json.loads(rx.calls[-1]["body"])["job"]["id"] == "j1"


def test_delivery_is_bounded_and_client_errors_are_final():
    sleeps: list[float] = []
    with Receiver([500] * 10) as rx:
        result = webhooks.deliver(
            rx.url,
            b"{}",
            SECRET,
            attempts=3,
            base_delay=0.1,
            sleep=sleeps.append,
            allow_networks=LOCAL,
        )
    assert not result.ok and result.attempts == 3 and len(rx.calls) == 3 and result.retryable
    assert sleeps == [0.1, 0.2]
    with Receiver([410]) as rx:
        result = webhooks.deliver(
            rx.url, b"{}", SECRET, attempts=5, sleep=sleeps.append, allow_networks=LOCAL
        )
    assert not result.ok and result.attempts == 1 and not result.retryable
    assert result.error == "HTTP 410"


def test_unreachable_receiver_is_retried_not_raised():
    with Receiver() as rx:
        url = rx.url
    result = webhooks.deliver(
        url,
        b"{}",
        SECRET,
        attempts=2,
        base_delay=0.0,
        timeout=2,
        sleep=lambda s: None,
        allow_networks=LOCAL,
    )
    assert not result.ok and result.attempts == 2 and result.status_code is None
    assert result.retryable and "ConnectError" in (result.error or "")


@pytest.mark.parametrize(
    "url",
    [
        "http://127.0.0.1:8001/v1/graphs",
        "http://127.0.0.1:5432/",
        "http://10.1.2.3/hook",
        "http://172.16.0.1/hook",
        "http://192.168.1.1/hook",
        "http://[::1]:8000/hook",
        "http://[::ffff:127.0.0.1]/hook",
        "http://169.254.169.254/latest/meta-data/",
        "http://100.64.0.1/hook",
        "http://0.0.0.0:8000/",
        "http://localhost:8000/",
        "http://metadata.google.internal/computeMetadata/v1/",
        "http://instance-data/latest/",
    ],
)
def test_internal_callback_targets_are_refused_and_never_contacted(url):
    with pytest.raises(webhooks.CallbackForbidden) as err:
        webhooks.check_callback_url(url)
    assert err.value.code == "callback_url_forbidden" and err.value.status == 422
    result = webhooks.deliver(url, b"{}", SECRET, attempts=3, sleep=lambda s: None)
    assert not result.ok and result.attempts == 1 and not result.retryable
    assert result.error.startswith("callback_url_forbidden")


def test_a_name_resolving_to_a_local_address_is_refused_at_send_time():
    import ipaddress
    import socket

    name = socket.gethostname()  # not on the name list: only DNS tells where it points
    if ipaddress.ip_address(socket.gethostbyname(name)).is_global:
        pytest.skip(f"this host's name {name!r} resolves to a public address")
    with Receiver() as rx:
        port = rx.url.split(":")[2].split("/")[0]
        url = f"http://{name}:{port}/hook"
        with pytest.raises(webhooks.CallbackForbidden):
            webhooks.check_callback_url(url)  # resolved at submit too
        result = webhooks.deliver(url, b"{}", SECRET, attempts=1, sleep=lambda s: None)
    assert not result.ok and result.error.startswith("callback_url_forbidden")
    assert rx.calls == []


def test_redirects_are_not_followed():
    with Receiver([307]) as rx:
        result = webhooks.deliver(
            rx.url, b"{}", SECRET, attempts=1, sleep=lambda s: None, allow_networks=LOCAL
        )
    assert not result.ok and result.status_code == 307 and len(rx.calls) == 1


@pytest.mark.parametrize("attempt,expected", [(0, 2.0), (1, 4.0), (3, 16.0), (10, 60.0)])
def test_backoff_doubles_and_is_capped(attempt, expected):
    assert webhooks.backoff_delay(attempt, 2.0, 60.0) == expected
