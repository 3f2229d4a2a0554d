"""Synthetic data with known truth, for tests, benchmarks, previews and the demo — one place.

Nothing outside tests, benchmarks, the web preview and warm-up may treat these as measurements:

* :mod:`cranetwin.testing.recordings` — sensor recordings of the crane with exactly known joint
  motion, forces and payload (inverse dynamics through Eq. 1–2): checks the twin's algebra.
* :mod:`cranetwin.testing.blocks` — exact kinematic samples of a periodic motion with a known
  payload schedule, and stored-block tiling of any recording over any duration (API tests,
  benchmarks, warm-up).
* :mod:`cranetwin.testing.histories` — closed-form load histories of shifts of log loading,
  with injectable misuse (analytics tests, ``cranetwin report --demo``, the analytics benchmark).
* :mod:`cranetwin.testing.views` — scripted crane motion in the API's JSON shapes (web preview
  and web tests; forces are a quasi-static estimate, not physics).
* :mod:`cranetwin.testing.indep_crane`, :mod:`~cranetwin.testing.indep_sim`,
  :mod:`~cranetwin.testing.indep_scenarios` — a PATU 655 simulated without any of the project's
  physics (Lagrangian, own geometry and hydraulics; numpy + scipy): the twin checked on data it
  did not make (``tests/indep_check.py``, docs/ACCURACY.md).

Each module is imported on its own (``from cranetwin.testing.blocks import tiled_blocks``); this
package imports none of them, so importing it costs nothing.
"""
