"""Errors of the service layer: what a caller asked for does not exist, conflicts, or is unusable.

Raised by :mod:`cranetwin.service` and translated once at the edges (the HTTP API in
:mod:`cranetwin.api.errors`, the CLI as an exit message)::

    CraneTwinError
    └── ServiceError            a request the service cannot answer (title + detail)
        ├── NotFoundError       unknown machine, page past the last            (HTTP 404)
        ├── ConflictError       machine id or wire id already registered       (HTTP 409)
        ├── InvalidRequestError bad parameter, range or page too large, unknown
        │                       channel, unknown model, invalid time           (HTTP 422)
        └── BusyError           the heavy work queue is full; retry later      (HTTP 503)

Replay failures keep their own classes (:class:`~cranetwin.errors.TwinError`,
:class:`~cranetwin.errors.SignalError`, …), storage outages :class:`~cranetwin.errors.StorageError`.
"""

from __future__ import annotations

from cranetwin.errors import CraneTwinError


class ServiceError(CraneTwinError):
    """A request the service cannot answer.

    Attributes:
        title: Short summary (``"Unknown machine"``).
        detail: What was wrong and what was expected.
    """

    def __init__(self, title: str, detail: str) -> None:
        self.title = title
        self.detail = detail
        super().__init__(f"{title}: {detail}")


class NotFoundError(ServiceError):
    """The machine (or the page) asked for does not exist."""


class ConflictError(ServiceError):
    """The machine id or wire id to register is already taken."""


class InvalidRequestError(ServiceError):
    """A parameter is invalid: range, limit, channel, time, model."""


class BusyError(ServiceError):
    """Heavy work (replays, reports, exports) is refused because its queue is full.

    Attributes:
        retry_after_s: When a retry may succeed [s].
    """

    def __init__(self, title: str, detail: str, retry_after_s: float = 1.0) -> None:
        super().__init__(title, detail)
        self.retry_after_s = retry_after_s
