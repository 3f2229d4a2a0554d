"""The one settings object every ``cranetwin`` command reads (environment prefix ``CRANETWIN_``).

:class:`Settings` holds every option of every process of a deployment: the database they share
(``CRANETWIN_DATABASE_URL``), the ingest daemon's, the HTTP service's, the twin worker's, the
web front end's and the demo's. ``cranetwin serve``, ``cranetwin worker``, ``cranetwin ingest``,
``cranetwin machines``, ``cranetwin keys``, ``cranetwin report`` and ``cranetwin fleetdemo`` all
build it once at start with :func:`load_settings` (command-line options override the
environment), so they resolve the database the same way: the ``--db`` option if given, else
``CRANETWIN_DATABASE_URL``, else ``sqlite:///cranetwin.db``. Nothing is read at import time.

Secrets (machine HMAC keys) are not settings: they come from files or the environment variable
the sending command documents, never from argv.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Literal, TypeVar

from pydantic import Field, ValidationError
from pydantic_settings import BaseSettings, SettingsConfigDict

from cranetwin.errors import CraneTwinError

DEFAULT_DATABASE_URL = "sqlite:///cranetwin.db"


class SettingsError(CraneTwinError):
    """An environment variable ``CRANETWIN_…`` (or an option) holds an invalid value."""


class Settings(BaseSettings):
    """Configuration of every command (see the module docstring).

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
    # -- fleet bus (NATS JetStream; docs/BUS.md) --------------------------------------------
    bus_url: str | None = Field(
        None, description="NATS server of the fleet bus (nats://host:port); set: `cranetwin "
                          "ingest` publishes blocks to JetStream instead of writing them to the "
                          "database, and `cranetwin store-writer` stores them")
    bus_stream: str = Field("CRANETWIN_BLOCKS", description="JetStream stream of the blocks")
    bus_prefix: str = Field("cranetwin.blocks", description="subject prefix of the blocks")
    bus_partitions: int = Field(16, ge=1, le=4096,
                                description="partitions of the fleet bus (machines by hash)")
    bus_duplicate_window_s: float = Field(
        120.0, gt=0, description="JetStream deduplication window of block messages [s]")
    bus_max_msgs: int = Field(2_000_000, ge=1,
                              description="stream size limit [blocks]; full: publishes refused")
    bus_publish_timeout_s: float = Field(
        2.0, gt=0, description="longest wait for a batch's PubAcks before it is retried [s]")
    bus_ack_wait_s: float = Field(
        30.0, gt=0, description="a block not acked by its storage writer within this time is "
                                "delivered again [s]")
    store_writer_metrics_bind: str = Field(
        "0", description="HOST:PORT of `cranetwin store-writer`'s Prometheus /metrics (HTTP); "
                         "0 = not served")
    # -- MQTT ingest adapter (``cranetwin mqtt-ingest``; docs/INGEST.md) ------------------------
    mqtt_broker_url: str | None = Field(
        None, description="MQTT broker of `cranetwin mqtt-ingest`: mqtt://[user@]host:port or "
                          "mqtts://… (Mosquitto, or NATS's MQTT listener); no password in it")
    mqtt_group: str = Field("cranetwin", min_length=1,
                            description="Sparkplug B group id whose DDATA is stored")
    mqtt_client_id: str = Field(
        "cranetwin-mqtt-ingest", min_length=1,
        description="MQTT client id of the adapter: names its persistent session (one adapter "
                    "per id)")
    mqtt_username: str | None = Field(None, description="MQTT user name (else from the URL)")
    mqtt_password: str = Field(
        "", repr=False, description="MQTT password (environment only; never logged)")
    mqtt_protocol: Literal["5", "3.1.1"] = Field(
        "5", description="MQTT version of the adapter: 5 (session expiry, Receive Maximum) or "
                         "3.1.1 (NATS's MQTT listener speaks 3.1.1 only)")
    mqtt_session_expiry_s: int = Field(
        7 * 86400, ge=0, description="how long the broker keeps the adapter's session and its "
                                     "unacknowledged messages while the adapter is away [s]")
    mqtt_receive_maximum: int = Field(
        1000, ge=1, le=65535, description="unacknowledged messages the broker may send the "
                                          "adapter at once (MQTT 5 Receive Maximum)")
    ingest_bind: str = Field("127.0.0.1:5005", description="UDP HOST:PORT of `cranetwin ingest`")
    ingest_metrics_bind: str = Field(
        "127.0.0.1:9105", description="HOST:PORT of the ingest daemon's Prometheus /metrics "
                                      "(HTTP); 0 = not served")
    ingest_queue_max: int = Field(50_000, ge=1,
                                  description="datagrams accepted, not yet decoded, at most")
    ingest_batch_max: int = Field(
        1000, ge=1, description="datagrams decoded together, blocks per transaction at most")
    ingest_batch_wait_s: float = Field(
        0.05, ge=0, le=10, description="time a batch is gathered after its first datagram [s]")
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

    # -- HTTP service (``cranetwin serve``) ------------------------------------------------------
    host: str = Field("127.0.0.1", description="bind address of `cranetwin serve`")
    port: int = Field(8000, ge=0, le=65535, description="TCP port of `cranetwin serve`")
    max_history_range_s: float = Field(
        400 * 86400.0, gt=0, description="longest range of one history/events/find query [s]")
    max_history_points: int = Field(10_000, ge=10, description="largest max_points of history")
    max_twin_range_s: float = Field(120.0, gt=0, description="longest window of one twin query [s]")
    max_twin_points: int = Field(12_000, ge=10, description="most output samples of one twin query")
    max_twin_rate_hz: float = Field(1000.0, gt=0, description="highest twin output rate [Hz]")
    twin_margin_s: float = Field(
        2.0, ge=0, description="extra samples read either side of a twin window [s] (spline ends)")
    max_analytics_range_s: float = Field(
        3600.0, gt=0, description="most time replayed per analytics/report request [s]: the "
        "minutes the worker has not processed yet (stored minutes are merged, not replayed)")
    max_samples_limit: int = Field(10_000, ge=1, description="most samples per samples page")
    nominal_rate_hz: float = Field(100.0, gt=0, description="expected sensor sample rate [Hz]")
    twin_cache_entries: int = Field(64, ge=0, description="replay results kept in the LRU cache")
    twin_cache_bytes: int = Field(
        256 * 2**20, ge=0, description="most bytes the replay cache holds (its results' bytes; "
                                       "least recently used evicted first) [B]")
    # -- service limits (``cranetwin.api.limits``, ``cranetwin.service.heavy``) ----------------
    rate_limit: bool = Field(True, description="rate-limit every key (token bucket per key)")
    rate_viewer_per_s: float = Field(
        20.0, gt=0, description="tokens a viewer key gets back per second (a cheap request "
                                "costs 1, a heavy one rate_heavy_cost)")
    rate_viewer_burst: float = Field(200.0, ge=1, description="bucket size of a viewer key")
    rate_fleet_per_s: float = Field(40.0, gt=0, description="tokens per second of a fleet key")
    rate_fleet_burst: float = Field(400.0, ge=1, description="bucket size of a fleet key")
    rate_admin_per_s: float = Field(100.0, gt=0, description="tokens per second of an admin key")
    rate_admin_burst: float = Field(1000.0, ge=1, description="bucket size of an admin key")
    rate_heavy_cost: float = Field(
        10.0, ge=1, description="tokens of a heavy request (twin replay, analytics, report, "
                                "export, export.html)")
    rate_limit_delay_s: float = Field(
        1.0, ge=0, le=60, description="a refused request is answered after min(Retry-After, "
                                      "this) [s], costing no CPU meanwhile: a client that "
                                      "ignores Retry-After cannot make the server refuse "
                                      "hundreds of requests a second")
    heavy_workers: int = Field(
        2, ge=1, le=64, description="threads that run heavy work (replays, reports, exports), "
                                    "apart from the threads serving cheap requests")
    heavy_processes: int | None = Field(
        None, ge=0, le=64, description="worker processes that run the twin replays (their own "
                                       "interpreters: cheap requests never wait for a replay's "
                                       "interpreter lock), started in the background (replays "
                                       "run on the heavy threads until they are up); 0 = "
                                       "replays on the heavy threads; unset: 1, or 0 with "
                                       "worker_in_process (the embedded demo)")
    heavy_queue: int = Field(
        8, ge=0, le=10_000, description="heavy requests that may wait for a heavy thread; "
                                        "beyond: 503 with Retry-After")
    live_rate_hz: float = Field(25.0, ge=1, le=50, description="live websocket frames per second")
    live_offline_s: float = Field(
        300.0, gt=0, description="a machine not seen for this long is 'offline' [s]")
    live_idle_s: float = Field(
        5.0, gt=0, description="a machine not seen for this long is 'idle' [s]")
    warm_up: bool = Field(
        True, description="load the twin's compiled kernels and the 3D scene code before "
                          "serving (fast first machine page)")
    web_dir: Path | None = Field(
        None, description="folder of the web front end's files (default: web/ of the "
                          "repository next to the package)")

    # -- twin worker (``cranetwin worker``; in ``cranetwin serve`` only when asked) --------------
    worker_in_process: bool = Field(
        False, description="run the twin worker inside `cranetwin serve` (the embedded demo); "
                           "otherwise it runs as its own process, `cranetwin worker`")
    worker_window_s: float = Field(60.0, gt=0, description="twin worker window [s]")
    worker_interval_s: float = Field(1.0, gt=0, description="twin worker poll period [s]")
    worker_rollup_s: float = Field(
        30.0, ge=0, description="least time between two roll-ups of the raw 1-min summaries "
                                "by the twin worker [s]; 0 = never (the ingest daemon or the "
                                "storage writers roll up, as in the distributed deployment)")
    worker_threads: int = Field(
        1, ge=1, le=32, description="machines a twin worker process replays at once (threads: "
                                    "one machine's database waits overlap another's work)")
    worker_settle_s: float = Field(
        2.0, ge=0, description="a window is processed once samples this much past its end exist")
    worker_metrics_bind: str = Field(
        "0", description="HOST:PORT of `cranetwin worker`'s Prometheus /metrics (HTTP); "
                         "0 = not served")
    worker_quiet_s: float = Field(
        60.0, gt=0, description="a machine whose newest sample has not changed for this long "
                                "gets its last window processed without samples past it [s]")
    worker_partitions: str | None = Field(
        None, description="machine partitions `cranetwin worker` owns: auto, all, I/P or I,J,… "
                          "(with worker_partition_count); unset: every machine, no locks")
    worker_partition_count: int = Field(
        16, ge=1, le=65536, description="number of machine partitions P of the twin workers")

    # -- time partitions of raw samples on PostgreSQL (``cranetwin.storage.partitions``) ------
    storage_partition_interval: Literal["day", "week", "month"] = Field(
        "month", description="range of one time partition of sample_blocks (new partitions)")
    storage_partitions_ahead: int = Field(
        2, ge=0, le=366, description="partitions the twin worker creates ahead of the current")
    storage_retention_days: float = Field(
        0.0, ge=0, description="drop raw-sample partitions older than this, once processed "
                               "by the twin worker [days]; 0 = keep forever")
    storage_maintenance_interval_s: float = Field(
        3600.0, gt=0, description="how often the twin worker makes partitions ahead and "
                                  "applies retention [s]")
    # -- machines sharded across databases (``cranetwin.storage.shards``; docs/SCALING.md) ----
    storage_shards: dict[str, str] | None = Field(
        None, description="partition map of the shards, JSON: {\"0-7\": \"postgresql://a/…\", "
                          "\"8-15\": \"postgresql://b/…\"}; each machine partition (0 … "
                          "storage_shard_partitions − 1) in exactly one range; set: "
                          "database_url is not used")
    storage_shard_partitions: int = Field(
        16, ge=1, le=65536, description="machine partitions P of the shard map (keep it equal "
                                        "to bus_partitions and worker_partition_count)")
    summary_interval_s: float = Field(1.0, gt=0, description="derived summary interval [s]")
    payload_lift_threshold_kg: float = Field(
        50.0, ge=0, description="payload above which the crane is holding a load (load count) [kg]")

    # -- alarms (``cranetwin.service.alarms``) ----------------------------------------------------
    alarm_offline_s: float = Field(
        120.0, gt=0, description="a machine without a new sample for this long gets a "
                                 "machine_offline event [s]")
    alarm_gap_s: float = Field(
        30.0, gt=0, description="a silence this long inside a machine's stream is a data_gap "
                                "event when the stream resumes [s]")
    alarm_check_interval_s: float = Field(
        5.0, ge=0, description="how often the API checks for offline machines and data gaps "
                               "[s]; 0 = never")

    # -- browser sign-in (``POST /api/v1/session``) --------------------------------------------
    session_ttl_s: float = Field(
        12 * 3600.0, gt=0, le=30 * 86400.0,
        description="lifetime of a browser session cookie after sign-in [s]")
    session_secret: str = Field(
        "", description="extra secret mixed into the session cookies' signatures (the same on "
                        "every API process); empty: signed with the API key's stored hash only")

    # -- machine side (``cranetwin send``) -----------------------------------------------------
    state_dir: Path | None = Field(
        None, description="folder of `cranetwin send`'s durable journals (<state_dir>/send); "
                          "default: $XDG_STATE_HOME/cranetwin, else ~/.local/state/cranetwin")

    # -- the one-command demo (``cranetwin fleetdemo``) ------------------------------------------
    demo_logs: Path | None = Field(
        None, description="folder of the demo's child-process logs, scenario and secret files "
                          "(default: cranetwin-demo-<uid> in the temporary folder)")

    # -- webhook notification of new alarms (``cranetwin.service.webhooks``) -------------------
    alarm_webhook_url: str = Field(
        "", description="URL that receives an HMAC-signed JSON POST for every new event of "
                        "alarm_webhook_severity and above; empty = no webhook")
    alarm_webhook_secret: str = Field(
        "", description="HMAC-SHA256 key of the X-Cranetwin-Signature header (environment "
                        "only; never logged); required with alarm_webhook_url")
    alarm_webhook_severity: Literal["info", "warning", "critical"] = Field(
        "critical", description="lowest severity sent to the webhook")
    alarm_webhook_retries: int = Field(
        5, ge=0, le=20, description="retries of a failed delivery (connection error, timeout, "
                                    "HTTP 429 or 5xx), after 1, 2, 4 … × the backoff")
    alarm_webhook_backoff_s: float = Field(
        1.0, gt=0, le=60, description="first retry delay of a webhook delivery [s]")
    alarm_webhook_timeout_s: float = Field(
        5.0, gt=0, le=60, description="timeout of one webhook request [s]")

    @property
    def replay_processes(self) -> int:
        """Worker processes for the API's twin replays: ``heavy_processes``, or when unset 1
        (0 with ``worker_in_process``, the embedded demo)."""
        if self.heavy_processes is not None:
            return self.heavy_processes
        return 0 if self.worker_in_process else 1


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
