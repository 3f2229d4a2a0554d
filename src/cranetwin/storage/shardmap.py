"""The partition map of the shards: which database holds which machine partitions.

:class:`ShardMap` maps each of P machine partitions
(:func:`cranetwin.storage.sharding.partition_of`) to a database URL; :class:`StoreSpec` is
where a process stores (one URL or a map), built from the settings by :func:`store_spec` and
opened by :func:`cranetwin.storage.shards.open_store`.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

from cranetwin.errors import StorageError
from cranetwin.storage.engine import display_url
from cranetwin.storage.sharding import partition_of


class ShardMapError(StorageError):
    """The partition map of the shards is malformed or does not cover every partition."""


@dataclass(frozen=True)
class ShardMap:
    """Machine partition → shard.

    Attributes:
        partitions: Number of machine partitions P.
        urls: The shards' database URLs (distinct), shard i at ``urls[i]``.
        owner: ``owner[p]`` is the shard of partition p (length P).
    """

    partitions: int
    urls: tuple[str, ...]
    owner: tuple[int, ...]

    @classmethod
    def parse(cls, spec: Mapping[str, str], partitions: int) -> ShardMap:
        """A map from ``{"0-7": url_a, "8-15": url_b}`` (ranges or single partitions as keys;
        one URL may take several ranges).

        Raises:
            ShardMapError: A key is not ``I`` or ``I-J`` within 0..P−1, ranges overlap, or a
                partition has no shard (messages never show a password).
        """
        if partitions < 1:
            raise ShardMapError(f"shard partitions must be ≥ 1, not {partitions}")
        urls: list[str] = []
        owner: list[int | None] = [None] * partitions
        for key, url in spec.items():
            lo, _, hi = str(key).strip().partition("-")
            if not lo.strip().isdigit() or (hi and not hi.strip().isdigit()):
                raise ShardMapError(f"shard map key {key!r}: expected a partition I or a range "
                                    "I-J, e.g. 0-7")
            a, b = int(lo), int(hi or lo)
            if a > b or b >= partitions:
                raise ShardMapError(f"shard map key {key!r}: partitions are 0..{partitions - 1}")
            if url not in urls:
                urls.append(url)
            for p in range(a, b + 1):
                if owner[p] is not None:
                    raise ShardMapError(f"partition {p} is in two ranges of the shard map")
                owner[p] = urls.index(url)
        missing = [p for p, o in enumerate(owner) if o is None]
        if missing:
            raise ShardMapError(f"partitions {_ranges(missing)} of 0..{partitions - 1} have no "
                                "shard in the shard map")
        return cls(partitions, tuple(urls), tuple(o for o in owner if o is not None))

    def shard_of(self, machine_id: str) -> int:
        """The shard index of a machine."""
        return self.owner[partition_of(machine_id, self.partitions)]

    def partitions_of(self, shard: int) -> list[int]:
        """The partitions shard ``shard`` holds."""
        return [p for p, o in enumerate(self.owner) if o == shard]

    def describe(self) -> list[str]:
        """One line per shard, ``partitions → URL`` with the password hidden."""
        return [f"{_ranges(self.partitions_of(i))} → {display_url(u)}"
                for i, u in enumerate(self.urls)]


def _ranges(ps: Sequence[int]) -> str:
    out: list[str] = []
    for p in ps:
        if out and out[-1].split("-")[-1] == str(p - 1):
            out[-1] = f"{out[-1].split('-')[0]}-{p}"
        else:
            out.append(str(p))
    return ",".join(out)


@dataclass(frozen=True)
class StoreSpec:
    """Where a process stores: one database URL, or a shard map (then ``url`` is unused).

    Attributes:
        url: The database URL without shards.
        shards: ``((range, url), …)`` of the shard map (see :meth:`ShardMap.parse`); empty:
            no sharding.
        partitions: Machine partitions P of the shard map.
    """

    url: str
    shards: tuple[tuple[str, str], ...] = ()
    partitions: int = 16

    @classmethod
    def of(cls, url: str, shards: Mapping[str, str] | None = None,
           partitions: int = 16) -> StoreSpec:
        """From the settings' ``database_url``, ``storage_shards``, ``storage_shard_partitions``."""
        return cls(url, tuple(sorted((shards or {}).items())), partitions)

    def shard_map(self) -> ShardMap | None:
        """The parsed map, or None without shards.

        Raises:
            ShardMapError: The map is invalid.
        """
        return ShardMap.parse(dict(self.shards), self.partitions) if self.shards else None

    def to_json(self) -> dict[str, Any]:
        """A JSON object for a child process (:meth:`from_json` reads it)."""
        return {"url": self.url, "shards": [list(s) for s in self.shards],
                "partitions": self.partitions}

    @classmethod
    def from_json(cls, obj: str | Mapping[str, Any]) -> StoreSpec:
        """From :meth:`to_json`'s object, or a bare URL."""
        if isinstance(obj, str):
            return cls(obj)
        return cls(str(obj["url"]), tuple((str(k), str(u)) for k, u in obj["shards"]),
                   int(obj["partitions"]))

    def display(self) -> str:
        """For a log line: the URL, or the shards, with passwords hidden."""
        m = self.shard_map()
        return display_url(self.url) if m is None else "shards " + "; ".join(m.describe())


class ShardSettings(Protocol):
    """The fields of :class:`cranetwin.settings.Settings` that say where to store."""

    @property
    def database_url(self) -> str: ...

    @property
    def storage_shards(self) -> dict[str, str] | None: ...

    @property
    def storage_shard_partitions(self) -> int: ...


def store_spec(settings: ShardSettings) -> StoreSpec:
    """Where every process stores: ``database_url``, or the shard map if ``storage_shards`` is
    set (validated here).

    Raises:
        ShardMapError: The shard map is invalid.
    """
    spec = StoreSpec.of(settings.database_url, settings.storage_shards,
                        settings.storage_shard_partitions)
    spec.shard_map()
    return spec
