"""The one settings object every ``cranetwin`` command reads (environment prefix ``CRANETWIN_``).

:class:`Settings` holds what more than one command needs — above all the database every process
of a deployment shares (``CRANETWIN_DATABASE_URL``) — and the ingest daemon's options.
:class:`cranetwin.api.Settings` extends it with the HTTP service's fields, so ``cranetwin serve``,
``cranetwin ingest``, ``cranetwin machines`` and ``cranetwin keys`` all resolve the database the
same way: the ``--db`` option if given, else ``CRANETWIN_DATABASE_URL``, else
``sqlite:///cranetwin.db``. Nothing is read at import time; call :func:`load_settings`.
"""

from __future__ import annotations

from typing import Any, TypeVar

from pydantic import Field, ValidationError
from pydantic_settings import BaseSettings, SettingsConfigDict

from cranetwin.errors import CraneTwinError

DEFAULT_DATABASE_URL = "sqlite:///cranetwin.db"


class SettingsError(CraneTwinError):
    """An environment variable ``CRANETWIN_…`` (or an option) holds an invalid value."""


class Settings(BaseSettings):
    """Configuration shared by every command.

    Every field can be set by an environment variable ``CRANETWIN_<FIELD>`` (upper case), e.g.
    ``CRANETWIN_DATABASE_URL`` or ``CRANETWIN_INGEST_METRICS_BIND``; command-line options
    override the environment.
    """

    model_config = SettingsConfigDict(env_prefix="CRANETWIN_", extra="ignore")

    database_url: str = Field(DEFAULT_DATABASE_URL,
                              description="SQLAlchemy database URL (sqlite:///… or postgresql://…)")
    live_bus_url: str | None = Field(
        None, description="live fan-out between the ingest daemon and the API (memory://, "
                          "postgresql://…, redis://host:port); unset: the live view polls "
                          "the store")
    ingest_bind: str = Field("127.0.0.1:5005", description="UDP HOST:PORT of `cranetwin ingest`")
    ingest_metrics_bind: str = Field(
        "127.0.0.1:9105", description="HOST:PORT of the ingest daemon's Prometheus /metrics "
                                      "(HTTP); 0 = not served")
    ingest_queue_max: int = Field(50_000, ge=1,
                                  description="datagrams waiting for the writer at most")
    ingest_batch_max: int = Field(1000, ge=1, description="blocks written per transaction at most")
    ingest_batch_wait_s: float = Field(0.05, ge=0, le=10,
                                       description="time the writer gathers a batch [s]")
    ingest_max_past_s: float = Field(
        400 * 86400.0, gt=0, description="oldest sample time accepted, before server time [s]")
    ingest_max_future_s: float = Field(
        300.0, ge=0, description="newest sample time accepted, after server time [s]")
    ingest_range_margin: float = Field(
        0.1, ge=0, description="share of each channel's [min, max] span a value may lie beyond it")
    ingest_busy_timeout_s: float = Field(
        3.0, gt=0, description="SQLite: how long the daemon's write waits for another "
                               "process's lock before it counts as an outage (retried) [s]")
    ingest_shutdown_timeout_s: float = Field(
        60.0, gt=0, description="longest flush of queued datagrams on SIGTERM while the database "
                                "is writable [s]")


S = TypeVar("S", bound=Settings)


def load_settings(cls: type[S], **overrides: Any) -> S:
    """Read ``cls`` (:class:`Settings` or a subclass) from the environment, then apply
    ``overrides`` (None values are skipped, so unset command-line options keep the environment's
    value).

    Raises:
        SettingsError: An environment variable or override is invalid (one line per field).
    """
    given = {k: v for k, v in overrides.items() if v is not None}
    try:
        return cls(**given)
    except ValidationError as exc:
        problems = "; ".join(
            f"{'CRANETWIN_' + '.'.join(str(x) for x in e['loc']).upper()}: {e['msg']}"
            for e in exc.errors())
        raise SettingsError(f"invalid setting: {problems}") from None
