"""Signed preview links: a browser that opens the preview page cannot send an API key header, so
a job's ``preview_url`` carries ``?token=<expires>.<signature>``, an HMAC-SHA256 (key
``Settings.preview_secret``) over the job id and the expiry time. The token opens that job's
preview page and the data the page loads, nothing else, until it expires."""

from __future__ import annotations

import base64
import hashlib
import hmac
import re
import time

from services.common.problems import ApiError
from services.config import Settings

_EXPIRY = re.compile(r"[0-9]{1,12}")


def _signature(secret: str, job_id: str, expires: int) -> str:
    mac = hmac.new(secret.encode(), f"preview:{job_id}:{expires}".encode(), hashlib.sha256)
    return base64.urlsafe_b64encode(mac.digest()).decode().rstrip("=")


def _expiry(text: str) -> int | None:
    """A token's expiry time: 1 to 12 ASCII digits (``str.isdigit`` also takes ``²`` or ``٣``,
    which ``int`` refuses or reads as another number), else None."""
    return int(text) if _EXPIRY.fullmatch(text) else None


def make_token(settings: Settings, job_id: str, now: float | None = None) -> str:
    """A token for ``job_id`` valid ``settings.preview_token_ttl_s`` seconds from ``now``."""
    expires = int(now if now is not None else time.time()) + settings.preview_token_ttl_s
    return f"{expires}.{_signature(settings.preview_secret, job_id, expires)}"


def check_token(settings: Settings, job_id: str, token: str, now: float | None = None) -> None:
    """Accept a token made by ``make_token`` for this job and not expired; else 401
    ``preview_token_invalid`` (malformed, forged or another job's) or ``preview_token_expired``."""
    expires_text, _, signature = token.partition(".")
    expires = _expiry(expires_text)
    if (
        expires is None
        or not signature.isascii()  # compare_digest raises TypeError on other text
        or not hmac.compare_digest(_signature(settings.preview_secret, job_id, expires), signature)
    ):
        raise ApiError(
            401,
            "preview_token_invalid",
            "the preview token is not valid for this job; take preview_url from GET /v1/jobs/{id}",
            field="query.token",
        )
    if expires < (now if now is not None else time.time()):
        raise ApiError(
            401,
            "preview_token_expired",
            "the preview token has expired; GET /v1/jobs/{id} hands out a fresh preview_url",
            field="query.token",
        )
