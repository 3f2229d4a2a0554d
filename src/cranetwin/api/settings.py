"""Service settings, read from the environment (prefix ``CRANETWIN_``) when the app is built.

:class:`Settings` extends the settings every command shares (:class:`cranetwin.settings.Settings`:
``database_url``, ``live_bus_url`` and the ingest daemon's fields) with the HTTP service's.
"""

from __future__ import annotations

from pydantic import Field

from cranetwin.settings import Settings as CommonSettings


class Settings(CommonSettings):
    """Configuration of the HTTP service (and everything :class:`cranetwin.settings.Settings`
    holds).

    Built by :func:`cranetwin.api.create_app` (or the caller), never at import time. Every field can
    be set by an environment variable ``CRANETWIN_<FIELD>`` (e.g. ``CRANETWIN_DATABASE_URL``).
    """

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
        3600.0, gt=0, description="longest range of one analytics/report request [s] (replayed)")
    max_samples_limit: int = Field(10_000, ge=1, description="most samples per samples page")
    nominal_rate_hz: float = Field(100.0, gt=0, description="expected sensor sample rate [Hz]")
    twin_cache_entries: int = Field(64, ge=0, description="replay results kept in the LRU cache")
    live_rate_hz: float = Field(25.0, ge=1, le=50, description="live websocket frames per second")
    live_offline_s: float = Field(
        300.0, gt=0, description="a machine not seen for this long is 'offline' [s]")
    live_idle_s: float = Field(
        5.0, gt=0, description="a machine not seen for this long is 'idle' [s]")
    worker_enabled: bool = Field(True, description="run the background twin worker")
    warm_up: bool = Field(
        True, description="load the twin's compiled kernels and the 3D scene code in a background "
                          "thread at start (fast first machine page)")
    worker_window_s: float = Field(60.0, gt=0, description="twin worker window [s]")
    worker_interval_s: float = Field(1.0, gt=0, description="twin worker poll period [s]")
    worker_settle_s: float = Field(
        2.0, ge=0, description="a window is processed once samples this much past its end exist")
    worker_grid_hz: float = Field(100.0, gt=0, description="twin worker replay grid rate [Hz]")
    summary_interval_s: float = Field(1.0, gt=0, description="derived summary interval [s]")
    payload_lift_threshold_kg: float = Field(
        50.0, ge=0, description="payload above which the crane is holding a load (load count) [kg]")
