"""Completion webhooks: a signed POST to the job's ``callback_url``, retried with backoff.

Wire format (documented in docs/tasks.md):

- body: JSON ``{"event": "job.succeeded", "job": {...job status...}, "sent_at": ISO-8601}``,
  serialised once; the exact bytes sent are the bytes signed;
- ``X-DanceGraph-Signature: sha256=<hex HMAC-SHA256 of the body with the webhook secret>``;
- ``X-DanceGraph-Event`` (the event name) and ``X-DanceGraph-Delivery`` (one id per delivery,
  the same across its retries, so a receiver can drop duplicates).

A delivery succeeds on any 2xx answer. Connection errors, timeouts, 408, 429 and 5xx are
retried with exponential backoff (``base_delay · 2^n``, capped at ``max_delay``) up to
``attempts`` tries in all; any other status is final (the receiver said no).

Targets (no internal port scanner): a ``callback_url`` must name a public address. Loopback,
private, link-local (cloud metadata 169.254.169.254), carrier-grade NAT, multicast and reserved
addresses, and metadata host names, are refused at submit (``check_callback_url``: 422
``callback_url_forbidden``; a host name is resolved and every address it names checked) and
again at send time (``resolve_target``), and the POST goes to the address that was checked (no
second lookup to rebind; the Host header and TLS server name keep the name). An IPv6 address
that carries an IPv4 one — IPv4-mapped ``::ffff:a.b.c.d``, IPv4-compatible ``::a.b.c.d``, NAT64
``64:ff9b::/96``, 6to4 ``2002::/16``, Teredo ``2001::/32`` (server and de-obfuscated client) —
is judged by the IPv4 addresses it carries; the local-use NAT64 prefix ``64:ff9b:1::/48`` is
refused. Redirects are never followed. ``Settings.webhook_allow_networks`` lists networks
allowed anyway (a local test receiver). What a receiver answered is recorded as its status code
only, never its body.
"""

from __future__ import annotations

import hashlib
import hmac
import ipaddress
import json
import logging
import socket
import time
import uuid
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime
from typing import Any
from urllib.parse import urlsplit

import httpx

from dancegraph.errors import DanceGraphError

log = logging.getLogger("dancegraph.webhooks")

SIGNATURE_HEADER = "X-DanceGraph-Signature"
EVENT_HEADER = "X-DanceGraph-Event"
DELIVERY_HEADER = "X-DanceGraph-Delivery"
_RETRY_STATUSES = {408, 429}
# Names that reach a cloud's instance metadata or this very host, whatever DNS says.
_FORBIDDEN_NAMES = {
    "localhost",
    "metadata",
    "metadata.google.internal",
    "metadata.goog",
    "instance-data",
    "instance-data.ec2.internal",
}
_FORBIDDEN_SUFFIXES = (".localhost", ".internal", ".local")
_NAT64 = ipaddress.ip_network("64:ff9b::/96")  # RFC 6052: the IPv4 address in the last 32 bits
_NAT64_LOCAL = ipaddress.ip_network("64:ff9b:1::/48")  # RFC 8215: local-use translation

IpAddress = ipaddress.IPv4Address | ipaddress.IPv6Address


class CallbackForbidden(DanceGraphError):
    """A callback_url that points at a non-public address (SSRF guard)."""

    code = "callback_url_forbidden"
    status = 422


def embedded_ipv4(ip: ipaddress.IPv6Address) -> list[ipaddress.IPv4Address]:
    """The IPv4 addresses an IPv6 address reaches through: IPv4-mapped, IPv4-compatible
    (``::a.b.c.d``, also ``::`` and ``::1``), NAT64 well-known prefix, 6to4, Teredo (server and
    client); empty for a plain IPv6 address."""
    value = int(ip)
    if ip.ipv4_mapped is not None:
        return [ip.ipv4_mapped]
    if value >> 32 == 0 or ip in _NAT64:
        return [ipaddress.IPv4Address(value & 0xFFFFFFFF)]
    if ip.sixtofour is not None:
        return [ip.sixtofour]
    return list(ip.teredo) if ip.teredo is not None else []


def _allowed(ip: IpAddress, allow: Sequence[str]) -> bool:
    """Whether a callback may go to ``ip``: in an allowed network, else a public unicast address
    (an IPv6 address carrying IPv4 ones: every one of those public)."""
    if any(ip in ipaddress.ip_network(net, strict=False) for net in allow):
        return True
    if isinstance(ip, ipaddress.IPv6Address):
        if ip in _NAT64_LOCAL:
            return False
        carried = embedded_ipv4(ip)
        if carried:
            return all(_allowed(v4, allow) for v4 in carried)
    return ip.is_global and not ip.is_multicast


def _host(url: str) -> str:
    parts = urlsplit(url)
    if parts.scheme not in ("http", "https") or not parts.hostname:
        raise CallbackForbidden(
            "callback_url must be an http(s) URL with a host", field="spec.callback_url"
        )
    return parts.hostname.rstrip(".").lower()


def check_callback_url(url: str, allow: Sequence[str] = ()) -> None:
    """Refuse (``CallbackForbidden``, 422 ``callback_url_forbidden``) a callback URL whose host
    is a non-public IP literal (in any IPv6 form that carries a non-public IPv4 address), a
    local/metadata host name, or a name that resolves to a non-public address. A name that does
    not resolve now passes: the send-time check (``resolve_target``) decides."""
    try:
        resolve_target(url, allow)
    except ConnectionError:
        pass


def resolve_target(url: str, allow: Sequence[str] = ()) -> IpAddress:
    """The one address to POST to: ``url``'s host (an IP literal, or a name resolved once),
    every address it names checked.

    Raises ``CallbackForbidden`` when any address is not public (a name that resolves to one
    private address among public ones is refused too), ``ConnectionError`` when the name does
    not resolve.
    """
    parts = urlsplit(url)
    host = _host(url)
    try:
        addresses: list[IpAddress] = [ipaddress.ip_address(host.strip("[]"))]
    except ValueError:
        if host in _FORBIDDEN_NAMES or host.endswith(_FORBIDDEN_SUFFIXES):
            raise CallbackForbidden(
                f"callback_url host {host!r} is a local or metadata name",
                field="spec.callback_url",
            ) from None
        addresses = _resolve(host, parts.port or (443 if parts.scheme == "https" else 80))
    bad = [ip for ip in addresses if not _allowed(ip, allow)]
    if bad:
        raise CallbackForbidden(
            f"callback_url host {host!r} is or resolves to a non-public address ({bad[0]})",
            field="spec.callback_url",
        )
    return addresses[0]


def _resolve(host: str, port: int) -> list[IpAddress]:
    """Every address ``host`` resolves to; ``ConnectionError`` when it resolves to none."""
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
    except (OSError, ValueError) as exc:  # ValueError: IDNA or NUL in the name
        raise ConnectionError(f"callback host {host!r} does not resolve") from exc
    addresses = [ipaddress.ip_address(str(info[4][0]).split("%")[0]) for info in infos]
    if not addresses:
        raise ConnectionError(f"callback host {host!r} does not resolve")
    return addresses


def _pinned(url: str, ip: IpAddress) -> tuple[str, dict, dict]:
    """``url`` with its host replaced by the checked ``ip``; the Host header and TLS server
    name keep the original host, so virtual hosts and certificates work as before."""
    parts = urlsplit(url)
    host = parts.hostname or ""
    port = f":{parts.port}" if parts.port else ""
    netloc = (f"[{ip}]" if ip.version == 6 else str(ip)) + port
    target = parts._replace(netloc=netloc).geturl()
    host_header = (f"[{host}]" if ":" in host else host) + port
    extensions = {"sni_hostname": host} if parts.scheme == "https" else {}
    return target, {"Host": host_header}, extensions


def sign(body: bytes, secret: str) -> str:
    """The signature header value for ``body``: ``sha256=<hex digest>``."""
    digest = hmac.new(secret.encode("utf-8"), body, hashlib.sha256).hexdigest()
    return f"sha256={digest}"


def verify(body: bytes, signature: str, secret: str) -> bool:
    """True when ``signature`` (the header value) matches ``body`` under ``secret``."""
    return hmac.compare_digest(sign(body, secret), signature or "")


def encode_payload(event: str, job: dict) -> bytes:
    """The body bytes of one webhook (stable key order, UTF-8 JSON)."""
    body = {"event": event, "job": job, "sent_at": datetime.now(UTC).isoformat()}
    return json.dumps(body, sort_keys=True, separators=(",", ":"), default=str).encode("utf-8")


def backoff_delay(attempt: int, base_delay: float, max_delay: float) -> float:
    """Seconds to wait after failed try number ``attempt`` (0-based): base·2^attempt, capped."""
    return min(max_delay, base_delay * (2**attempt))


@dataclass
class DeliveryResult:
    """What happened to one delivery: ``ok``, the tries made, and the last status or error."""

    ok: bool
    attempts: int
    status_code: int | None = None
    error: str | None = None
    delivery_id: str = ""
    retryable: bool = False  # the last failure was transient (a later try may succeed)
    history: list[str] = field(default_factory=list)


def _retryable(status: int) -> bool:
    return status >= 500 or status in _RETRY_STATUSES


def deliver(
    url: str,
    body: bytes,
    secret: str,
    *,
    event: str = "job.succeeded",
    attempts: int = 5,
    base_delay: float = 1.0,
    max_delay: float = 60.0,
    timeout: float = 10.0,
    delivery_id: str | None = None,
    sleep: Callable[[float], None] = time.sleep,
    allow_networks: Sequence[str] = (),
) -> DeliveryResult:
    """POST ``body`` to ``url`` signed with ``secret``; retry transient failures, bounded.

    The host is resolved and checked before every try (``resolve_target``); a forbidden target
    is a final failure ``callback_url_forbidden``. Never raises for delivery problems: the
    outcome is in the returned DeliveryResult (a job's result does not depend on whether its
    webhook got through).
    """
    delivery_id = delivery_id or str(uuid.uuid4())
    headers = {
        "Content-Type": "application/json",
        "User-Agent": "dancegraph-webhook/1",
        SIGNATURE_HEADER: sign(body, secret),
        EVENT_HEADER: event,
        DELIVERY_HEADER: delivery_id,
    }
    result = DeliveryResult(ok=False, attempts=0, delivery_id=delivery_id)
    with httpx.Client(timeout=timeout, follow_redirects=False) as client:
        for attempt in range(max(1, attempts)):
            result.attempts = attempt + 1
            try:
                target, extra, extensions = _pinned(url, resolve_target(url, allow_networks))
                response = client.post(
                    target, content=body, headers={**headers, **extra}, extensions=extensions
                )
            except CallbackForbidden as exc:
                result.status_code, result.error = None, f"{exc.code}: {exc.message}"
                result.retryable = False
                result.history.append(result.error)
                log.warning("webhook target refused", extra={"url": url, "error": exc.message})
                break
            except (httpx.HTTPError, ConnectionError) as exc:
                # the kind of failure only: the exception text may echo internal details
                result.status_code, result.error = None, f"connection failed ({type(exc).__name__})"
                retry = True
            else:
                result.status_code, result.error = response.status_code, None
                if 200 <= response.status_code < 300:
                    result.ok, result.retryable = True, False
                    result.history.append(str(response.status_code))
                    break
                result.error = f"HTTP {response.status_code}"
                retry = _retryable(response.status_code)
            result.retryable = retry
            result.history.append(result.error or "")
            log.warning(
                "webhook attempt failed",
                extra={"url": url, "attempt": attempt + 1, "error": result.error, "retry": retry},
            )
            if not retry or attempt + 1 >= attempts:
                break
            sleep(backoff_delay(attempt, base_delay, max_delay))
    return result


# --- jobs -----------------------------------------------------------------------------------


def job_payload(job) -> dict:
    """The ``job`` object of a webhook body: the job's final state, as GET /v1/jobs/{id} shows it."""
    result = job.result or {}
    alternatives = [
        {"index": k, "cost": alt.get("cost")}
        for k, alt in enumerate(result.get("alternatives", []))
    ]
    out = {
        "id": job.id,
        "status": job.status,
        "stage": job.stage,
        "progress": job.progress,
        "batch_id": job.batch_id,
        "alternatives": alternatives,
        "files": result.get("files", []),
        "url": f"/v1/jobs/{job.id}",
        "finished_at": job.finished_at.isoformat() if job.finished_at else None,
    }
    if job.error_code:
        out["error"] = {
            "code": job.error_code,
            "message": job.error_message,
            "field": job.error_field,
        }
    return out


def deliver_job_webhook(
    job_id: str, *, delivery_id: str, final_attempt: bool
) -> DeliveryResult | None:
    """POST one try of a job's completion webhook and record it on the job row.

    Returns None when there is nothing to send (no callback URL, job not final, or already
    delivered/failed). ``final_attempt``: a failure now marks the webhook ``failed`` for good.
    """
    from sqlalchemy import update

    from services.config import get_settings
    from services.db import session_scope
    from services.models import (
        FINAL_STATUSES,
        WEBHOOK_DELIVERED,
        WEBHOOK_FAILED,
        WEBHOOK_PENDING,
        Job,
        utcnow,
    )

    settings = get_settings()
    with session_scope() as session:
        job = session.get(Job, job_id)
        if job is None or not job.callback_url or job.status not in FINAL_STATUSES:
            return None
        if job.webhook_status != WEBHOOK_PENDING:
            return None
        url, body = job.callback_url, encode_payload(f"job.{job.status}", job_payload(job))
        event = f"job.{job.status}"
    result = deliver(
        url,
        body,
        settings.webhook_secret,
        event=event,
        attempts=1,
        timeout=settings.webhook_timeout_s,
        delivery_id=delivery_id,
        allow_networks=settings.webhook_allow_networks,
    )
    values: dict[str, Any] = {
        "webhook_attempts": Job.webhook_attempts + 1,
        "webhook_last_error": result.error,
    }
    if result.ok:
        values.update(webhook_status=WEBHOOK_DELIVERED, webhook_delivered_at=utcnow())
    elif final_attempt or not result.retryable:
        values.update(webhook_status=WEBHOOK_FAILED)
    with session_scope() as session:
        session.execute(
            update(Job)
            .where(Job.id == job_id, Job.webhook_status == WEBHOOK_PENDING)
            .values(**values)
            .execution_options(synchronize_session=False)
        )
    log.info(
        "webhook attempt",
        extra={
            "job_id": job_id,
            "ok": result.ok,
            "status_code": result.status_code,
            "error": result.error,
        },
    )
    return result
