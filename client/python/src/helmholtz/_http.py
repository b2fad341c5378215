"""REST plumbing on the standard library (urllib): bearer token, problem+json errors, retries of
idempotent requests."""

from __future__ import annotations

import email.message
import http.client
import json
import socket
import ssl
import time
import urllib.error
import urllib.parse
import urllib.request
from dataclasses import dataclass
from typing import Any, Iterator, Mapping, Optional

from .errors import ApiError, ServerUnreachable
from .retry import RetryPolicy

PROBLEM_JSON = "application/problem+json"

# Statuses worth another try for an idempotent request (the server or a proxy in front of it
# is restarting, overloaded, or rate limiting).
_TRANSIENT_STATUS = {429, 502, 503, 504}


@dataclass
class Response:
    status: int
    headers: email.message.Message
    body: bytes

    def json(self) -> Any:
        return json.loads(self.body.decode("utf-8"))


class _NoRedirect(urllib.request.HTTPRedirectHandler):
    def redirect_request(self, req, fp, code, msg, headers, newurl):  # type: ignore[no-untyped-def]
        return None


class Http:
    """Requests to one server with one token."""

    def __init__(
        self,
        base_url: str,
        token: Optional[str],
        policy: RetryPolicy,
        ssl_context: Optional[ssl.SSLContext] = None,
    ):
        self.base_url = base_url.rstrip("/")
        self.token = token
        self.policy = policy
        handlers: list[Any] = [_NoRedirect()]
        if ssl_context is not None:
            handlers.append(urllib.request.HTTPSHandler(context=ssl_context))
        self._opener = urllib.request.build_opener(*handlers)

    def url(self, path: str, query: Optional[Mapping[str, Any]] = None) -> str:
        url = self.base_url + path
        if query:
            items = {k: v for k, v in query.items() if v is not None}
            if items:
                url += "?" + urllib.parse.urlencode(items)
        return url

    def request(
        self,
        method: str,
        path: str,
        *,
        query: Optional[Mapping[str, Any]] = None,
        body: Optional[bytes] = None,
        content_type: Optional[str] = None,
        json_body: Any = None,
        retry: bool = True,
        auth: bool = True,
    ) -> Response:
        """One request; retried per the policy when ``retry`` (idempotent requests only).

        Raises:
            ApiError: the server answered with an error status (problem+json as attributes).
            ServerUnreachable: no answer (after retrying, when ``retry``).
        """
        url = self.url(path, query)
        if json_body is not None:
            body = json.dumps(json_body).encode("utf-8")
            content_type = "application/json"
        headers = {"Accept": "application/json, application/octet-stream, */*"}
        if auth and self.token:
            headers["Authorization"] = f"Bearer {self.token}"
        if content_type:
            headers["Content-Type"] = content_type
        started = time.monotonic()
        attempt = 0
        while True:
            try:
                return self._once(method, url, headers, body)
            except (ApiError, ServerUnreachable) as e:
                transient = isinstance(e, ServerUnreachable) or e.status in _TRANSIENT_STATUS
                elapsed = time.monotonic() - started
                if not retry or not transient or elapsed >= self.policy.retry_for:
                    raise
                delay = self.policy.backoff.delay(attempt)
                if isinstance(e, ApiError) and e.retry_after is not None:
                    delay = max(delay, e.retry_after)
                time.sleep(min(delay, max(0.0, self.policy.retry_for - elapsed)))
                attempt += 1

    def events(
        self, path: str, *, query: Optional[Mapping[str, Any]] = None
    ) -> Iterator[tuple[str, Any]]:
        """``GET path`` as server-sent events: yields ``(event name, JSON data)`` until the
        server ends the stream (comment lines, which keep a quiet stream open, are skipped).
        Closing the generator closes the connection.

        Raises:
            ApiError: the server refused the request (problem+json as attributes).
            ServerUnreachable: no answer.
        """
        url = self.url(path, query)
        headers = {"Accept": "text/event-stream"}
        if self.token:
            headers["Authorization"] = f"Bearer {self.token}"
        req = urllib.request.Request(url, headers=headers, method="GET")
        try:
            # No read timeout: a stream may be quiet between events for as long as the rows
            # take to come (the server sends a comment line every 15 s).
            r = self._opener.open(req, timeout=None)
        except urllib.error.HTTPError as e:
            data = e.read() if e.fp is not None else b""
            raise _api_error("GET", url, e.code, e.headers, data) from None
        except (urllib.error.URLError, ConnectionError, socket.timeout, http.client.HTTPException, OSError) as e:
            reason = getattr(e, "reason", None) or e
            raise ServerUnreachable("GET", url, str(reason)) from None
        with r:
            name, data = "message", []
            for raw in r:
                line = raw.decode("utf-8").rstrip("\r\n")
                if not line:
                    if data:
                        yield name, json.loads("\n".join(data))
                    name, data = "message", []
                elif line.startswith(":"):
                    continue
                elif line.startswith("event:"):
                    name = line[6:].strip()
                elif line.startswith("data:"):
                    data.append(line[5:].removeprefix(" "))

    def _once(
        self, method: str, url: str, headers: Mapping[str, str], body: Optional[bytes]
    ) -> Response:
        req = urllib.request.Request(url, data=body, headers=dict(headers), method=method)
        try:
            with self._opener.open(req, timeout=self.policy.http_timeout) as r:
                return Response(r.status, r.headers, r.read())
        except urllib.error.HTTPError as e:
            data = e.read() if e.fp is not None else b""
            raise _api_error(method, url, e.code, e.headers, data) from None
        except (urllib.error.URLError, ConnectionError, socket.timeout, http.client.HTTPException, OSError) as e:
            reason = getattr(e, "reason", None) or e
            raise ServerUnreachable(method, url, str(reason)) from None


def _api_error(
    method: str, url: str, status: int, headers: email.message.Message, data: bytes
) -> ApiError:
    ctype = (headers.get("Content-Type") or "").split(";")[0].strip().lower()
    text = data.decode("utf-8", errors="replace")
    problem: dict[str, Any] = {}
    if ctype in (PROBLEM_JSON, "application/json"):
        try:
            parsed = json.loads(text)
            if isinstance(parsed, dict):
                problem = parsed
        except ValueError:
            pass
    err = ApiError(method, url, status, problem, text if not problem else "")
    retry_after = headers.get("Retry-After")
    err.retry_after = float(retry_after) if retry_after and retry_after.isdigit() else None
    return err
