"""Warm-up at service start: the generic warm-up runs the twin, views and scene code, and the
per-machine warm-up caches each machine's smoothing choice (what short page windows reuse)."""

from __future__ import annotations

from cranetwin.api.services import Services
from cranetwin.model import load_machine
from cranetwin.service.warmup import start_warm_up, warm_up
from cranetwin.settings import Settings
from cranetwin.testing.blocks import kinematic_samples, tiled_blocks

T0 = 1795420800.0
MACHINE = load_machine("patu655")


def test_warm_up_runs_the_page_code_paths() -> None:
    assert warm_up() > 0.0
    done: list[bool] = []
    th = start_warm_up(then=lambda: done.append(True))
    th.join(60)
    assert not th.is_alive() and done == [True]


def test_warm_machines_caches_the_smoothing_choice_of_machines_with_data(sqlite_url: str) -> None:
    services = Services.open(Settings(database_url=sqlite_url, worker_in_process=False,
                                      warm_up=False))
    store = services.backend.store
    store.add_machine("with-data", wire_id=1, secret=b"k" * 32)
    store.add_machine("empty", wire_id=2, secret=b"k" * 32)
    base = kinematic_samples(MACHINE, 120.0)
    store.write_blocks(list(tiled_blocks("with-data", MACHINE, T0, 40.0, 1.0, base=base,
                                         origin_s=T0)))
    assert services.fleet.warm_machines() == 1
    assert [k[0] for k in services.fleet.replayer._choices] == ["with-data"]
    services.backend.close()
