"""Machine keys for the ingest daemon: wire id → :class:`~cranetwin.protocol.MachineKey`, read from
storage, reloaded in the background (rate-limited) when an unknown wire id arrives."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

from cranetwin.ingest.config import layout_of
from cranetwin.protocol import Layout, MachineKey
from cranetwin.storage import Store


class MachineKeys:
    """The registered machines' keys, as the daemon's :class:`~cranetwin.protocol.Receiver`
    looks them up.

    Args:
        store: Where machines are registered.
        refresh_s: Least time between reloads after an unknown wire id [s].
        log_once: The daemon's log-once function ``(kind, exc, msg, *args)``.

    Attributes:
        bad_models: Wire id → machine id of machines whose model does not load (their datagrams
            are dropped as ``bad_model``).
    """

    def __init__(self, store: Store, refresh_s: float, log_once: Callable[..., None]) -> None:
        self.store = store
        self.refresh_s = refresh_s
        self._log_once = log_once
        self._keys: dict[int, MachineKey] = {}
        self.bad_models: dict[int, str] = {}
        self._layouts: dict[str, Layout] = {}
        self._loaded = 0.0
        self._reloading = threading.Lock()

    def __len__(self) -> int:
        return len(self._keys)

    def reload(self) -> None:
        """Read machine keys from storage (new registrations become valid). A machine whose
        model does not load is logged once; its datagrams are dropped as ``bad_model``.

        Raises:
            Exception: storage could not be read (the previous keys stay in use).
        """
        keys: dict[int, MachineKey] = {}
        bad: dict[int, str] = {}
        models = {m.machine_id: m.model for m in self.store.machines()}
        for wire_id, (machine_id, secret) in self.store.machine_keys().items():
            model = models.get(machine_id, "")
            layout = self._layouts.get(model)
            if layout is None:
                try:
                    layout = layout_of(model)
                except Exception as exc:  # MachineFileError, or a loader bug: never fatal
                    bad[wire_id] = machine_id
                    self._log_once(f"bad_model:{machine_id}", None,
                                   "machine %s: its model does not load, its datagrams are "
                                   "dropped as bad_model until it is fixed: %s",
                                   machine_id, " ".join(str(exc).split()))
                    continue
                self._layouts[model] = layout
            keys[wire_id] = MachineKey(wire_id, machine_id, secret, layout)
        self._keys = keys
        self.bad_models = bad
        self._loaded = time.monotonic()

    def _reload_in_background(self) -> None:
        """Reload keys in a thread of its own (the decoder never waits for the database)."""
        if time.monotonic() - self._loaded < self.refresh_s:
            return
        if not self._reloading.acquire(blocking=False):
            return
        self._loaded = time.monotonic()  # rate limit even if the reload fails

        def run() -> None:
            try:
                self.reload()
            except Exception as exc:
                self._log_once("reload_keys", exc, "could not reload machine keys: %s", exc)
            finally:
                self._reloading.release()

        threading.Thread(target=run, name="ingest-keys", daemon=True).start()

    def lookup(self, wire_id: int) -> MachineKey | None:
        """The key of ``wire_id``, or None (then a background reload is started, rate-limited)."""
        key = self._keys.get(wire_id)
        if key is None:
            self._reload_in_background()
        return key
