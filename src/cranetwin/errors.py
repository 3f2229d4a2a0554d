"""The one exception tree of cranetwin.

Every package raises a subclass of :class:`CraneTwinError`; the edges (CLI, ingest daemon, API)
translate them once into an exit message, a dropped-and-counted datagram or a 4xx problem JSON::

    CraneTwinError
    ├── ModelError              machine description invalid or inconsistent
    │   └── MachineFileError    a machine file failed to load (lists every problem)
    ├── PhysicsError            state outside the kinematic range of the machine
    ├── SignalError             bad sample arrays (shape, order, too few knots)
    ├── SimulationError         bad scenario or unstable integration
    │   └── ScenarioError       scenario file invalid
    ├── TwinError               replay input unusable
    ├── ProtocolError           datagram malformed, forged or replayed
    ├── StorageError            database problems
    ├── AnalyticsError          analytics input unusable
    ├── ReportError             export failed
    └── MissingExtraError       an optional dependency is not installed (names the extra)
"""

from __future__ import annotations


class CraneTwinError(Exception):
    """Base of every error cranetwin raises on purpose."""


class ModelError(CraneTwinError):
    """A machine description is invalid or inconsistent."""


class MachineFileError(ModelError):
    """A machine file could not be loaded.

    Attributes:
        source: File path or built-in name that failed.
        problems: One ``"field.path: message"`` string per problem found.
    """

    def __init__(self, source: str, problems: list[str]) -> None:
        self.source = source
        self.problems = list(problems)
        lines = "\n".join(f"  - {p}" for p in self.problems)
        super().__init__(f"{source}: {len(self.problems)} problem(s)\n{lines}")


class PhysicsError(CraneTwinError):
    """Input state outside the machine's kinematic range or of the wrong shape."""


class SignalError(CraneTwinError):
    """Sample arrays unusable for signal processing."""


class SimulationError(CraneTwinError):
    """Simulation could not run (bad input or unstable integration)."""


class ScenarioError(SimulationError):
    """A scenario file or built-in scenario specification is invalid."""


class TwinError(CraneTwinError):
    """Replay input unusable."""


class ProtocolError(CraneTwinError):
    """A datagram is malformed, forged, replayed or of an unknown version."""


class StorageError(CraneTwinError):
    """A database operation failed."""


class StorageUnavailableError(StorageError):
    """The database cannot be reached or used right now (server down, connection lost, locked
    for longer than the busy timeout); nothing of the failed call was committed. Retry later,
    with backoff: the same call succeeds once the database is back."""


class AnalyticsError(CraneTwinError):
    """Analytics input unusable."""


class ReportError(CraneTwinError):
    """An export could not be produced."""


class MissingExtraError(CraneTwinError):
    """A feature needs an optional dependency that is not installed.

    Raised where the optional module is imported (lazily), ``from`` the ``ImportError``::

        try:
            import reportlab
        except ImportError as exc:
            raise MissingExtraError("reports", "PDF reports") from exc

    Attributes:
        extra: Name of the ``cranetwin[...]`` extra that installs it.
        feature: What needs it ("PDF reports", "the Redis live bus").
    """

    def __init__(self, extra: str, feature: str) -> None:
        self.extra = extra
        self.feature = feature
        super().__init__(f"{feature}: install the {extra!r} extra: "
                         f"pip install 'cranetwin[{extra}]'")
